"""How well a fitted body agrees with its evidence: the residuals written beside every fit."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def fit_residuals(
    vertices_cam: np.ndarray,
    keypoints_model_cam: np.ndarray,
    points_cam: list[np.ndarray],
    keypoints_2d: np.ndarray,
    K: np.ndarray,
    min_confidence: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Per person: mean distance of its LiDAR points to the nearest mesh vertex, and mean
    reprojection error of its confident keypoints.

    vertices_cam: (B, V, 3) fitted mesh, cam frame, m. keypoints_model_cam: (B, 17, 3) the model's
    COCO-17 keypoints, cam frame. points_cam: B arrays (N_b, 3), the person's LiDAR points, cam
    frame. keypoints_2d: (B, 17, 3) detected (u, v, confidence), pixels. K: (3, 3).
    Returns chamfer_m (B,) float32 (NaN: no points) and reproj_px (B,) float32 (NaN: no keypoint
    with confidence >= min_confidence).
    """
    B = len(points_cam)
    chamfer = np.full(B, np.nan, np.float32)
    for b, pts in enumerate(points_cam):
        if len(pts):
            dist, _ = cKDTree(np.asarray(vertices_cam[b], np.float64)).query(
                np.asarray(pts, np.float64)
            )
            chamfer[b] = dist.mean()
    kp = np.asarray(keypoints_model_cam, np.float64)
    z = np.maximum(kp[..., 2:3], 1e-6)
    uv = (kp[..., :2] / z) @ np.asarray(K, np.float64)[:2, :2].T + np.asarray(K, np.float64)[:2, 2]
    err = np.linalg.norm(uv - np.asarray(keypoints_2d, np.float64)[..., :2], axis=-1)
    ok = np.asarray(keypoints_2d)[..., 2] >= min_confidence
    reproj = np.where(
        ok.any(1), np.sum(np.where(ok, err, 0.0), 1) / np.maximum(ok.sum(1), 1), np.nan
    )
    return chamfer, reproj.astype(np.float32)
