"""Visible fraction of instances in a voxel grid from a camera (nuScenes visibility, issue 19)."""

from __future__ import annotations

import numpy as np
import pytest

from storage.export.nuscenes import visibility_token
from tasks.occupancy.instance_visibility import visible_fractions

# camera at the base origin looking along +x: image u to the right (base -y), v down (base -z)
T_BASE_FROM_CAM = np.eye(4)
T_BASE_FROM_CAM[:3, :3] = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]
K = np.array([[400.0, 0.0, 199.5], [0.0, 400.0, 199.5], [0.0, 0.0, 1.0]])
W = H = 400
LO, VS, SHAPE = np.array([0.0, -4.0, -4.0]), 0.2, (50, 40, 40)


def _grids():
    return np.zeros(SHAPE, bool), np.zeros(SHAPE, np.uint16)


def _frac(occ, inst, ids):
    return visible_fractions(LO, VS, occ, inst, ids, K, W, H, T_BASE_FROM_CAM)


def test_alone_in_view_is_fully_visible_and_absent_ids_are_zero():
    occ, inst = _grids()
    inst[25, 18:22, 15:25] = 1  # a 0.8 x 2.0 m person 5 m ahead, centred
    inst[26:28, 18:22, 15:25] = 1  # its depth (self-occlusion does not count)
    occ[40, :, :] = True  # a wall behind it
    np.testing.assert_array_equal(_frac(occ, inst, [1, 2]), [1.0, 0.0])


def test_hidden_behind_a_wall_and_behind_the_camera_is_zero():
    occ, inst = _grids()
    inst[30, 18:22, 15:25] = 1
    occ[10, 10:30, 5:35] = True  # a wall 2 m ahead covering it completely
    assert _frac(occ, inst, [1])[0] == 0.0
    T = T_BASE_FROM_CAM.copy()
    T[0, 3] = 8.0  # the camera moved past it: it is behind the camera
    occ[:] = False
    assert visible_fractions(LO, VS, occ, inst, [1], K, W, H, T)[0] == 0.0


def test_half_occluded_and_half_outside_the_image():
    occ, inst = _grids()
    # person 1: 6.1 m ahead, y in [-0.4, 0.4); a pole 3.1 m ahead covering y >= 0 (half of it, by projection)
    inst[30, 18:22, 15:25] = 1
    occ[15, 20:30, 0:40] = True
    # person 2: y in [-2.6, -1.8), inside the image (its right edge is at y = -(W / 2) * 6.1 / 400 = -3.05)
    inst[30, 7:11, 15:25] = 2
    f = _frac(occ, inst, [1, 2])
    assert f[0] == pytest.approx(0.5, abs=0.05)
    assert f[1] == 1.0
    inst[inst == 2] = 0
    inst[30, 3:11, 15:25] = 2  # y in [-3.4, -1.8): 0.35 m of 1.6 m beyond the edge
    assert _frac(occ, inst, [2])[0] == pytest.approx(1.25 / 1.6, abs=0.05)


def test_visibility_bins():
    assert [visibility_token(f) for f in (0.0, 0.39, 0.4, 0.59, 0.6, 0.79, 0.8, 1.0)] == [
        "1",
        "1",
        "2",
        "2",
        "3",
        "3",
        "4",
        "4",
    ]


def test_shape_mismatch_is_an_error():
    occ, inst = _grids()
    with pytest.raises(ValueError, match="same"):
        visible_fractions(LO, VS, occ[:-1], inst, [1], K, W, H, T_BASE_FROM_CAM)


def test_a_person_beyond_the_grid_is_drawn_from_its_box():
    from tasks.occupancy.instance_visibility import box_lattice

    pts = box_lattice([12.0, 0.0, 0.0], [0.4, 0.6, 1.8], 0.3, VS)
    assert pts.shape == (2 * 3 * 9, 3)
    np.testing.assert_allclose(pts.mean(0), [12.0, 0.0, 0.0], atol=1e-12)
    occ, inst = _grids()
    assert (
        visible_fractions(LO, VS, occ, inst, [5], K, W, H, T_BASE_FROM_CAM, outside={5: pts})[0]
        == 1.0
    )
    occ[45, 15:25, 10:30] = True  # a wall at the grid's far end hides it
    assert (
        visible_fractions(LO, VS, occ, inst, [5], K, W, H, T_BASE_FROM_CAM, outside={5: pts})[0]
        == 0.0
    )
    inst[25, 18:22, 15:25] = 5  # with voxels in the grid, its box points are not used
    assert (
        visible_fractions(LO, VS, occ, inst, [5], K, W, H, T_BASE_FROM_CAM, outside={5: pts})[0]
        == 1.0
    )
