"""Where the wrong voxels of each class lie, and the per-class voxel counts beside the IoU.

The Occ3D confusion matrix (:class:`tasks.metrics.occupancy.OccupancyMetric`) says how many voxels
of a class are wrong; this module says where they are, so that a systematic error (a surface
labelled one voxel in front of where it is, a class that is only a few stray voxels) shows at once.

For a class c, over the evaluated voxels (the mask):

- a **false** voxel is labelled c where the ground truth is not c; its reference is the ground
  truth's c voxels (anywhere in the grid, visible or not);
- a **missed** voxel is c in the ground truth and labelled otherwise; its reference is the
  labelled c voxels.

Each wrong voxel lies, relative to its reference (first match wins):

- ``adjacent_sensor_side``: a reference voxel touches it (26-neighbourhood) and lies farther
  from the sensor than it (centre distances): the wrong voxel is in front of the right one, as
  a surface marked one voxel too near the sensor;
- ``adjacent_far_side``: a reference voxel touches it, none of them farther from the sensor;
- ``along_ray``: no reference voxel touches it, but one lies on the sensor ray through its centre
  within ``reach_voxels`` in front of or behind it (a range error);
- ``elsewhere``: neither (a wrong label, a missed or invented object).

Grids are ``[x, y, z]`` class ids (:mod:`tasks.conventions`, 10 free); the sensor is a point in
the grid's frame, given in voxel units (``(p - range_min) / voxel_size_m``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tasks import conventions as C
from tasks.metrics._common import MetricInputError, check_label_grid, check_mask

LOCATIONS = ("adjacent_sensor_side", "adjacent_far_side", "along_ray", "elsewhere")
#: the two kinds of wrong voxel of a class
KINDS = ("false", "missed")
#: how far (voxels) in front of or behind a wrong voxel the sensor ray is searched
RAY_REACH_VOXELS = 3.0

_OFFSETS = np.array(
    [
        (i, j, k)
        for i in (-1, 0, 1)
        for j in (-1, 0, 1)
        for k in (-1, 0, 1)
        if (i, j, k) != (0, 0, 0)
    ],
    dtype=np.int64,
)


def _zeros() -> np.ndarray:
    return np.zeros((len(KINDS), C.FREE, len(LOCATIONS)), dtype=np.int64)


@dataclass(frozen=True)
class ErrorLocations:
    """counts (2, 10, 4) int64: [kind (false, missed), class 0..9 (9 unclassified), location (:data:`LOCATIONS`)].
    Add two to sum frames or sequences."""

    counts: np.ndarray = field(default_factory=_zeros)

    def __add__(self, other: ErrorLocations) -> ErrorLocations:
        return ErrorLocations(self.counts + other.counts)

    def as_dict(self) -> dict:
        """{class name: {kind: {location: voxels}}} for the classes with a wrong voxel."""
        out = {}
        for c, name in enumerate(C.CLASS_NAMES[: C.FREE]):
            if self.counts[:, c].any():
                out[name] = {
                    kind: {loc: int(v) for loc, v in zip(LOCATIONS, self.counts[k, c])}
                    for k, kind in enumerate(KINDS)
                }
        return out


def _locate(
    wrong: np.ndarray, ref: np.ndarray, sensor_voxel: np.ndarray, reach: float
) -> np.ndarray:
    """(4,) counts of the wrong voxels (M, 3) int by location relative to the reference grid ref
    (X, Y, Z) bool."""
    out = np.zeros(len(LOCATIONS), dtype=np.int64)
    if not len(wrong):
        return out
    shape = np.asarray(ref.shape)
    padded = np.zeros(tuple(shape + 2), dtype=bool)
    padded[1:-1, 1:-1, 1:-1] = ref
    nb = wrong[:, None, :] + _OFFSETS[None]  # (M, 26, 3)
    touch = padded[nb[..., 0] + 1, nb[..., 1] + 1, nb[..., 2] + 1]
    dist = np.linalg.norm(wrong + 0.5 - sensor_voxel, axis=1)
    nb_dist = np.linalg.norm(nb + 0.5 - sensor_voxel, axis=2)
    behind = (touch & (nb_dist > dist[:, None] + 1e-9)).any(axis=1)
    adjacent = touch.any(axis=1)
    out[0] = np.count_nonzero(behind)
    out[1] = np.count_nonzero(adjacent & ~behind)
    rest = ~adjacent
    if rest.any():
        c = wrong[rest] + 0.5
        ray = c - sensor_voxel
        unit = ray / np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-12)
        steps = np.arange(-reach, reach + 1e-9, 0.25)
        pts = c[:, None, :] + steps[None, :, None] * unit[:, None, :]
        idx = np.floor(pts).astype(np.int64)
        inside = np.all((idx >= 0) & (idx < shape), axis=2)
        idx = np.where(inside[..., None], idx, 0)
        on_ray = (ref[idx[..., 0], idx[..., 1], idx[..., 2]] & inside).any(axis=1)
        out[2] = np.count_nonzero(on_ray)
        out[3] = np.count_nonzero(~on_ray)
    return out


def error_locations(
    pred: np.ndarray,
    gt: np.ndarray,
    mask: np.ndarray | None,
    sensor_voxel: np.ndarray,
    reach_voxels: float = RAY_REACH_VOXELS,
) -> ErrorLocations:
    """Where the false and missed voxels of each class lie (module docstring) in one frame.

    pred, gt: (X, Y, Z) integer class ids (0..9 occupied, 9 unclassified, 10 free); mask: (X, Y, Z) bool voxels
    evaluated (e.g. mask_camera; None: all); sensor_voxel: (3,) float the sensor's position in
    voxel units of the grid (``(p_sensor - range_min) / voxel_size_m``, base frame).
    """
    gt = check_label_grid("gt", gt)
    pred = check_label_grid("pred", pred, gt.shape)
    m = check_mask("mask", mask, gt.shape)
    o = np.asarray(sensor_voxel, dtype=np.float64).reshape(-1)
    if o.shape != (3,) or not np.all(np.isfinite(o)):
        raise MetricInputError(f"sensor_voxel must be 3 finite values, got {sensor_voxel!r}")
    counts = _zeros()
    for c in np.union1d(np.unique(pred[m]), np.unique(gt[m])):
        if c >= C.FREE:
            continue
        is_gt, is_pred = gt == c, pred == c
        for k, (wrong, ref) in enumerate(((is_pred & ~is_gt, is_gt), (is_gt & ~is_pred, is_pred))):
            counts[k, c] = _locate(np.argwhere(wrong & m), ref, o, reach_voxels)
    return ErrorLocations(counts)


def class_counts(confusion: np.ndarray) -> dict:
    """Per occupied class of a confusion matrix (NUM_CLASSES, NUM_CLASSES) int (rows ground
    truth, columns labels): {class name: {"iou", "gt_voxels", "labelled_voxels", "true_voxels"}}
    (iou NaN where the class is in neither)."""
    cm = np.asarray(confusion, dtype=np.int64)
    if cm.shape != (C.NUM_CLASSES, C.NUM_CLASSES):
        raise MetricInputError(
            f"confusion must be ({C.NUM_CLASSES}, {C.NUM_CLASSES}), got shape {cm.shape}"
        )
    out = {}
    for c, name in enumerate(C.CLASS_NAMES[: C.FREE]):
        tp, g, p = int(cm[c, c]), int(cm[c].sum()), int(cm[:, c].sum())
        union = g + p - tp
        out[name] = {
            "iou": tp / union if union else float("nan"),
            "gt_voxels": g,
            "labelled_voxels": p,
            "true_voxels": tp,
        }
    return out
