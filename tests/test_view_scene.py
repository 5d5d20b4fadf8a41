"""tasks/view: what the viewer draws (exact answers on small analytic grids) and the QA kernels."""

from __future__ import annotations

import numpy as np
import pytest

from tasks import conventions as C
from tasks.metrics.bev import DIFF_CORRECT, DIFF_EXTRA, DIFF_MISSED, DIFF_UNKNOWN, DIFF_WRONG_CLASS
from tasks.view import qa as Q
from tasks.view import scene as S


def test_surface_of_a_solid_cube_and_of_a_region_cut_by_the_border():
    keep = np.zeros((9, 9, 9), bool)
    keep[2:7, 2:7, 2:7] = True  # 5^3 cube: 3^3 inside
    assert S.surface_voxels(keep).sum() == 125 - 27
    assert not S.surface_voxels(keep)[3:6, 3:6, 3:6].any()
    full = np.ones((3, 3, 3), bool)
    assert S.surface_voxels(full, border_exposed=True).sum() == 26  # all but the centre
    assert S.surface_voxels(full, border_exposed=False).sum() == 0  # the border is no surface


def test_merge_blocks_takes_the_majority_and_the_lowest_code_on_ties():
    index = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0], [3, 0, 0]])
    codes = np.array([4, 4, 0, 5, 0], np.uint8)
    blocks, got = S.merge_blocks(index, codes, 2, (4, 2, 2))
    np.testing.assert_array_equal(blocks, [[0, 0, 0], [1, 0, 0]])
    np.testing.assert_array_equal(got, [4, 0])  # 2 road vs 1 pedestrian; a 5 / 0 tie -> 0


def test_class_layer_keeps_surfaces_and_merges_into_blocks_beyond_the_limit():
    sem = np.full((40, 40, 6), C.FREE, np.uint8)
    sem[:, :, 0] = C.ROAD
    sem[10:12, 10:12, 1:5] = C.PEDESTRIAN  # a 2x2x4 column: every voxel on its surface
    layer = S.class_layer(sem, (0.0, -2.0, -1.0), 0.1)
    assert layer.block == 1 and len(layer) == 40 * 40 + 16 == layer.surface == layer.selected
    np.testing.assert_allclose(layer.centers.min(0), [0.05, -1.95, -0.95], atol=1e-6)
    ped = layer.codes == C.PEDESTRIAN
    assert ped.sum() == 16 and (layer.colors[ped] == C.CLASS_COLORS[C.PEDESTRIAN]).all()
    small = S.class_layer(sem, (0.0, -2.0, -1.0), 0.1, max_voxels=500)
    assert small.block == 2 and small.size_m == pytest.approx(0.2)
    # the plane in 2x2 blocks; the column (z 1..4) adds the blocks of z 2-3 and 4-5
    assert len(small) == 20 * 20 + 2
    # the block of z 0-1 under the column holds 4 road and 4 pedestrian voxels: a tie, pedestrian
    assert (small.codes == C.PEDESTRIAN).sum() == 3
    # a mask keeps only the voxels inside it
    mask = np.zeros_like(sem)
    mask[:20] = 1
    assert len(S.class_layer(sem, (0, 0, 0), 0.1, mask=mask)) == 20 * 40 + 16


def test_unknown_layer_is_the_face_of_unknown_space_towards_observed_space():
    sem = np.full((6, 6, 6), C.FREE, np.uint8)
    mask = np.zeros((6, 6, 6), np.uint8)
    mask[:3] = 1  # observed near half; unknown beyond x = 3
    layer = S.unknown_layer(sem, mask, (0, 0, 0), 1.0)
    assert len(layer) == 36 and np.allclose(layer.centers[:, 0], 3.5)
    assert (layer.colors == C.UNKNOWN_COLOR).all()


def test_difference_codes_voxel_by_voxel():
    gt = np.full((5, 1, 1), C.FREE, np.uint8)
    pred = gt.copy()
    gt[0], pred[0] = C.ROAD, C.ROAD  # correct
    gt[1], pred[1] = C.ROAD, C.TERRAIN  # wrong class
    gt[2] = C.PEDESTRIAN  # missed
    pred[3] = C.CAR  # extra
    codes = S.difference_codes(pred, gt)
    assert codes.ravel().tolist() == [DIFF_CORRECT, DIFF_WRONG_CLASS, DIFF_MISSED, DIFF_EXTRA, 0]
    mask = np.ones_like(gt)
    mask[1] = 0
    assert S.difference_codes(pred, gt, mask)[1, 0, 0] == DIFF_UNKNOWN
    layer = S.difference_layer(pred, gt, (0, 0, 0), 1.0)
    assert sorted(layer.codes.tolist()) == [1, 2, 3, 4]
    np.testing.assert_array_equal(layer.colors, S.DIFF_COLORS[layer.codes])


def test_box_segments_are_the_edges_along_the_heading():
    segs = S.box_segments([[1.0, 2.0, 0.5]], [[2.0, 1.0, 3.0]], [np.pi / 2])
    assert segs.shape == (12, 2, 3)
    # l = 2 along the heading (+y after a quarter turn), w = 1 across it, h = 3: four edges each
    lengths = np.sort(np.linalg.norm(segs[:, 1] - segs[:, 0], axis=1))
    np.testing.assert_allclose(lengths, [1.0] * 4 + [2.0] * 4 + [3.0] * 4, atol=1e-6)
    along = segs[:, 1] - segs[:, 0]
    long_edges = along[np.isclose(np.linalg.norm(along, axis=1), 2.0)]
    np.testing.assert_allclose(np.abs(long_edges), [[0.0, 2.0, 0.0]] * 4, atol=1e-6)
    np.testing.assert_allclose(segs.reshape(-1, 3).mean(0), [1.0, 2.0, 0.5], atol=1e-6)
    with pytest.raises(S.SceneError):
        S.box_segments([[0, 0, 0]] * 2, [[1, 1, 1]], [0, 0])


def test_velocity_arrows_per_voxel_and_per_block_on_fine_grids():
    sem = np.full((4, 4, 4), C.FREE, np.uint8)
    vel = np.zeros((4, 4, 4, 2), np.float16)
    sem[1, 1, 1], vel[1, 1, 1] = C.PEDESTRIAN, (1.0, -0.5)
    sem[2, 2, 2] = C.PEDESTRIAN  # standing: no arrow
    arrows, speed = S.velocity_arrows(sem, vel, (0, 0, 0), 0.2, seconds=0.5)
    np.testing.assert_allclose(arrows[0], [[0.3, 0.3, 0.3], [0.8, 0.05, 0.3]], atol=1e-6)
    np.testing.assert_allclose(speed, [np.hypot(1.0, 0.5)], rtol=1e-3)
    fine = np.full((20, 20, 10), C.FREE, np.uint8)
    fvel = np.zeros((20, 20, 10, 2), np.float16)
    fine[:, :10, :], fvel[:, :10, :] = C.PEDESTRIAN, (2.0, 0.0)  # 0.4 x 0.2 m at 0.02 m
    arrows, _ = S.velocity_arrows(fine, fvel, (0, 0, 0), 0.02)
    assert len(arrows) == 2  # one per 0.2 m block (10 x 10 x 10 voxels)
    np.testing.assert_allclose(arrows[:, 1, 0] - arrows[:, 0, 0], 1.0, rtol=1e-3)


def _camera_pose() -> np.ndarray:
    # a camera 0.5 m forward, 1 m up, looking along base +x (z_cam = x_base, x_cam = -y_base)
    T = np.eye(4)
    T[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], np.float64)
    T[:3, 3] = (0.5, 0.0, 1.0)
    return T


def test_camera_view_and_a_click_ray_back_to_the_pixel():
    K = np.array([[700.0, 0, 600.0], [0, 710.0, 520.0], [0, 0, 1]])
    T = _camera_pose()
    cam = S.camera_view(K, 1224, 1024, T, depth_m=2.0)
    assert cam.fov_y == pytest.approx(2 * np.arctan(1024 / (2 * 710.0)))
    assert cam.image_size_m == pytest.approx((1224 / 700 * 2, 1024 / 710 * 2))
    R = np.array(T[:3, :3])
    q = cam.wxyz  # the quaternion is the pose's rotation
    w, x, y, z = q
    Rq = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    np.testing.assert_allclose(Rq, R, atol=1e-12)
    # a reviewer's eye somewhere behind, clicking the point of pixel (900, 300) on the image plane
    u, v = 900.0, 300.0
    p_cam = np.array([(u - 600) / 700 * 2.0, (v - 520) / 710 * 2.0, 2.0])
    p = R @ p_cam + T[:3, 3]
    eye = np.array([-3.0, 1.5, 4.0])
    got = S.pixel_from_ray(eye, p - eye, K, T, 2.0)
    assert got == pytest.approx((u, v), abs=1e-6)
    assert S.pixel_from_ray(eye, eye - p, K, T, 2.0) is None  # pointing away from the plane
    # the image's centre as drawn is the image centre's pixel
    got = S.pixel_from_ray(cam.image_center + [-1, 0, 0], [1, 0, 0], K, T, 2.0)
    assert got == pytest.approx((612.0, 512.0), abs=1e-6)


def test_lidar_points_thin_and_move_to_base():
    pts = np.zeros((1000, 3), np.float32)
    pts[:800, 0] = np.arange(1, 801)
    T = np.eye(4)
    T[2, 3] = 0.8
    base, cols = S.lidar_points(pts, T, max_points=100)
    assert len(base) == 100 and np.allclose(base[:, 2], 0.8) and base[1, 0] == 9.0
    assert cols.shape == (100, 3) and cols.dtype == np.uint8
    # only the points around the grid: a sweep reaches 100 m
    near, _ = S.lidar_points(pts, T, 1000, box_min=(0, -1, 0), box_max=(50.5, 1, 1))
    assert len(near) == 50 and near[:, 0].max() == 50.0


def test_draw_boxes_2d_outlines_only():
    img = np.zeros((20, 30, 3), np.uint8)
    out = S.draw_boxes_2d(img, [[5, 4, 15, 12]], [[255, 0, 0]], width=1)
    assert (out[4, 5:16] == [255, 0, 0]).all() and (out[12, 5:16] == [255, 0, 0]).all()
    assert (out[4:13, 5] == [255, 0, 0]).all() and (out[8, 10] == 0).all()
    assert (img == 0).all()  # a copy


def test_qa_conditions_sample_and_counts():
    assert Q.frame_condition(True, "crowded", 9, 5) == "night"
    assert Q.frame_condition(False, "uncrowded", 9, 5) == "uncrowded"
    assert Q.frame_condition(False, None, 5, 5) == "crowded"
    assert Q.frame_condition(False, None, 4, 5) == "uncrowded"
    conds = ["crowded"] * 10 + ["night"] * 3 + ["uncrowded"] * 7
    pick = Q.sample_frames(conds, 4)
    assert [conds[i] for i in pick].count("crowded") == 4 and pick[:4] == [0, 3, 6, 9]
    assert [i for i in pick if conds[i] == "night"] == [10, 11, 12]  # fewer than asked: all
    assert pick == sorted(pick) and Q.sample_frames(conds, 4) == pick
    counts = Q.counts_by_condition(
        ["crowded", "crowded", "crowded", "night", "night", "night"],
        ["T", "T", "W", "T", "M_vis", None],
    )
    assert list(counts) == ["crowded", "night", "all"]
    assert (counts["crowded"].T, counts["crowded"].W) == (2, 1)
    assert counts["night"].recall == pytest.approx(0.5)
    assert counts["all"].T == 3


def test_qa_marks_must_be_a_whole_verdict():
    ok = [Q.Mark("T", 3), Q.Mark("W", 5), Q.Mark("M_occ", None, 10.0, 20.0)]
    Q.check_marks("frame 1", [3, 5], ok, (100, 100))
    with pytest.raises(Q.QAMarkError, match=r"\[5\] not marked"):
        Q.check_marks("frame 1", [3, 5], ok[:1], (100, 100))
    with pytest.raises(Q.QAMarkError, match="track 7 is not labelled"):
        Q.check_marks("frame 1", [3, 5], [*ok, Q.Mark("T", 7)])
    with pytest.raises(Q.QAMarkError, match="marked twice"):
        Q.check_marks("frame 1", [3, 5], [*ok, Q.Mark("W", 3)])
    with pytest.raises(Q.QAMarkError, match="outside the 100 x 100 image"):
        Q.check_marks("frame 1", [], [Q.Mark("M_vis", None, 100.0, 5.0)], (100, 100))
    with pytest.raises(Q.QAMarkError, match="needs its click"):
        Q.check_marks("frame 1", [], [Q.Mark("M_vis")])
    with pytest.raises(Q.QAMarkError, match="mark kind 'X'"):
        Q.check_marks("frame 1", [], [Q.Mark("X")])
