"""Left / right swaps of 2D keypoints, decided along a track (beyond the paper).

Top-down keypoint detectors (BlazePose, ViTPose) often label a person seen from behind as if
seen from the front: every left keypoint is called right and vice versa. A fit that follows them
turns the body round. For each detection there are two candidates, the keypoints as labelled and
mirrored (:func:`tasks.fit.init_lidar.mirrored`), and for each a heading cost over candidate
headings (:class:`tasks.fit.init_lidar.FacingCosts`: LiDAR shape and keypoint layout). A track's
rows are decided together by dynamic programming over the states (labelling, heading) of its
rows, minimising

    sum_t [ cost_t(state) + motion_weight * m_t (1 - cos(yaw(state) - walking direction_t)) ]
    + smooth_weight * sum_t (1 - cos(yaw_t - yaw_t+1)),

with m_t in [0, 1] growing with the track's speed from ``walking_min_speed_mps`` to
``walking_full_speed_mps``
(people walk forwards; a standing person's position says nothing) and the smoothness term between
rows at most ``smooth_max_step_s`` apart (a body does not turn round in a fifth of a second). Each row's
labelling is the one of its cheapest min-marginal; where the two labellings' min-marginals differ
by less than ``min_margin`` the evidence is too weak and the row keeps its keypoints as detected
(counted as undecided).

Yaw angles are about the world's z axis (up), in radians; facing directions arrive in the camera
frame with each row's ``R_world_from_cam``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tasks.fit.settings import FlipSettings


@dataclass(frozen=True)
class FlipDecision:
    """Per row: mirrored (R,) bool: fit the mirrored keypoints; heading (R,) int64: the chosen
    candidate heading (index into the FacingCosts candidates); margin (R,) float64: min-marginal
    cost of the other labelling minus the chosen one's (>= 0); decided (R,) bool: margin >=
    min_margin (else kept as detected); speed_mps (R,) float64: the track's speed there; chains
    (R, 3) bool or None: the chains (:data:`CHAINS`: face, arms, legs) relabelled afterwards
    towards the start (:func:`chains_towards`, ``follow_start``); dropped (R, 17) bool or None:
    keypoints dropped as far from the start (:func:`far_from_start`)."""

    mirrored: np.ndarray
    heading: np.ndarray
    margin: np.ndarray
    decided: np.ndarray
    speed_mps: np.ndarray
    chains: np.ndarray | None = None
    dropped: np.ndarray | None = None

    def counts(self) -> dict[str, int]:
        """How many rows were flipped, kept as detected by decision, and left undecided; with
        chains, how many rows had a chain relabelled towards the start; with dropped, how many
        keypoints were dropped as far from it."""
        out = {
            "flipped": int((self.mirrored & self.decided).sum()),
            "kept": int((~self.mirrored & self.decided).sum()),
            "undecided": int((~self.decided).sum()),
        }
        if self.chains is not None:
            out["chains_to_start"] = int(self.chains.any(1).sum())
        if self.dropped is not None:
            out["keypoints_dropped"] = int(self.dropped.sum())
        return out


def track_velocities_ls(
    track_id: np.ndarray, stamps_s: np.ndarray, position_world: np.ndarray, window_s: float
) -> np.ndarray:
    """Per row the slope (R, 3) m/s of a least-squares line through its track's positions
    (R, 3) (world frame, m) within ``window_s`` of it; zero where fewer than two rows span time."""
    ids = np.asarray(track_id).reshape(-1)
    t = np.asarray(stamps_s, np.float64).reshape(-1)
    p = np.asarray(position_world, np.float64).reshape(-1, 3)
    out = np.zeros_like(p)
    for tid in np.unique(ids):
        rows = np.flatnonzero(ids == tid)
        tt, pp = t[rows], p[rows]
        for k, r in enumerate(rows):
            near = np.abs(tt - tt[k]) <= window_s + 1e-9
            dt = tt[near] - tt[near].mean()
            den = float(dt @ dt)
            if near.sum() >= 2 and den > 0:
                out[r] = dt @ (pp[near] - pp[near].mean(0)) / den
    return out


def decide_flips(
    track_id,
    stamps_s,
    position_world,
    facing_cam,
    cost,
    R_world_from_cam,
    settings: FlipSettings,
) -> FlipDecision:
    """Decide, for R detections, between their keypoints as labelled and mirrored.

    track_id (R,) int; stamps_s (R,) float seconds; position_world (R, 3) m: where the person is
    (e.g. the median of its LiDAR points), world frame; facing_cam (R, Y, 3): each row's candidate
    facing directions, cam frame, and cost (R, 2, Y) their costs for the keypoints as labelled
    [:, 0] and mirrored [:, 1] (:class:`tasks.fit.init_lidar.FacingCosts`); R_world_from_cam
    (R, 3, 3) or (3, 3). A track of one row is decided by its own costs and walking direction
    (none: kept as detected).
    """
    s = settings
    ids = np.asarray(track_id, np.int64).reshape(-1)
    t = np.asarray(stamps_s, np.float64).reshape(-1)
    cost = np.asarray(cost, np.float64)
    R_rows, _, Y = cost.shape
    Rw = np.broadcast_to(np.asarray(R_world_from_cam, np.float64), (R_rows, 3, 3))
    f_world = np.einsum("rij,ryj->ryi", Rw, np.asarray(facing_cam, np.float64))
    yaw = np.arctan2(f_world[..., 1], f_world[..., 0])  # (R, Y)
    vel = track_velocities_ls(ids, t, position_world, s.velocity_window_s)
    speed = np.linalg.norm(vel[:, :2], axis=1)
    if not s.enabled:
        heading = np.argmin(cost[:, 0], axis=1)
        return FlipDecision(
            np.zeros(R_rows, bool), heading, np.zeros(R_rows), np.zeros(R_rows, bool), speed
        )
    walk = np.arctan2(vel[:, 1], vel[:, 0])
    m = np.clip(
        (speed - s.walking_min_speed_mps)
        / max(s.walking_full_speed_mps - s.walking_min_speed_mps, 1e-9),
        0,
        1,
    )
    unary = (
        s.cost_weight * cost
        + (s.motion_weight * m)[:, None, None] * (1.0 - np.cos(yaw - walk[:, None]))[:, None, :]
    )  # (R, 2, Y)
    mirrored = np.zeros(R_rows, bool)
    heading = np.zeros(R_rows, np.int64)
    margin = np.zeros(R_rows)
    for tid in np.unique(ids):
        rows = np.flatnonzero(ids == tid)
        rows = rows[np.argsort(t[rows], kind="stable")]
        mm = _min_marginals(unary[rows].reshape(len(rows), 2 * Y), yaw[rows], t[rows], s)
        per_label = mm.reshape(len(rows), 2, Y).min(2)  # (n, 2)
        lab = np.argmin(per_label, axis=1)
        mirrored[rows] = lab == 1
        margin[rows] = np.abs(per_label[:, 1] - per_label[:, 0])
        heading[rows] = np.argmin(mm.reshape(len(rows), 2, Y)[np.arange(len(rows)), lab], axis=1)
    decided = margin >= s.min_margin
    # undecided rows keep their keypoints as detected, with that labelling's best heading
    keep = ~decided & mirrored
    if keep.any():
        mirrored[keep] = False
        heading[keep] = np.argmin(unary[keep, 0], axis=1)
    return FlipDecision(mirrored, heading, margin, decided, speed)


def _min_marginals(unary: np.ndarray, yaw: np.ndarray, t: np.ndarray, s: FlipSettings):
    """Min-sum forward-backward on a chain: unary (n, S) over states S = 2 x Y (labelling,
    heading), yaw (n, Y) of each row's headings; the pairwise cost between consecutive rows is
    smooth_weight (1 - cos(yaw difference)) when they are at most smooth_max_step_s apart. Returns the
    min-marginals (n, S): the cheapest total cost of a labelling of the whole chain with that
    row in that state."""
    n, S = unary.shape
    ys = np.concatenate([yaw, yaw], axis=1)  # (n, S): a state's yaw
    fwd = np.empty((n, S))
    bwd = np.zeros((n, S))
    fwd[0] = unary[0]
    pair = []
    for k in range(1, n):
        if t[k] - t[k - 1] <= s.smooth_max_step_s:
            P = s.smooth_weight * (1.0 - np.cos(ys[k - 1][:, None] - ys[k][None, :]))  # (S, S)
        else:
            P = np.zeros((S, S))
        pair.append(P)
        fwd[k] = unary[k] + (fwd[k - 1][:, None] + P).min(0)
    for k in range(n - 2, -1, -1):
        bwd[k] = (pair[k] + (unary[k + 1] + bwd[k + 1])[None, :]).min(1)
    return fwd + bwd


#: COCO-17 left / right chains relabelled as one (left indices, right indices): the face's eyes
#: and ears, the arms, the legs. BlazePose may swap one chain and not the others (e.g. the legs
#: of a person seen from behind)
CHAINS: tuple[tuple[tuple[int, ...], tuple[int, ...]], ...] = (
    ((1, 3), (2, 4)),
    ((5, 7, 9), (6, 8, 10)),
    ((11, 13, 15), (12, 14, 16)),
)


def chains_towards(
    keypoints, start_uv, rows, min_confidence: float, margin: float
) -> tuple[np.ndarray, np.ndarray]:
    """Relabel left / right per chain (:data:`CHAINS`) of some rows towards a start body.

    keypoints (R, 17, 3) (u, v, confidence) px; start_uv (R, 17, 2) px: the start bodies'
    projected COCO-17 keypoints (e.g. a provider's estimate); rows (R,) bool: which rows may be
    relabelled (e.g. those the track left undecided). Per row and chain, over its left / right
    pairs whose two keypoints are both at least ``min_confidence``: the mean distance of the
    keypoints as labelled and chain-swapped to the start's, in units of the start's projected
    height (its keypoints' vertical extent); the chain is swapped when that is smaller by more
    than ``margin``. Returns the keypoints (relabelled where swapped) and swapped (R, 3) bool,
    one column per chain."""
    kp = np.array(keypoints, np.float64, copy=True)
    uv = np.asarray(start_uv, np.float64)
    R = len(kp)
    rows = np.asarray(rows, bool).reshape(R)
    swapped = np.zeros((R, len(CHAINS)), bool)
    if R == 0:
        return kp, swapped
    height = _start_height(uv)
    for c, (left, right) in enumerate(CHAINS):
        L, Rt = list(left), list(right)
        ok = (kp[:, L, 2] >= min_confidence) & (kp[:, Rt, 2] >= min_confidence)  # (R, n)
        n = ok.sum(1)
        d_as = np.linalg.norm(kp[:, L, :2] - uv[:, L], axis=-1) + np.linalg.norm(
            kp[:, Rt, :2] - uv[:, Rt], axis=-1
        )
        d_sw = np.linalg.norm(kp[:, Rt, :2] - uv[:, L], axis=-1) + np.linalg.norm(
            kp[:, L, :2] - uv[:, Rt], axis=-1
        )
        mean_as = (d_as * ok).sum(1) / np.maximum(2 * n, 1) / height
        mean_sw = (d_sw * ok).sum(1) / np.maximum(2 * n, 1) / height
        swap = rows & (n > 0) & (mean_sw + margin < mean_as)
        swapped[:, c] = swap
        if swap.any():
            idx = np.flatnonzero(swap)
            a, b = kp[np.ix_(idx, L)].copy(), kp[np.ix_(idx, Rt)].copy()
            kp[np.ix_(idx, L)], kp[np.ix_(idx, Rt)] = b, a
    return kp, swapped


def far_from_start(keypoints, start_uv, rows, max_distance: float) -> tuple[np.ndarray, np.ndarray]:
    """Drop (confidence 0) the keypoints of some rows that lie farther than ``max_distance``
    start heights from the start body's projected keypoint (e.g. a person cut by the image
    border, whose keypoints a detector squeezes into the visible part).

    keypoints (R, 17, 3), start_uv (R, 17, 2) px, rows (R,) bool as :func:`chains_towards`.
    Returns the keypoints and dropped (R, 17) bool."""
    kp = np.array(keypoints, np.float64, copy=True)
    uv = np.asarray(start_uv, np.float64)
    if len(kp) == 0:
        return kp, np.zeros((0, 17), bool)
    height = _start_height(uv)
    dist = np.linalg.norm(kp[..., :2] - uv, axis=-1) / height[:, None]
    dropped = np.asarray(rows, bool)[:, None] & (dist > max_distance) & (kp[..., 2] > 0)
    kp[..., 2] = np.where(dropped, 0.0, kp[..., 2])
    return kp, dropped


def _start_height(start_uv: np.ndarray) -> np.ndarray:
    """(R,) the start bodies' projected heights (px; their keypoints' vertical extent, >= 1)."""
    return np.maximum(np.ptp(start_uv[..., 1], axis=1), 1.0)
