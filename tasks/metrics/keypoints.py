"""2D person quality of matched detections: keypoint PCK and instance-mask IoU.

PCK@alpha (percentage of correct keypoints): a predicted keypoint is correct when it lies within
alpha x the reference size (the ground-truth person's box height) of the ground-truth keypoint;
only ground-truth keypoints with flag 2 (visible) count.
"""

from __future__ import annotations

import numpy as np


def pck_counts(
    pred: np.ndarray, gt: np.ndarray, ref_size: np.ndarray, alpha: float = 0.1
) -> tuple[int, int]:
    """Correct and counted keypoints of K matched persons.

    pred (K, J, >=2) px; gt (K, J, 3) px + flag (2 = visible); ref_size (K,) px. Returns
    (correct, visible ground-truth keypoints)."""
    pred = np.asarray(pred, np.float64).reshape(-1, np.shape(gt)[1], np.shape(pred)[-1])
    gt = np.asarray(gt, np.float64)
    vis = gt[..., 2] == 2
    err = np.linalg.norm(pred[..., :2] - gt[..., :2], axis=-1)
    ok = vis & (err < alpha * np.asarray(ref_size, np.float64)[:, None])
    return int(ok.sum()), int(vis.sum())


def mask_iou(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """IoU (K,) of K predicted and ground-truth masks (K, H, W) bool (0 where both are empty)."""
    p, g = np.asarray(pred, bool), np.asarray(gt, bool)
    inter = (p & g).reshape(len(p), -1).sum(1)
    union = (p | g).reshape(len(p), -1).sum(1)
    return np.where(union > 0, inter / np.maximum(union, 1), 0.0)
