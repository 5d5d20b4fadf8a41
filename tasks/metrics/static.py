"""Static semantic voxels vs ground-truth labelled LiDAR points (the paper's Tab. label quality, top).

Every labelled GT point inside the grid looks up the label of its voxel (``floor((p - range_min)
/ voxel_size_m)``, free when the voxel is free). A voxel holds the surface that passes through it,
not every return of it (storage/SCHEMA.md, "Voxel convention"): with a sensor position and a noise
tolerance, a point whose voxel is free takes the voxel ``tolerance_m`` further along its ray
(:func:`surface_voxel_index`), where the surface whose range noise put it in front lies. From that:

- per-class IoU at point level: TP = points of GT class c whose voxel is c; FN = points of GT class
  c whose voxel is anything else (free included); FP = points of another GT class whose voxel is c.
  mIoU is the mean over the requested classes (the paper: road / vegetation / terrain).
- GT point coverage: fraction of GT points whose voxel is occupied (any class but free).
- point-level accuracy: among covered points, the fraction whose voxel label equals their GT class.
- voxel-level accuracy: among occupied voxels holding at least one GT point, the fraction whose
  label equals the majority GT class of their points (ties: the lower class id).

Coverage and the two accuracies are kept apart on purpose: coverage says how much annotated
geometry the grid holds, the accuracies how well what it holds is labelled. Points labelled
UNLABELED (255) and points outside the grid are left out (counted in ``num_points_ignored``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tasks import conventions as C
from tasks.metrics._common import MetricInputError, check_label_grid, ratio

_N = C.NUM_CLASSES


@dataclass(frozen=True)
class StaticCounts:
    """Accumulable counts. confusion (NUM_CLASSES, NUM_CLASSES) int64 points, rows GT class,
    columns voxel label (10 = free voxel, 9 = unclassified: counts against the GT class); voxel counts over occupied voxels holding GT points."""

    confusion: np.ndarray = field(default_factory=lambda: np.zeros((_N, _N), dtype=np.int64))
    voxels_evaluated: int = 0
    voxels_correct: int = 0
    num_points_ignored: int = 0

    def __add__(self, other: StaticCounts) -> StaticCounts:
        return StaticCounts(
            self.confusion + other.confusion,
            self.voxels_evaluated + other.voxels_evaluated,
            self.voxels_correct + other.voxels_correct,
            self.num_points_ignored + other.num_points_ignored,
        )

    def per_class_iou(self, classes=None) -> dict[str, float]:
        """IoU per class id in ``classes`` (default: the classes present in the GT points)."""
        cm = self.confusion
        if classes is None:
            classes = [c for c in range(C.NUM_SEMANTIC_CLASSES) if cm[c].sum() > 0]
        out = {}
        for c in classes:
            tp = cm[c, c]
            fn = cm[c].sum() - tp
            fp = cm[:, c].sum() - tp
            out[C.CLASS_NAMES[c]] = ratio(tp, tp + fn + fp)
        return out

    @property
    def num_points(self) -> int:
        return int(self.confusion.sum())

    @property
    def coverage(self) -> float:
        return ratio(self.confusion[:, : C.FREE].sum(), self.num_points)

    @property
    def point_accuracy(self) -> float:
        return ratio(np.trace(self.confusion), self.confusion[:, : C.FREE].sum())

    @property
    def voxel_accuracy(self) -> float:
        return ratio(self.voxels_correct, self.voxels_evaluated)

    def as_dict(self, classes=None) -> dict:
        iou = self.per_class_iou(classes)
        vals = [v for v in iou.values() if not np.isnan(v)]
        return {
            "per_class_iou": iou,
            "miou": float(np.mean(vals)) if vals else float("nan"),
            "coverage": self.coverage,
            "voxel_accuracy": self.voxel_accuracy,
            "point_accuracy": self.point_accuracy,
            "num_points": self.num_points,
            "num_voxels": int(self.voxels_evaluated),
            "num_points_ignored": int(self.num_points_ignored),
            "confusion": self.confusion.tolist(),  # points: rows GT class, columns voxel label
        }


def surface_voxel_index(
    labels: np.ndarray,
    range_min,
    voxel_size_m: float,
    points: np.ndarray,
    sensor: np.ndarray | None = None,
    tolerance_m: float = 0.0,
) -> np.ndarray:
    """(N, 3) int64 voxel index of each point: its own voxel (floor rule), or, where that is free
    in labels (X, Y, Z) and a sensor (3,) is given, the voxel of the point moved tolerance_m
    further along its ray from the sensor, when that one is occupied (a return thrown in front of
    its surface by range noise). points (N, 3) float metres, grid frame; indices may lie outside
    the grid."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    lo = np.asarray(range_min, dtype=np.float64)
    idx = np.floor((pts - lo) / float(voxel_size_m)).astype(np.int64)
    if sensor is None or tolerance_m <= 0 or not len(pts):
        return idx
    shape = np.asarray(labels.shape)
    inside = np.all((idx >= 0) & (idx < shape), axis=1)
    free = np.zeros(len(pts), dtype=bool)
    free[inside] = labels[tuple(idx[inside].T)] == C.FREE
    ray = pts[free] - np.asarray(sensor, dtype=np.float64).reshape(3)
    ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-12)
    beyond = np.floor((pts[free] + tolerance_m * ray - lo) / float(voxel_size_m)).astype(np.int64)
    ok = np.all((beyond >= 0) & (beyond < shape), axis=1)
    ok[ok] = labels[tuple(beyond[ok].T)] != C.FREE
    rows = np.flatnonzero(free)[ok]
    idx[rows] = beyond[ok]
    return idx


def static_counts(
    labels: np.ndarray,
    range_min,
    voxel_size_m: float,
    points: np.ndarray,
    gt_classes: np.ndarray,
    sensor: np.ndarray | None = None,
    tolerance_m: float = 0.0,
) -> StaticCounts:
    """Counts of one frame (or one accumulated map) against its labelled GT points.

    labels: (X, Y, Z) uint8 class ids (10 free) of the grid; range_min: (3,) metres, the grid's
    corner in the points' frame; voxel_size_m: metres; points: (N, 3) float metres in the grid's
    frame; gt_classes: (N,) uint8 our class ids (0..8), UNLABELED (255) ignored. sensor (3,) and
    tolerance_m: the noise tolerance of :func:`surface_voxel_index` (None / 0: the floor rule).
    """
    labels = check_label_grid("labels", labels)
    pts = np.asarray(points, dtype=np.float64)
    cls = np.asarray(gt_classes)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise MetricInputError(f"points: expected (N, 3) metres, got shape {pts.shape}")
    if cls.shape != (len(pts),):
        raise MetricInputError(
            f"gt_classes: expected ({len(pts)},) class ids, got shape {cls.shape}"
        )
    labelled = cls != C.UNLABELED
    if np.any(cls[labelled] >= C.NUM_SEMANTIC_CLASSES):
        bad = cls[labelled][cls[labelled] >= C.NUM_SEMANTIC_CLASSES][0]
        raise MetricInputError(
            f"gt_classes: class id {int(bad)} "
            f"is not a semantic class (0..{C.NUM_SEMANTIC_CLASSES - 1}) or {C.UNLABELED}"
        )
    idx = surface_voxel_index(labels, range_min, voxel_size_m, pts, sensor, tolerance_m)
    inside = np.all((idx >= 0) & (idx < np.asarray(labels.shape)), axis=1)
    keep = labelled & inside
    idx, g = idx[keep], cls[keep].astype(np.int64)
    p = labels[idx[:, 0], idx[:, 1], idx[:, 2]].astype(np.int64)
    confusion = np.bincount(g * _N + p, minlength=_N * _N).reshape(_N, _N)
    # voxel level: majority GT class per occupied voxel holding points
    occ = p != C.FREE
    flat = (
        np.ravel_multi_index(tuple(idx[occ].T), labels.shape)
        if occ.any()
        else np.zeros(0, np.int64)
    )
    vox, inv = np.unique(flat, return_inverse=True)
    votes = np.zeros((len(vox), _N), dtype=np.int64)
    np.add.at(votes, (inv, g[occ]), 1)
    majority = np.argmax(votes, axis=1)
    vox_label = labels.reshape(-1)[vox]
    return StaticCounts(
        confusion, int(len(vox)), int(np.sum(vox_label == majority)), int(np.sum(~keep))
    )
