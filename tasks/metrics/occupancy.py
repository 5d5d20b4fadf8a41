"""Occ3D semantic occupancy metric: per-class IoU, mIoU and geometric IoU over mask_camera.

Follows the Occ3D / CVPR 2023 occupancy challenge evaluation: one confusion matrix over the
voxels where the camera mask is 1, accumulated over frames; IoU_c = TP / (TP + FP + FN) per class;
mIoU is the mean over the occupied classes (free excluded). A class absent from both ground truth
and prediction has IoU NaN and is left out of the mean. Geometric IoU treats every occupied class
as one "occupied" label against free.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tasks import conventions as C
from tasks.metrics._common import check_label_grid, check_mask


@dataclass(frozen=True)
class OccupancyScores:
    """per_class_iou (NUM_SEMANTIC_CLASSES,) float64 over the semantic classes 0..8 (NaN: class in
    neither grid; an UNCLASSIFIED voxel where the truth has class c counts against c); miou:
    nanmean of it; geometric_iou: occupied-vs-free IoU (UNCLASSIFIED is occupied);
    unclassified_share: UNCLASSIFIED voxels among the predicted occupied ones (NaN: none);
    confusion (NUM_CLASSES, NUM_CLASSES) int64 voxel counts, rows ground truth, columns
    prediction; num_voxels evaluated."""

    per_class_iou: np.ndarray
    miou: float
    geometric_iou: float
    confusion: np.ndarray
    num_voxels: int
    unclassified_share: float = float("nan")

    def as_dict(self) -> dict:
        names = C.CLASS_NAMES[: C.NUM_SEMANTIC_CLASSES]
        return {
            "per_class_iou": {n: float(v) for n, v in zip(names, self.per_class_iou)},
            "miou": float(self.miou),
            "geometric_iou": float(self.geometric_iou),
            "unclassified_share": float(self.unclassified_share),
            "num_voxels": int(self.num_voxels),
        }


class OccupancyMetric:
    """Accumulates the Occ3D confusion matrix over frames: ``update(pred, gt, mask)``, ``compute()``."""

    def __init__(self, num_classes: int = C.NUM_CLASSES, free_class: int = C.FREE) -> None:
        if free_class != num_classes - 1:
            raise ValueError(
                f"free_class must be the last class ({num_classes - 1}), got {free_class}"
            )
        self.num_classes = num_classes
        self.free_class = free_class
        self.confusion = np.zeros((num_classes, num_classes), dtype=np.int64)

    def update(self, pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> None:
        """Add one frame.

        pred, gt: (X, Y, Z) integer class ids (0..8 semantic, 9 unclassified, 10 free), base frame [x, y, z];
        mask: (X, Y, Z) bool / uint8 mask_camera (1 = evaluated), None = every voxel.
        """
        gt = check_label_grid("gt", gt)
        pred = check_label_grid("pred", pred, gt.shape)
        m = check_mask("mask", mask, gt.shape)
        g = gt[m].astype(np.int64)
        p = pred[m].astype(np.int64)
        self.confusion += np.bincount(
            g * self.num_classes + p, minlength=self.num_classes**2
        ).reshape(self.num_classes, self.num_classes)

    def compute(self) -> OccupancyScores:
        """Scores of everything added so far (NaN everywhere when nothing was added)."""
        cm = self.confusion
        tp = np.diag(cm).astype(np.float64)
        union = cm.sum(0) + cm.sum(1) - np.diag(cm)
        with np.errstate(invalid="ignore", divide="ignore"):
            iou = np.where(union > 0, tp / np.maximum(union, 1), np.nan)
        occ = iou[: min(self.free_class, C.NUM_SEMANTIC_CLASSES)]
        miou = float(np.nanmean(occ)) if np.any(~np.isnan(occ)) else float("nan")
        f = self.free_class
        occ_tp = cm[:f, :f].sum()
        occ_fn = cm[:f, f].sum()  # occupied in GT, predicted free
        occ_fp = cm[f, :f].sum()  # free in GT, predicted occupied
        den = occ_tp + occ_fn + occ_fp
        geo = float(occ_tp / den) if den else float("nan")
        pred_occ = cm[:, :f].sum()
        unc = cm[:, C.UNCLASSIFIED].sum() if f > C.UNCLASSIFIED else 0
        share = float(unc / pred_occ) if pred_occ else float("nan")
        return OccupancyScores(occ.copy(), miou, geo, cm.copy(), int(cm.sum()), share)
