"""Temporal refinement of the fits along a track (beyond the paper; in the spirit of SmoothNet,
whose learned filter cuts acceleration error several times at a millimetre of MPJPE).

After the per-frame fits, each track's frames are refitted together: pose and root translation
of every frame by the fit's own objective (tasks/fit/optimize.py: keypoints, LiDAR Chamfer, pose
priors) plus an acceleration penalty that ties consecutive frames,

    L_acc = w_limbs * sum_limb joints |a_j|^2 + w_torso * sum_torso joints |a_j|^2
            + w_root * |a_root|^2,   a = x_prev - 2 x + x_next

with x the joints in a frame fixed to the world (the robot's motion removed), in metres per
frame^2 at the sequence's nominal rate (unequal steps use the second divided difference scaled
to it). The shape is held at the track's (tasks/fit/shape.py). Long tracks are refined in
overlapping windows of ``window_frames``; each row keeps the result of the window where it lies
farthest from an edge. Rows of different tracks share batches but never a term.
"""

from __future__ import annotations

import numpy as np
import torch

from tasks.body.params import BodyParams
from tasks.fit.settings import RefineSettings

#: SMPL joints that move nearly with the pelvis: spine 1-3, neck, collars, head, shoulders
TORSO_JOINTS = (3, 6, 9, 12, 13, 14, 15, 16, 17)


class AccelerationPenalty:
    """The coupling term of a batch of rows: joints (k, 24, 3) cam frame -> (k,) L_acc of each
    row that has a neighbour on both sides (0 for the others).

    T_ref_from_cam (k, 4, 4) float64: each row's camera in a frame fixed to the world (near the
    rows, so float32 keeps millimetres); prev / next (k,) int64: the row's neighbours in the
    batch (-1 none); scale_prev / scale_mid / scale_next (k,): the divided-difference weights
    times the nominal step squared."""

    def __init__(
        self, T_ref_from_cam, prev, nxt, coef, joint_weight, torso_weight, root_weight, device="cpu"
    ):
        T = torch.as_tensor(np.asarray(T_ref_from_cam), dtype=torch.float32, device=device)
        self.R, self.t = T[:, :3, :3], T[:, :3, 3]
        self.prev = torch.as_tensor(np.maximum(prev, 0), device=device)
        self.next = torch.as_tensor(np.maximum(nxt, 0), device=device)
        self.on = torch.as_tensor((prev >= 0) & (nxt >= 0), device=device)
        self.coef = torch.as_tensor(np.asarray(coef), dtype=torch.float32, device=device)
        w = np.full(24, float(joint_weight))
        w[list(TORSO_JOINTS)] = float(torso_weight)
        w[0] += float(root_weight)
        self.w = torch.as_tensor(w, dtype=torch.float32, device=device)

    def __call__(self, joints: torch.Tensor) -> torch.Tensor:
        x = joints @ self.R.transpose(1, 2) + self.t[:, None]  # (k, 24, 3) reference frame
        c = self.coef
        a = (
            c[:, 0, None, None] * x[self.prev]
            + c[:, 1, None, None] * x
            + c[:, 2, None, None] * x[self.next]
        )
        a2 = (a * a).sum(-1)  # (k, 24)
        pen = (a2 * self.w).sum(-1)
        return torch.where(self.on, pen, torch.zeros_like(pen))


def neighbours(track_id, stamps_s, max_step_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Previous and next row (R,) int64 of each row along its track (-1: none, or farther than
    max_step_s)."""
    from tasks.track.velocity import track_neighbours

    return track_neighbours(track_id, stamps_s, max_step_s)


def divided_difference_coefficients(stamps_s, prev, nxt, step_s: float) -> np.ndarray:
    """(R, 3) weights (previous, this, next) of the second divided difference of each row with
    both neighbours, scaled by step_s^2 (so that equal steps of step_s give 1, -2, 1); zeros
    for the others."""
    t = np.asarray(stamps_s, np.float64)
    out = np.zeros((len(t), 3))
    ok = (prev >= 0) & (nxt >= 0)
    h1 = t[ok] - t[prev[ok]]
    h2 = t[nxt[ok]] - t[ok]
    k = 2.0 * step_s * step_s / (h1 + h2)
    out[ok] = np.stack([k / h1, -k * (1.0 / h1 + 1.0 / h2), k / h2], 1)
    return out


def windows(track_id, position, window_frames: int, overlap_frames: int) -> list[np.ndarray]:
    """Rows (n,) int64 of each window: a track's rows split into runs of at most
    ``window_frames`` frame positions overlapping by ``overlap_frames`` (one window for a short
    track)."""
    ids = np.asarray(track_id).reshape(-1)
    pos = np.asarray(position).reshape(-1)
    out = []
    step = max(1, window_frames - overlap_frames)
    for tid in np.unique(ids):
        rows = np.flatnonzero(ids == tid)
        rows = rows[np.argsort(pos[rows], kind="stable")]
        lo, hi = int(pos[rows].min()), int(pos[rows].max())
        start = lo
        while True:
            sel = rows[(pos[rows] >= start) & (pos[rows] < start + window_frames)]
            if len(sel):
                out.append(sel)
            if start + window_frames > hi:
                break
            start += step
    return out


def keep_centre(win_rows: list[np.ndarray], position, n_rows: int) -> np.ndarray:
    """(R,) index of the window each row takes its result from: the one where it lies farthest
    from the window's ends (in frame positions)."""
    pos = np.asarray(position).reshape(-1)
    best = np.full(n_rows, -1)
    margin = np.full(n_rows, -np.inf)
    for w, rows in enumerate(win_rows):
        p = pos[rows]
        m = np.minimum(p - p.min(), p.max() - p)
        better = m > margin[rows]
        best[rows[better]] = w
        margin[rows[better]] = m[better]
    return best


def refine_tracks(
    fit,
    fits: BodyParams,
    track_id,
    stamps_s,
    position,
    T_ref_from_cam,
    step_s: float,
    settings: RefineSettings,
):
    """Refit R rows (cam frame bodies ``fits``, shapes already the tracks') with the acceleration
    penalty. fit: a callable (rows (n,) int64, init BodyParams of those rows, coupling) ->
    tasks.fit.optimize.FitResult that refits those rows with the data terms, the shape frozen
    and no rigid alignment (the stage binds its keypoints, points and settings); track_id (R,),
    stamps_s (R,) seconds, position (R,) frame positions; T_ref_from_cam (R, 4, 4) float64: each
    row's camera in a world-fixed frame; step_s: the nominal frame step. Returns BodyParams
    (cam frame) of the R rows and the residuals of each row's final refit (dict of (R,)).
    """
    s = settings
    R = len(fits)
    ids = np.asarray(track_id, np.int64)
    t = np.asarray(stamps_s, np.float64)
    T = np.asarray(T_ref_from_cam, np.float64)
    win = windows(ids, position, s.window_frames, s.overlap_frames)
    take = keep_centre(win, position, R)
    out = {k: np.array(getattr(fits, k), np.float32, copy=True) for k in _FIELDS}
    residuals: dict[str, np.ndarray] = {}
    # windows packed into batches of about batch_rows rows
    batches, cur = [], []
    for w, rows in enumerate(win):
        if cur and sum(len(win[v]) for v in cur) + len(rows) > s.batch_rows:
            batches.append(cur)
            cur = []
        cur.append(w)
    if cur:
        batches.append(cur)
    for batch in batches:
        rows = np.concatenate([win[w] for w in batch])
        which = np.concatenate([np.full(len(win[w]), w) for w in batch])
        # neighbours inside the batch: same window only (a window's rows are consecutive)
        local_ids = which.astype(np.int64)
        prev, nxt = neighbours(local_ids, t[rows], s.tie_max_step_s)
        coef = divided_difference_coefficients(t[rows], prev, nxt, step_s)
        # a world-fixed frame near each window: its first row's camera
        first = {w: rows[which == w][0] for w in batch}
        T_ref = np.stack([np.linalg.inv(T[first[w]]) @ T[r] for r, w in zip(rows, which)])
        penalty = AccelerationPenalty(
            T_ref, prev, nxt, coef, s.joint_weight, s.torso_weight, s.root_weight
        )
        result = fit(rows, fits.take(rows), penalty)
        mine = take[rows] == which
        for k in _FIELDS:
            out[k][rows[mine]] = getattr(result, k)[mine]
        for k, v in result.residuals.items():
            residuals.setdefault(k, np.zeros(R))[rows[mine]] = np.asarray(v)[mine]
    return BodyParams(*(out[k] for k in _FIELDS)), residuals


_FIELDS = BodyParams.FIELDS


def acceleration_error(track_id, stamps_s, pred, truth, max_step_s: float = np.inf):
    """Per row with two neighbours the mean over points of |a_pred - a_truth| (R,) (NaN
    elsewhere) and the mask of such rows: pred / truth (R, J, 3) points (joints) in a frame fixed
    to the world, m; a = the second divided difference of the row's track (m/s^2). Multiply by
    step^2 for m/frame^2."""
    ids = np.asarray(track_id).reshape(-1)
    t = np.asarray(stamps_s, np.float64).reshape(-1)
    prev, nxt = neighbours(ids, t, max_step_s)
    coef = divided_difference_coefficients(t, prev, nxt, 1.0)
    ok = (prev >= 0) & (nxt >= 0)
    out = np.full(len(ids), np.nan)
    if ok.any():
        p, g = np.asarray(pred, np.float64), np.asarray(truth, np.float64)

        def acc(x):
            c = coef[ok]
            return (
                c[:, 0, None, None] * x[prev[ok]]
                + c[:, 1, None, None] * x[ok]
                + c[:, 2, None, None] * x[nxt[ok]]
            )

        out[ok] = np.linalg.norm(acc(p) - acc(g), axis=-1).mean(-1)
    return out, ok
