"""The static map resampled into a frame's local grid (tasks/occupancy/resample.py)."""

from __future__ import annotations

import numpy as np

from tasks.conventions import OTHER_STRUCTURE, ROAD, UNLABELED, VEGETATION
from tasks.occupancy.grid import GridSpec
from tasks.occupancy.resample import static_in_grid, static_labels_at_cells
from tasks.occupancy.static_map import NUM_OCCUPIED_CLASSES, StaticMap, lookup_labels

SPEC = GridSpec((0.4, -1.0, -0.6), (3.0, 1.0, 1.0), 0.2)  # 13 x 10 x 8


def _pose(yaw: float, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
    T[:3, 3] = t
    return T


def _map(voxel_size_m: float, seed: int = 0) -> StaticMap:
    rng = np.random.default_rng(seed)
    keys = np.unique(rng.integers([-5, -25, -8], [60, 25, 8], (20000, 3)), axis=0)
    labels = rng.choice(np.array([ROAD, OTHER_STRUCTURE, VEGETATION], np.uint8), len(keys))
    return StaticMap(
        voxel_size_m, keys, labels, np.zeros((len(keys), NUM_OCCUPIED_CLASSES), np.uint16), 0
    )


def test_cells_take_the_label_of_the_map_voxel_under_their_centre():
    """A yawed, shifted pose and a coarser, offset map: every cell against a direct lookup of its
    centre; the points are the labelled cells' centres in the world frame, in C order."""
    smap = _map(0.25)
    T = _pose(0.7, (1.13, -0.41, 0.07))
    centres = SPEC.centers().reshape(-1, 3).astype(np.float64)
    world = (centres @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
    expected = lookup_labels(smap, world)
    assert 50 < (expected != UNLABELED).sum() < len(expected) - 50  # both kinds of cell
    np.testing.assert_array_equal(static_labels_at_cells(smap, SPEC, T).reshape(-1), expected)
    pts, lab = static_in_grid(smap, SPEC, T, reach_m=12.0)
    hit = expected != UNLABELED
    np.testing.assert_array_equal(lab, expected[hit])
    np.testing.assert_allclose(pts, world[hit], atol=1e-6)
    assert pts.dtype == np.float32 and lab.dtype == np.uint8


def test_finer_map_is_pushed_as_points_and_empty_map_gives_nothing():
    fine = _map(0.1, seed=1)
    T = _pose(0.0, (0.0, 0.0, 0.0))
    pts, lab = static_in_grid(fine, SPEC, T, reach_m=3.0)
    near = fine.crop(T[:3, 3], 3.0)
    assert len(pts) == len(near.keys) and set(lab.tolist()) <= {ROAD, OTHER_STRUCTURE, VEGETATION}
    empty = StaticMap(
        0.2,
        np.zeros((0, 3), np.int64),
        np.zeros(0, np.uint8),
        np.zeros((0, NUM_OCCUPIED_CLASSES), np.uint16),
        0,
    )
    pts, lab = static_in_grid(empty, SPEC, T, reach_m=3.0)
    assert pts.shape == (0, 3) and lab.shape == (0,)


def test_lookup_far_outside_the_key_range_is_unlabelled():
    smap = _map(0.2)
    far = np.array([[1e6, 0.0, 0.0], [0.0, -1e7, 0.0]])  # keys beyond +-2^20
    assert lookup_labels(smap, far).tolist() == [UNLABELED, UNLABELED]
