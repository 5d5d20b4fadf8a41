"""Multi-object tracking scores: MOTA and IDF1 (py-motmetrics) and HOTA (own implementation).

Input per frame: GT ids (G,) and boxes (G, 4), predicted ids (P,) and boxes (P, 4), boxes as
axis-aligned (x1, y1, x2, y2) in one 2D space (image pixels, or BEV metres), similarity = IoU,
a pair counts as a match only at IoU >= ``iou_threshold`` (0.5) for MOTA / IDF1.

py-motmetrics 1.4 has no HOTA, so HOTA follows its definition (Luiten et al., IJCV 2021):
for each alpha in 0.05, 0.10, .., 0.95, per frame a one-to-one matching maximising
IoU x global-alignment score, matches kept where IoU >= alpha; DetA = TP / (TP + FN + FP);
per matched pair (g, p), A = TPA / (TPA + FNA + FPA) = |g~p| / (|g| + |p| - |g~p|) over the
sequence; AssA = mean of A over all TPs; HOTA_alpha = sqrt(DetA AssA); HOTA = mean over alpha.
Scores add over sequences (counts summed, AssA weighted by TP), as TrackEval combines them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from tasks.geometry import box_iou
from tasks.metrics._common import MetricInputError, ratio

HOTA_ALPHAS: np.ndarray = np.arange(1, 20) * 0.05
_EPS = 1e-9


@dataclass(frozen=True)
class TrackingScores:
    """Counts of one or more sequences; properties give MOTA, IDF1, HOTA (DetA, AssA).

    CLEAR: num_objects (GT boxes), misses, false_positives, switches. Identity: idtp, idfp, idfn.
    HOTA: per alpha (19,) float64 hota_tp, hota_fn, hota_fp, hota_ass_sum (sum of A over TPs).
    """

    num_objects: int
    misses: int
    false_positives: int
    switches: int
    idtp: int
    idfp: int
    idfn: int
    hota_tp: np.ndarray
    hota_fn: np.ndarray
    hota_fp: np.ndarray
    hota_ass_sum: np.ndarray

    def __add__(self, other: TrackingScores) -> TrackingScores:
        return TrackingScores(
            *(getattr(self, f) + getattr(other, f) for f in self.__dataclass_fields__)
        )

    @property
    def mota(self) -> float:
        return 1.0 - ratio(self.misses + self.false_positives + self.switches, self.num_objects)

    @property
    def idf1(self) -> float:
        return ratio(2 * self.idtp, 2 * self.idtp + self.idfp + self.idfn)

    @property
    def deta_per_alpha(self) -> np.ndarray:
        den = self.hota_tp + self.hota_fn + self.hota_fp
        return np.where(den > 0, self.hota_tp / np.maximum(den, _EPS), np.nan)

    @property
    def assa_per_alpha(self) -> np.ndarray:
        return np.where(self.hota_tp > 0, self.hota_ass_sum / np.maximum(self.hota_tp, 1), 0.0)

    @property
    def hota_per_alpha(self) -> np.ndarray:
        return np.sqrt(self.deta_per_alpha * self.assa_per_alpha)

    @property
    def hota(self) -> float:
        return float(np.mean(self.hota_per_alpha))

    @property
    def deta(self) -> float:
        return float(np.mean(self.deta_per_alpha))

    @property
    def assa(self) -> float:
        return float(np.mean(self.assa_per_alpha))

    def as_dict(self) -> dict:
        return {
            "mota": self.mota,
            "idf1": self.idf1,
            "hota": self.hota,
            "deta": self.deta,
            "assa": self.assa,
            "num_objects": int(self.num_objects),
            "misses": int(self.misses),
            "false_positives": int(self.false_positives),
            "switches": int(self.switches),
        }


def _frames(frames) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    out = []
    for k, (gi, gb, pi, pb) in enumerate(frames):
        gi, pi = np.asarray(gi).reshape(-1), np.asarray(pi).reshape(-1)
        gb = np.asarray(gb, dtype=np.float64).reshape(-1, 4)
        pb = np.asarray(pb, dtype=np.float64).reshape(-1, 4)
        if len(gi) != len(gb) or len(pi) != len(pb):
            raise MetricInputError(
                f"frame {k}: {len(gi)} GT ids for {len(gb)} boxes, "
                f"{len(pi)} predicted ids for {len(pb)} boxes"
            )
        for name, ids in (("GT", gi), ("predicted", pi)):
            if len(np.unique(ids)) != len(ids):
                raise MetricInputError(f"frame {k}: repeated {name} ids {ids.tolist()}")
        out.append((gi, gb, pi, pb))
    return out


def _clear_and_identity(frames, iou_threshold: float) -> dict:
    import motmetrics as mm  # heavy import (pandas) kept local

    acc = mm.MOTAccumulator(auto_id=True)
    for gi, gb, pi, pb in frames:
        dist = 1.0 - box_iou(gb, pb)
        dist[dist > 1.0 - iou_threshold + _EPS] = np.nan  # IoU below the threshold: never pair
        acc.update(gi.tolist(), pi.tolist(), dist)
    names = [
        "num_objects",
        "num_misses",
        "num_false_positives",
        "num_switches",
        "idtp",
        "idfp",
        "idfn",
    ]
    summary = mm.metrics.create().compute(acc, metrics=names, name="seq")
    return {n: int(summary[n].iloc[0]) for n in names}


def _hota_counts(frames, alphas: np.ndarray) -> tuple[np.ndarray, ...]:
    g_ids = np.unique(np.concatenate([f[0] for f in frames])) if frames else np.zeros(0)
    p_ids = np.unique(np.concatenate([f[2] for f in frames])) if frames else np.zeros(0)
    nG, nP, nA = len(g_ids), len(p_ids), len(alphas)
    g_count, p_count = np.zeros(nG), np.zeros(nP)
    potential = np.zeros((nG, nP))
    per_frame = []
    for gi, gb, pi, pb in frames:
        g, p = np.searchsorted(g_ids, gi), np.searchsorted(p_ids, pi)
        sim = box_iou(gb, pb)
        g_count[g] += 1
        p_count[p] += 1
        if sim.size:
            den = sim.sum(0)[None, :] + sim.sum(1)[:, None] - sim
            potential[np.ix_(g, p)] += np.where(den > _EPS, sim / np.maximum(den, _EPS), 0.0)
        per_frame.append((g, p, sim))
    align = potential / np.maximum(g_count[:, None] + p_count[None, :] - potential, _EPS)
    tp, fn, fp = np.zeros(nA), np.zeros(nA), np.zeros(nA)
    matches = np.zeros((nA, nG, nP))
    for g, p, sim in per_frame:
        if len(g) == 0 or len(p) == 0:
            fn += len(g)
            fp += len(p)
            continue
        r, c = linear_sum_assignment(-(align[np.ix_(g, p)] * sim))
        for a, alpha in enumerate(alphas):
            ok = sim[r, c] >= alpha - _EPS
            k = int(ok.sum())
            tp[a] += k
            fn[a] += len(g) - k
            fp[a] += len(p) - k
            matches[a, g[r[ok]], p[c[ok]]] += 1
    den = g_count[None, :, None] + p_count[None, None, :] - matches
    ass = np.where(matches > 0, matches / np.maximum(den, _EPS), 0.0)
    ass_sum = (matches * ass).sum(axis=(1, 2))
    return tp, fn, fp, ass_sum


def tracking_scores(frames, iou_threshold: float = 0.5) -> TrackingScores:
    """MOTA / IDF1 / HOTA counts of one sequence.

    frames: iterable over the sequence's frames of (gt_ids (G,) int, gt_boxes (G, 4) float,
    pred_ids (P,) int, pred_boxes (P, 4) float), boxes (x1, y1, x2, y2); empty arrays for a frame
    without persons. Ids must be unique within a frame.
    """
    fr = _frames(frames)
    clear = _clear_and_identity(fr, iou_threshold)
    tp, fn, fp, ass_sum = _hota_counts(fr, HOTA_ALPHAS)
    return TrackingScores(
        clear["num_objects"],
        clear["num_misses"],
        clear["num_false_positives"],
        clear["num_switches"],
        clear["idtp"],
        clear["idfp"],
        clear["idfn"],
        tp,
        fn,
        fp,
        ass_sum,
    )
