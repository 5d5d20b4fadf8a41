"""Geometry shared by the readers, the exports and the kernels: rigid transforms, points in
oriented boxes, axis-aligned box IoU and one-to-one box matching.

Frames, units and dtypes follow :mod:`tasks.conventions`: transforms are (4, 4) float64
``T_target_from_source``, rotations (3, 3) float64, metres and radians. Every function computes
in float64 and returns float64 (cast where a float32 product is wanted).
"""

from __future__ import annotations

import numpy as np
from numba import njit
from scipy.optimize import linear_sum_assignment

# --- rigid transforms ----------------------------------------------------------------------------


def rot_x(angle: float) -> np.ndarray:
    """(3, 3) float64 rotation about x by ``angle`` radians."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_z(yaw: float) -> np.ndarray:
    """(3, 3) float64 rotation about z by ``yaw`` radians."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def yaw_rotations(yaws: np.ndarray) -> np.ndarray:
    """(B,) yaw angles (rad) -> (B, 3, 3) float64 rotations about z (as :func:`rot_z`)."""
    yaws = np.asarray(yaws, dtype=np.float64).reshape(-1)
    c, s = np.cos(yaws), np.sin(yaws)
    R = np.zeros((len(yaws), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    return R


def make_transform(R: np.ndarray, t) -> np.ndarray:
    """(4, 4) float64 from a (3, 3) rotation and a (3,) translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def transform_points(T_target_from_source: np.ndarray, points_source: np.ndarray) -> np.ndarray:
    """(N, 3) points in the source frame -> (N, 3) float64 in the target frame (4x4 rigid T).

    Always float64, whatever the input dtype (float32 points are widened exactly first); a caller
    that stores float32 casts the result.
    """
    T = np.asarray(T_target_from_source, dtype=np.float64)
    return np.asarray(points_source, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]


# --- points in oriented boxes ---------------------------------------------------------------------


@njit(cache=True)
def _points_in_boxes(p, centers, half, rotations, floor, inside):
    for b in range(centers.shape[0]):
        cx, cy, cz = centers[b, 0], centers[b, 1], centers[b, 2]
        hx, hy, hz = half[b, 0], half[b, 1], half[b, 2]
        R = rotations[b]
        # a conservative reach (the box's half diagonal): skips far points before the exact test
        r2 = (hx * hx + hy * hy + hz * hz) * (1.0 + 1e-6) + 1e-9
        for i in range(p.shape[0]):
            if inside[i]:
                continue
            dx = p[i, 0] - cx
            dy = p[i, 1] - cy
            dz = p[i, 2] - cz
            if dx * dx + dy * dy + dz * dz > r2:
                continue
            # R^T (p - c): the point in the box's own axes
            lx = dx * R[0, 0] + dy * R[1, 0] + dz * R[2, 0]
            ly = dx * R[0, 1] + dy * R[1, 1] + dz * R[2, 1]
            lz = dx * R[0, 2] + dy * R[1, 2] + dz * R[2, 2]
            inside[i] = abs(lx) <= hx and abs(ly) <= hy and abs(lz) <= hz and lz >= floor[b]


def points_in_boxes(
    points: np.ndarray,
    centers: np.ndarray,
    sizes: np.ndarray,
    rotations: np.ndarray,
    *,
    margin_m: float = 0.0,
    bottom_exclude_m: float = 0.0,
) -> np.ndarray:
    """(N,) bool: which points lie inside any of B oriented boxes.

    points (N, 3) metres; centers (B, 3) metres; sizes (B, 3) (l, w, h) metres along the box's own
    x, y, z; rotations (B, 3, 3) box-to-points-frame rotations (:func:`yaw_rotations` for boxes
    turned about z only; CODa's Rz(yaw) Ry(pitch) Rx(roll) for its roll / pitch / yaw boxes); all
    in one frame. margin_m grows every half-size; bottom_exclude_m leaves out the bottom slab of
    each box (the ground at a pedestrian's feet: the paper leaves out 0.1 m). A point on a face
    is inside.
    """
    p = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    c = np.ascontiguousarray(np.asarray(centers, dtype=np.float64).reshape(-1, 3))
    half = np.asarray(sizes, dtype=np.float64).reshape(-1, 3) / 2.0 + margin_m
    R = np.ascontiguousarray(np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3))
    if not len(c) == len(half) == len(R):
        raise ValueError(
            f"points_in_boxes: {len(c)} centers, {len(half)} sizes, {len(R)} rotations"
        )
    floor = -half[:, 2] + bottom_exclude_m
    inside = np.zeros(len(p), dtype=bool)
    _points_in_boxes(p, c, np.ascontiguousarray(half), R, floor, inside)
    return inside


# --- axis-aligned 2D boxes ------------------------------------------------------------------------


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of axis-aligned boxes. a (N, 4), b (M, 4) as (x1, y1, x2, y2) (pixels or metres) -> (N, M)."""
    a = np.asarray(a, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4)
    iw = np.clip(
        np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0]), 0, None
    )
    ih = np.clip(
        np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1]), 0, None
    )
    inter = iw * ih
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    union = area_a[:, None] + area_b[None, :] - inter
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)


def match_boxes(
    gt_boxes: np.ndarray, det_boxes: np.ndarray, iou_threshold: float = 0.5
) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one matches maximising total IoU, pairs below ``iou_threshold`` dropped.

    gt_boxes (G, 4), det_boxes (D, 4) as (x1, y1, x2, y2). Returns (gt_index (K,), det_index (K,)) int64.
    """
    iou = box_iou(gt_boxes, det_boxes)
    if iou.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    # forbid sub-threshold pairs inside the assignment so they cannot displace a valid match
    cost = np.where(iou >= iou_threshold, -iou, 1.0)
    r, c = linear_sum_assignment(cost)
    ok = iou[r, c] >= iou_threshold
    return r[ok].astype(np.int64), c[ok].astype(np.int64)
