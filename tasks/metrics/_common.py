"""Shared helpers of the metric kernels: input checks and precision / recall counts."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tasks import conventions as C


class MetricInputError(ValueError):
    """Arrays given to a metric that do not have the documented shape, dtype or values."""


def ratio(num: float, den: float) -> float:
    """num / den as a float, NaN when den is 0."""
    return float(num) / float(den) if den else float("nan")


def check_label_grid(name: str, grid, shape: tuple[int, ...] | None = None) -> np.ndarray:
    """A class-id grid (X, Y, Z) with values in 0..FREE, as an ndarray; raises with the name."""
    a = np.asarray(grid)
    if a.ndim != 3:
        raise MetricInputError(f"{name}: expected an (X, Y, Z) class-id grid, got shape {a.shape}")
    if shape is not None and a.shape != tuple(shape):
        raise MetricInputError(f"{name}: shape {a.shape} differs from the expected {tuple(shape)}")
    if not np.issubdtype(a.dtype, np.integer):
        raise MetricInputError(f"{name}: expected integer class ids, got dtype {a.dtype}")
    if a.size and (a.min() < 0 or a.max() > C.FREE):
        bad = a[(a < 0) | (a > C.FREE)][0]
        raise MetricInputError(
            f"{name}: class id {int(bad)} outside 0..{C.FREE} (0 pedestrian .. 8 vegetation, 9 unclassified, 10 free)"
        )
    return a


def check_mask(name: str, mask, shape: tuple[int, ...]) -> np.ndarray:
    """A visibility / region mask of the given shape as bool (None -> all True)."""
    if mask is None:
        return np.ones(shape, dtype=bool)
    m = np.asarray(mask)
    if m.shape != tuple(shape):
        raise MetricInputError(
            f"{name}: mask shape {m.shape} differs from the grid shape {tuple(shape)}"
        )
    return m.astype(bool)


@dataclass(frozen=True)
class PRCounts:
    """Counts behind a precision / recall pair whose two sides are matched separately.

    precision = pred_matched / pred_total (predicted elements that hit the reference);
    recall = ref_matched / ref_total (reference elements that the prediction hits). Add two
    PRCounts to micro-average (e.g. all sequences).
    """

    pred_matched: int = 0
    pred_total: int = 0
    ref_matched: int = 0
    ref_total: int = 0

    def __add__(self, other: PRCounts) -> PRCounts:
        return PRCounts(
            self.pred_matched + other.pred_matched,
            self.pred_total + other.pred_total,
            self.ref_matched + other.ref_matched,
            self.ref_total + other.ref_total,
        )

    @property
    def precision(self) -> float:
        return ratio(self.pred_matched, self.pred_total)

    @property
    def recall(self) -> float:
        return ratio(self.ref_matched, self.ref_total)

    @property
    def f1(self) -> float:
        p, r = self.precision, self.recall
        if np.isnan(p) or np.isnan(r) or p + r == 0:
            return float("nan") if (np.isnan(p) or np.isnan(r)) else 0.0
        return 2 * p * r / (p + r)

    def as_dict(self) -> dict:
        return {
            "precision": self.precision,
            "recall": self.recall,
            "f1": self.f1,
            "pred_matched": int(self.pred_matched),
            "pred_total": int(self.pred_total),
            "ref_matched": int(self.ref_matched),
            "ref_total": int(self.ref_total),
        }
