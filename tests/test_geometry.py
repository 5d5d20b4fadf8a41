"""tasks/geometry.py: rigid transforms, points in oriented boxes, box IoU and matching, on shapes
whose answers are known by hand, and the box test against its definition R^T (p - c)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tasks.geometry import (
    box_iou,
    make_transform,
    match_boxes,
    points_in_boxes,
    rot_x,
    rot_z,
    transform_points,
    yaw_rotations,
)


def test_transform_points_is_float64_whatever_the_input():
    T = make_transform(rot_z(np.pi / 2), [1.0, 2.0, 3.0])
    p32 = np.array([[1.0, 0.0, 0.0], [0.0, 0.5, -1.0]], np.float32)
    out = transform_points(T, p32)
    assert out.dtype == np.float64
    np.testing.assert_allclose(out, [[1.0, 3.0, 3.0], [0.5, 2.0, 2.0]], atol=1e-12)
    # float32 points are widened exactly first: the same bytes as float64 input
    assert transform_points(T, p32.astype(np.float64)).tobytes() == out.tobytes()
    assert transform_points(T, np.zeros((0, 3))).shape == (0, 3)


def test_rotations_are_right_handed():
    np.testing.assert_allclose(rot_z(np.pi / 2) @ [1.0, 0, 0], [0, 1.0, 0], atol=1e-15)
    np.testing.assert_allclose(rot_x(np.pi / 2) @ [0, 1.0, 0], [0, 0, 1.0], atol=1e-15)
    yaws = np.array([0.3, -2.0, np.pi])
    assert np.array_equal(yaw_rotations(yaws), np.stack([rot_z(y) for y in yaws]))


def _yaw_boxes(points, boxes, margin_m=0.0):
    b = np.asarray(boxes, float)
    return points_in_boxes(points, b[:, :3], b[:, 3:6], yaw_rotations(b[:, 6]), margin_m=margin_m)


def test_points_in_yaw_boxes_by_hand():
    pts = np.array([[5, -1.5, 0], [5, 1, 0], [0.55, 0, 0], [0.0, 0.45, 0], [0.5, 0.5, 0]], float)
    box = np.array([[0, 0, 0, 1.0, 0.2, 2.0, 0.0]])
    assert _yaw_boxes(pts, box, 0.1).tolist() == [False, False, True, False, False]
    box[0, 6] = np.pi / 2  # now 1 m along y
    assert _yaw_boxes(pts, box).tolist() == [False, False, False, True, False]
    box[0, 6] = np.pi / 4  # along the diagonal: (0.5, 0.5) is 0.707 m along the box
    assert _yaw_boxes(pts, box).tolist() == [False] * 5
    # margin 0.25: half sizes 0.75 x 0.35; (0, 0.45) -> (0.32, 0.32) inside, (0.55, 0) -> (0.39, -0.39) not
    assert _yaw_boxes(pts, box, 0.25).tolist() == [False, False, False, True, True]


def test_points_in_boxes_bottom_slab_and_no_boxes():
    R = rot_z(np.pi / 2)
    pts = np.array(
        [
            [5.0, 0.9, 0.0],  # inside: l = 2 lies along y after the 90 deg yaw
            [5.9, 0.0, 0.0],  # outside: w = 0.5 along x
            [5.0, 0.0, -0.85],  # in the bottom 0.1 m (box z -0.9 .. 0.9): left out
            [5.0, 0.0, -0.75],  # above the slab
        ]
    )
    inside = points_in_boxes(pts, [[5.0, 0.0, 0.0]], [[2.0, 0.5, 1.8]], [R], bottom_exclude_m=0.1)
    assert inside.tolist() == [True, False, False, True]
    none = points_in_boxes(pts, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3, 3)))
    assert none.dtype == bool and none.tolist() == [False] * 4
    assert points_in_boxes(np.zeros((0, 3)), [[0, 0, 0]], [[1, 1, 1]], [np.eye(3)]).shape == (0,)
    with pytest.raises(ValueError, match="2 centers, 1 sizes"):
        points_in_boxes(pts, np.zeros((2, 3)), np.ones((1, 3)), np.stack([np.eye(3)] * 2))


def test_points_in_boxes_follows_its_definition_for_tilted_boxes():
    """Random roll / pitch / yaw boxes: inside exactly where |R^T (p - c)| <= half (margin
    added) and above the bottom slab, points in float32 as the readers give them."""
    rng = np.random.default_rng(7)
    centers = rng.uniform(-3, 3, (6, 3))
    sizes = rng.uniform(0.3, 2.5, (6, 3))
    R = Rotation.from_euler("zyx", rng.uniform(-np.pi, np.pi, (6, 3))).as_matrix()
    pts = rng.uniform(-5, 5, (20000, 3)).astype(np.float32)
    got = points_in_boxes(pts, centers, sizes, R, margin_m=0.05, bottom_exclude_m=0.2)
    want = np.zeros(len(pts), bool)
    for c, s, r in zip(centers, sizes, R):
        local = (pts.astype(np.float64) - c) @ r
        half = s / 2 + 0.05
        want |= np.all(np.abs(local) <= half, axis=1) & (local[:, 2] >= -half[2] + 0.2)
    assert 200 < want.sum() < len(pts) - 200  # both answers well represented
    assert np.array_equal(got, want)


def test_box_iou_by_hand():
    a = [[0, 0, 10, 10], [0, 0, 0, 0]]
    b = [[5, 0, 15, 10], [20, 20, 30, 30]]
    np.testing.assert_allclose(box_iou(a, b), [[50 / 150, 0.0], [0.0, 0.0]])
    assert box_iou(np.zeros((0, 4)), b).shape == (0, 2)


def test_hungarian_beats_greedy():
    gt = np.array([[0, 0, 10, 10], [4, 0, 14, 10]])
    det = np.array([[3, 0, 13, 10], [6, 0, 16, 10]])
    # IoU [[0.538, 0.25], [0.818, 0.667]]: greedy takes (1, 0) and leaves one pair; optimal has two
    gi, di = match_boxes(gt, det)
    assert gi.tolist() == [0, 1] and di.tolist() == [0, 1]
    # a pair under the threshold is never matched
    gi, di = match_boxes(gt, det, iou_threshold=0.9)
    assert gi.tolist() == [] and di.tolist() == []
