"""Detection robustness (the paper's Tab. label quality, bottom), per condition.

Per frame, GT persons (2D boxes with a visible / occluded flag) and detections are matched one to
one by the Hungarian algorithm on IoU, keeping pairs with IoU >= ``iou_threshold`` (0.5):
T = matched GT persons, M_vis / M_occ = unmatched visible / occluded GT persons, W = unmatched
detections. As in the paper's numbers (e.g. crowded: 480 / (480 + 6) = 98.8):
recall = T / (T + M_vis), precision = T / (T + W), Miss_vis = M_vis / (T + M_vis) = 1 - recall;
occluded misses are reported but not held against recall.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from tasks.metrics._common import MetricInputError, ratio


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


@dataclass(frozen=True)
class DetectionCounts:
    """T, M_vis, M_occ, W counts of one condition (add over frames / sequences)."""

    T: int = 0
    M_vis: int = 0
    M_occ: int = 0
    W: int = 0

    def __add__(self, other: DetectionCounts) -> DetectionCounts:
        return DetectionCounts(
            self.T + other.T, self.M_vis + other.M_vis, self.M_occ + other.M_occ, self.W + other.W
        )

    @property
    def recall(self) -> float:
        return ratio(self.T, self.T + self.M_vis)

    @property
    def precision(self) -> float:
        return ratio(self.T, self.T + self.W)

    @property
    def miss_vis(self) -> float:
        return ratio(self.M_vis, self.T + self.M_vis)

    def as_dict(self) -> dict:
        return {
            "T": int(self.T),
            "M_vis": int(self.M_vis),
            "M_occ": int(self.M_occ),
            "W": int(self.W),
            "recall": self.recall,
            "precision": self.precision,
            "miss_vis": self.miss_vis,
        }


def detection_counts(
    gt_boxes: np.ndarray, gt_visible: np.ndarray, det_boxes: np.ndarray, iou_threshold: float = 0.5
) -> DetectionCounts:
    """Counts of one frame. gt_boxes (G, 4) and det_boxes (D, 4) (x1, y1, x2, y2) pixels in the same
    image; gt_visible (G,) bool, False for an occluded person."""
    gt_boxes = np.asarray(gt_boxes, dtype=np.float64).reshape(-1, 4)
    det_boxes = np.asarray(det_boxes, dtype=np.float64).reshape(-1, 4)
    vis = np.asarray(gt_visible, dtype=bool).reshape(-1)
    if len(vis) != len(gt_boxes):
        raise MetricInputError(f"gt_visible has {len(vis)} flags for {len(gt_boxes)} GT boxes")
    gi, di = match_boxes(gt_boxes, det_boxes, iou_threshold)
    missed = np.ones(len(gt_boxes), dtype=bool)
    missed[gi] = False
    return DetectionCounts(
        len(gi), int(np.sum(missed & vis)), int(np.sum(missed & ~vis)), len(det_boxes) - len(gi)
    )
