"""One body shape per person: the betas of a track from its per-frame fits (beyond the paper).

Estimator: the weighted geometric median (Weiszfeld's iteration) of the track's per-frame betas,
each frame weighted by its LiDAR point count. Why this and not a track-level solve of the data
terms: each per-frame fit already is a solve of the data terms for that frame, so their betas are
measurements of the one shape; the median needs no further optimisation (it costs nothing next
to a fit), and one frame gone wrong (another person's points, a body turned round) cannot move
it far (breakdown point 1/2, where a mean follows every outlier). Weights by points because a
frame with more returns constrains the surface, hence the shape, better. The track's shape is then
held fixed while its frames are refitted with the acceleration penalty (tasks/fit/refine.py).
"""

from __future__ import annotations

import numpy as np
import torch


def track_shapes(track_id, betas, weights=None) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """Per row the shape (R, 10) float32 of its track, and {track id: betas (10,)}.

    track_id (R,) int; betas (R, 10) the per-frame fits' shapes; weights (R,) >= 0 (e.g. LiDAR
    point counts; None: equal). A track whose weights are all 0 takes its plain median.
    """
    ids = np.asarray(track_id, np.int64).reshape(-1)
    b = np.asarray(betas, np.float64).reshape(len(ids), -1)
    w = np.ones(len(ids)) if weights is None else np.asarray(weights, np.float64).reshape(-1)
    out = np.empty_like(b)
    per_track = {}
    for tid in np.unique(ids):
        rows = np.flatnonzero(ids == tid)
        ww = w[rows] if w[rows].sum() > 0 else np.ones(len(rows))
        m = geometric_median(b[rows], ww)
        out[rows] = m
        per_track[int(tid)] = m.astype(np.float32)
    return out.astype(np.float32), per_track


#: Weiszfeld steps at most, and the step (in betas) below which it stops
MEDIAN_STEPS, MEDIAN_TOL = 50, 1e-6


def geometric_median(x: np.ndarray, w: np.ndarray):
    """The point (D,) minimising sum_i w_i |x_i - m| over rows x (N, D) (Weiszfeld, started at
    the weighted mean; a step that lands on a sample stops there)."""
    x = np.asarray(x, np.float64)
    w = np.asarray(w, np.float64)
    m = (w[:, None] * x).sum(0) / w.sum()
    for _ in range(MEDIAN_STEPS):
        d = np.linalg.norm(x - m, axis=1)
        if (d < 1e-12).any():
            return x[int(np.argmin(d))].copy()
        c = w / d
        new = (c[:, None] * x).sum(0) / c.sum()
        if np.linalg.norm(new - m) < MEDIAN_TOL:
            return new
        m = new
    return m


def with_shape(model, betas_old, transl_old, betas_new) -> np.ndarray:
    """The SMPL transl (R, 3) that keeps each body's root joint where it was when its shape
    changes from betas_old to betas_new (R, 10): transl + J_0(old) - J_0(new). Any frame (the
    root joint's rest position does not depend on the frame)."""
    with torch.no_grad():
        j_old = model.rest_joints(torch.as_tensor(np.asarray(betas_old, np.float32)))[:, 0]
        j_new = model.rest_joints(torch.as_tensor(np.asarray(betas_new, np.float32)))[:, 0]
    return (np.asarray(transl_old, np.float64) + (j_old - j_new).double().numpy()).astype(
        np.float32
    )


def shape_spread(track_id, betas) -> float:
    """Mean over tracks with two or more rows of the RMS distance of their betas (R, 10) to the
    track's mean (unitless): 0 when each person keeps one shape."""
    ids = np.asarray(track_id).reshape(-1)
    b = np.asarray(betas, np.float64).reshape(len(ids), -1)
    spreads = []
    for tid in np.unique(ids):
        rows = np.flatnonzero(ids == tid)
        if len(rows) >= 2:
            d = b[rows] - b[rows].mean(0)
            spreads.append(float(np.sqrt((d * d).sum(1).mean())))
    return float(np.mean(spreads)) if spreads else 0.0
