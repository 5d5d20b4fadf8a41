"""Bird's-eye summaries of class grids for the report's BEV figures (prediction, GT, difference).

Arrays stay in grid order [x, y]; the report flips them so that x (forward) points up and
y (left) points left.
"""

from __future__ import annotations

import numpy as np

from tasks import conventions as C
from tasks.metrics._common import check_label_grid, check_mask

#: codes of :func:`bev_difference`
DIFF_FREE, DIFF_CORRECT, DIFF_WRONG_CLASS, DIFF_MISSED, DIFF_EXTRA, DIFF_UNKNOWN = 0, 1, 2, 3, 4, 5
DIFF_NAMES: tuple[str, ...] = (
    "free in both",
    "correct",
    "wrong class",
    "missed",
    "extra",
    "unknown",
)
#: RGB colours of the DIFF_* codes, shared by the report's BEV figure and the 3D viewer
DIFF_COLORS = np.array(
    [
        [255, 255, 255],  # free in both
        [44, 160, 44],  # correct: green
        [255, 165, 0],  # wrong class: orange
        [31, 90, 220],  # missed: blue
        [220, 30, 30],  # extra: red
        [200, 200, 200],  # unknown: light grey
    ],
    dtype=np.uint8,
)


def bev_top_labels(grid: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Class of the highest occupied (and visible) voxel of each column.

    grid: (X, Y, Z) uint8 class ids (10 free); mask: (X, Y, Z) bool visibility or None (all visible).
    Returns (X, Y) uint8: a class id 0..8, FREE when the column has no occupied visible voxel,
    UNLABELED (255) when no voxel of the column is visible.
    """
    grid = check_label_grid("grid", grid)
    m = check_mask("mask", mask, grid.shape)
    occ = (grid != C.FREE) & m
    Z = grid.shape[2]
    top = Z - 1 - np.argmax(occ[:, :, ::-1], axis=2)
    out = np.take_along_axis(grid, top[:, :, None], axis=2)[:, :, 0].astype(np.uint8)
    out[~occ.any(axis=2)] = C.FREE
    out[~m.any(axis=2)] = C.UNLABELED
    return out


def bev_difference(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Per-column summary of the voxel-wise comparison of two grids.

    pred, gt: (X, Y, Z) uint8 class ids (10 free); mask: (X, Y, Z) bool visibility or None (all).
    Over the visible voxels of a column: wrong class (both occupied, classes differ), missed (GT
    occupied, predicted free), extra (predicted occupied, GT free). The column shows the error kind
    with most voxels (ties: wrong class, missed, extra), else correct when it holds an occupied
    voxel, else free; unknown when none of its voxels is visible. Returns (X, Y) uint8 DIFF_* codes.
    """
    gt = check_label_grid("gt", gt)
    pred = check_label_grid("pred", pred, gt.shape)
    m = check_mask("mask", mask, gt.shape)
    g_occ, p_occ = (gt != C.FREE) & m, (pred != C.FREE) & m
    counts = np.stack(
        [
            (g_occ & p_occ & (gt != pred)).sum(2),
            (g_occ & ~p_occ).sum(2),
            (~g_occ & p_occ & m).sum(2),
        ]
    )
    out = np.full(gt.shape[:2], DIFF_FREE, dtype=np.uint8)
    out[g_occ.any(2)] = DIFF_CORRECT
    err = counts.max(0) > 0
    out[err] = (
        np.array([DIFF_WRONG_CLASS, DIFF_MISSED, DIFF_EXTRA], np.uint8)[np.argmax(counts, axis=0)]
    )[err]
    out[~m.any(2)] = DIFF_UNKNOWN
    return out
