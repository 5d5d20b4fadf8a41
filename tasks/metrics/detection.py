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

from tasks.geometry import match_boxes
from tasks.metrics._common import MetricInputError, ratio


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
