"""Per-track velocities from positions over time (the paper's pedestrian velocity task)."""

from __future__ import annotations

import numpy as np


def track_velocities(track_ids: np.ndarray, stamps_s: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Velocity of every row from its track's neighbouring rows.

    track_ids: (R,) int. stamps_s: (R,) float seconds. positions: (R, 3) float metres in one fixed
    frame (e.g. world). Central differences inside a track, one-sided at its ends, zero for a track
    seen once. Returns (R, 3) float64 m/s in the frame of ``positions``.
    """
    ids = np.asarray(track_ids).reshape(-1)
    t = np.asarray(stamps_s, np.float64).reshape(-1)
    p = np.asarray(positions, np.float64).reshape(-1, 3)
    if not len(ids) == len(t) == len(p):
        raise ValueError(f"track_velocities: {len(ids)} ids, {len(t)} stamps, {len(p)} positions")
    out = np.zeros_like(p)
    for tid in np.unique(ids):
        rows = np.flatnonzero(ids == tid)
        rows = rows[np.argsort(t[rows], kind="stable")]
        if len(rows) < 2:
            continue
        tt, pp = t[rows], p[rows]
        prev = np.r_[0, np.arange(len(rows) - 1)]
        nxt = np.r_[np.arange(1, len(rows)), len(rows) - 1]
        dt = tt[nxt] - tt[prev]
        ok = dt > 0
        v = np.zeros_like(pp)
        v[ok] = (pp[nxt[ok]] - pp[prev[ok]]) / dt[ok, None]
        out[rows] = v
    return out
