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
    if s.root_cutoff_hz > 0 or s.orient_cutoff_hz > 0 or s.pose_cutoff_hz > 0:
        fits = smooth_tracks(fits, ids, t, T, step_s, s)
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


def whittaker_lambda(cutoff_hz: float, step_s: float) -> float:
    """The Whittaker smoother's weight on the squared second differences (per frame^2) that
    halves a sine of frequency ``cutoff_hz`` at frame step ``step_s``: its gain at frequency f
    is 1 / (1 + lam (2 - 2 cos 2 pi f step)^2) ~ 1 / (1 + (f / f_c)^4) for f well below the
    rate, with lam = 1 / (2 pi f_c step)^4: the same cut-off at every rate."""
    return 1.0 / (2.0 * np.pi * float(cutoff_hz) * float(step_s)) ** 4


def whittaker_smooth(y, prev, nxt, coef, lam) -> np.ndarray:
    """Minimiser x (R, D) of sum_r |x_r - y_r|^2 + lam_r |a_r|^2 with a_r = coef[r] . (x_prev,
    x_r, x_next) (the scaled second divided difference of rows with both neighbours, rows of one
    chain linked by prev / nxt (R,) int64, -1 none); lam: scalar or (D,) per column. Exact: one
    sparse (pentadiagonal along a chain) solve per column weight, so a track of thousands of
    frames costs linear time and memory."""
    from scipy.sparse import csr_matrix, identity
    from scipy.sparse.linalg import splu

    y = np.asarray(y, np.float64)
    R, D = y.shape
    lam = np.broadcast_to(np.asarray(lam, np.float64), (D,))
    rows = np.flatnonzero((prev >= 0) & (nxt >= 0))
    m = np.arange(len(rows))
    Dm = csr_matrix(
        (
            np.concatenate([coef[rows, 0], coef[rows, 1], coef[rows, 2]]),
            (np.concatenate([m, m, m]), np.concatenate([prev[rows], rows, nxt[rows]])),
        ),
        shape=(len(rows), R),
    )  # one row per interior row (duplicate entries sum)
    DtD = (Dm.T @ Dm).tocsc()
    out = np.empty_like(y)
    for value in np.unique(lam):
        cols = np.flatnonzero(lam == value)
        out[:, cols] = splu((identity(R, format="csc") + value * DtD).tocsc()).solve(y[:, cols])
    return out


def _rotations_smooth(aa, prev, nxt, coef, lam) -> np.ndarray:
    """Smooth rotations (R, K, 3) axis-angle: the Whittaker smoother on the matrices' entries,
    projected back onto rotations (nearest in Frobenius norm)."""
    R, K = aa.shape[:2]
    M = _aa_to_matrix(aa)
    S = whittaker_smooth(M.reshape(R, K * 9), prev, nxt, coef, lam).reshape(R, K, 3, 3)
    U, _, Vt = np.linalg.svd(S)
    d = np.sign(np.linalg.det(U @ Vt))
    U[..., :, 2] *= d[..., None]
    return _matrix_to_aa(U @ Vt)


def smooth_tracks(
    fits: BodyParams, track_id, stamps_s, T_world_from_cam, step_s: float, settings
) -> BodyParams:
    """The closed-form start of the refinement: each track's pelvis path and global
    orientation (in a world-fixed frame) and its body pose (local joint rotations) through a
    Whittaker smoother of cut-off ``settings.root_cutoff_hz`` / ``orient_cutoff_hz`` /
    ``pose_cutoff_hz`` (0: that part as fitted); neighbours farther apart than
    ``tie_max_step_s`` split a track. fits cam frame; T_world_from_cam (R, 4, 4)."""
    s = settings
    ids = np.asarray(track_id, np.int64)
    t = np.asarray(stamps_s, np.float64)
    T = np.asarray(T_world_from_cam, np.float64)
    prev, nxt = neighbours(ids, t, s.tie_max_step_s)
    coef = divided_difference_coefficients(t, prev, nxt, step_s)
    # one solve per track (its rows renumbered 0..n-1): chains never share a term
    go = np.array(fits.global_orient, np.float64)
    pose = np.array(fits.body_pose, np.float64)
    transl = np.array(fits.transl, np.float64)
    Rwc = T[:, :3, :3]
    for tid in np.unique(ids):
        rows = np.flatnonzero(ids == tid)
        if len(rows) < 3:
            continue
        loc = -np.ones(len(ids), np.int64)
        loc[rows] = np.arange(len(rows))
        p = np.where(prev[rows] >= 0, loc[np.maximum(prev[rows], 0)], -1)
        n = np.where(nxt[rows] >= 0, loc[np.maximum(nxt[rows], 0)], -1)
        c = coef[rows]
        if s.root_cutoff_hz > 0:
            # pelvis = R_wc (J0 + transl) + t_wc; J0 is the track's: smoothing moves transl by
            # R_cw (smoothed - fitted) of the world position of transl itself
            w = np.einsum("rij,rj->ri", Rwc[rows], transl[rows]) + T[rows, :3, 3]
            ws = whittaker_smooth(w, p, n, c, whittaker_lambda(s.root_cutoff_hz, step_s))
            transl[rows] += np.einsum("rji,rj->ri", Rwc[rows], ws - w)
        if s.orient_cutoff_hz > 0:
            Rw = Rwc[rows] @ _aa_to_matrix(go[rows])
            aw = _rotations_smooth(
                _matrix_to_aa(Rw)[:, None], p, n, c, whittaker_lambda(s.orient_cutoff_hz, step_s)
            )[:, 0]
            go[rows] = _matrix_to_aa(np.transpose(Rwc[rows], (0, 2, 1)) @ _aa_to_matrix(aw))
        if s.pose_cutoff_hz > 0:
            pose[rows] = _rotations_smooth(
                pose[rows].reshape(len(rows), 23, 3),
                p,
                n,
                c,
                whittaker_lambda(s.pose_cutoff_hz, step_s),
            ).reshape(len(rows), 69)
    f32 = np.float32
    return BodyParams(
        np.asarray(fits.betas, f32), go.astype(f32), pose.astype(f32), transl.astype(f32)
    )


def _aa_to_matrix(aa) -> np.ndarray:
    from tasks.body.rotations import axis_angle_to_matrix

    return axis_angle_to_matrix(torch.as_tensor(np.asarray(aa, np.float64))).numpy()


def _matrix_to_aa(M) -> np.ndarray:
    from tasks.body.rotations import matrix_to_axis_angle

    return matrix_to_axis_angle(torch.as_tensor(np.asarray(M, np.float64))).numpy()
