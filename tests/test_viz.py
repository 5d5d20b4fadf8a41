"""Render kernels: exact pixels on tiny analytic grids and point sets."""

from __future__ import annotations

import numpy as np

from tasks import conventions as C
from tasks import viz


def test_bev_shows_highest_voxel_with_x_up_and_y_left():
    occ = np.full((4, 3, 5), C.FREE, np.uint8)
    occ[0, 0, 0] = C.ROAD  # x index 0 (nearest), y index 0 (rightmost): bottom-right pixel
    occ[0, 0, 4] = C.CAR  # above the road in the same column: the car is shown
    occ[3, 2, 1] = C.PEDESTRIAN  # far, left: top-left pixel
    inst = np.zeros_like(occ, dtype=np.uint16)
    inst[3, 2, 1] = 7
    img = viz.bev_image(occ, inst, scale=2)
    assert img.shape == (8, 6, 3) and img.dtype == np.uint8
    assert np.array_equal(img[7, 5], C.CLASS_COLORS[C.CAR])  # top layer: full brightness
    assert np.array_equal(
        img[0, 0], (viz.instance_colors(np.array([7]))[0] * (0.55 + 0.45 * 2 / 5)).astype(np.uint8)
    )
    assert np.array_equal(img[0, 5], C.CLASS_COLORS[C.FREE])


def test_bev_marks_unseen_columns_unknown():
    occ = np.full((2, 2, 2), C.FREE, np.uint8)
    visible = np.zeros((2, 2, 2), bool)
    visible[0, 0, 0] = True
    img = viz.bev_image(occ, None, visible, scale=1)
    assert np.array_equal(img[1, 1], C.CLASS_COLORS[C.FREE])  # seen and free
    assert np.array_equal(img[0, 0], C.UNKNOWN_COLOR)


def test_instance_colours_are_stable_and_distinct():
    a = viz.instance_colors(np.arange(1, 9))
    assert np.array_equal(a, viz.instance_colors(np.arange(1, 9)))
    assert len({tuple(c) for c in a}) == 8


def test_point_projects_to_its_pixel_coloured_by_depth():
    K = np.array([[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]  # lidar x forward -> camera z
    pts = np.array([[10.0, 0.0, 0.0], [5.0, -0.5, 0.2], [0.0, 0.0, 0.0]], np.float32)
    img = viz.draw_points(np.zeros((80, 100, 3), np.uint8), pts, K, T, max_depth=30.0, radius=1)
    assert np.array_equal(img[40, 50], viz.depth_colors(np.array([10.0]))[0])
    assert np.array_equal(img[36, 60], viz.depth_colors(np.array([5.0]))[0])
    assert np.count_nonzero(img.any(axis=2)) == 2  # the zero (no-return) point is skipped


def test_side_by_side_resizes_to_one_height():
    a = np.zeros((10, 20, 3), np.uint8)
    b = np.full((40, 40, 3), 9, np.uint8)
    out = viz.side_by_side([a, b], height=20, gap=2)
    assert out.shape == (20, 40 + 2 + 20, 3)
    assert (out[:, :40] == 0).all() and (out[:, 40:42] == 255).all() and (out[:, 42:] == 9).all()
