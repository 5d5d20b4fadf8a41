"""Bodies for the frames inside a track that have no detection (the tracker coasted over a missed
detection), interpolated from the track's fits on either side (beyond the paper).

For a gap of at most ``max_gap_frames`` frame positions between two fitted rows of a track, each
missing frame gets a body: the two fits moved into the world (robot motion removed), every joint
rotation (the root's in the world, the others local) interpolated by slerp, the root joint along
the straight line between them, the shape of the earlier fit; then moved into the missing
frame's LiDAR frame. The body is checked against that frame's sweep:
- the LiDAR points near it (within ``align_max_m`` + ``support_radius_m`` of the mesh) pull it by
  a translation (a few nearest-vertex steps, at most ``align_max_m``); if ``min_support_points``
  of them then lie within ``support_radius_m`` of its surface, it is kept ("supported");
- otherwise the rays of the sweep through the body's direction (its angular footprint seen from
  the sensor) decide: more of them pass the body and return from behind it than stop in front
  of it or on it (at least ``min_support_points``): the sensor saw through where the body would
  be, and it is dropped ("seen through"); else it is kept ("occluded" when something in front
  hides it, "unobserved" when the sweep says nothing there).

Frames: the LiDAR frame of each frame (x forwards, y left, z up), poses T_world_from_lidar (4, 4)
float64; axis-angle in radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from tasks.body.params import BodyParams
from tasks.body.rotations import (
    axis_angle_to_matrix,
    matrix_to_quaternion,
    quaternion_to_axis_angle,
)
from tasks.fit.reframe import reframe_params
from tasks.fit.settings import GapSettings

_FIELDS = BodyParams.FIELDS
#: check outcomes (the GapBodies.status codes)
SUPPORTED, OCCLUDED, UNOBSERVED, SEEN_THROUGH = 0, 1, 2, 3
STATUS_NAMES = ("supported", "occluded", "unobserved", "seen through")


@dataclass(frozen=True)
class Gap:
    """The missing frames of tracks: track_id (G,), position (G,) the missing frame position,
    before / after (G,) the fitted rows on either side, alpha (G,) in (0, 1): where the frame
    lies between them in time."""

    track_id: np.ndarray
    position: np.ndarray
    before: np.ndarray
    after: np.ndarray
    alpha: np.ndarray

    def __len__(self) -> int:
        return len(self.track_id)

    def only(self, positions) -> Gap:
        """The gaps at these frame positions only (the frames whose sweep may be read: a frame
        the detect stage left out for bad input is never read, so never filled)."""
        keep = np.isin(self.position, np.asarray(list(positions), np.int64))
        return Gap(*(a[keep] for a in (self.track_id, self.position, self.before, self.after,
                                       self.alpha)))  # fmt: skip


def find_gaps(track_id, position, stamps_s, max_gap_frames: int) -> Gap:
    """The frame positions missing inside each track (R rows: track_id (R,), position (R,) frame
    positions; stamps_s (F,) seconds per frame position) where the run of missing positions is
    at most ``max_gap_frames`` long."""
    ids = np.asarray(track_id, np.int64).reshape(-1)
    pos = np.asarray(position, np.int64).reshape(-1)
    t = np.asarray(stamps_s, np.float64)
    out = {k: [] for k in ("track_id", "position", "before", "after", "alpha")}
    for tid in np.unique(ids):
        rows = np.flatnonzero(ids == tid)
        rows = rows[np.argsort(pos[rows], kind="stable")]
        for a, b in zip(rows[:-1], rows[1:]):
            missing = np.arange(pos[a] + 1, pos[b])
            if 0 < len(missing) <= max_gap_frames:
                for p in missing:
                    out["track_id"].append(tid)
                    out["position"].append(p)
                    out["before"].append(a)
                    out["after"].append(b)
                    out["alpha"].append((t[p] - t[pos[a]]) / (t[pos[b]] - t[pos[a]]))
    return Gap(
        *(
            np.asarray(out[k], np.float64 if k == "alpha" else np.int64)
            for k in ("track_id", "position", "before", "after", "alpha")
        )
    )


def interpolate_bodies(
    model, fits: BodyParams, gaps: Gap, T_world_from_lidar: np.ndarray, position
) -> BodyParams:
    """Bodies of the G missing frames (each in its own frame's LiDAR frame) from the fits (R
    rows, each in the LiDAR frame of its frame position ``position`` (R,)); T_world_from_lidar
    (F, 4, 4) per frame position."""
    if len(gaps) == 0:
        z = np.zeros
        return BodyParams(*(z((0, n), np.float32) for n in (10, 3, 69, 3)))
    pos = np.asarray(position, np.int64)
    T = np.asarray(T_world_from_lidar, np.float64)
    a = _to_world(model, fits, gaps.before, T[pos[gaps.before]])
    b = _to_world(model, fits, gaps.after, T[pos[gaps.after]])
    w = gaps.alpha[:, None]
    rot = _slerp_axis_angle(
        np.concatenate([a.global_orient, a.body_pose], 1).reshape(-1, 24, 3),
        np.concatenate([b.global_orient, b.body_pose], 1).reshape(-1, 24, 3),
        gaps.alpha,
    ).reshape(-1, 72)
    betas = a.betas
    with torch.no_grad():
        j0 = model.rest_joints(torch.as_tensor(betas, dtype=torch.float32))[:, 0].double().numpy()
        j0b = (
            model.rest_joints(torch.as_tensor(b.betas, dtype=torch.float32))[:, 0].double().numpy()
        )
    root = (1 - w) * (j0 + a.transl) + w * (j0b + b.transl)  # the posed root joint, world
    world = BodyParams(
        betas.astype(np.float32),
        rot[:, :3].astype(np.float32),
        rot[:, 3:].astype(np.float32),
        (root - j0).astype(np.float32),
    )
    parts = [
        reframe_params(model, world.take(slice(g, g + 1)), np.linalg.inv(T[gaps.position[g]]))
        for g in range(len(gaps))
    ]
    return BodyParams(*(np.concatenate([getattr(p, f) for p in parts]) for f in _FIELDS))


def _to_world(model, fits: BodyParams, rows, T_world_from_lidar) -> BodyParams:
    parts = [
        reframe_params(model, fits.take(slice(r, r + 1)), T_world_from_lidar[k])
        for k, r in enumerate(rows)
    ]
    return BodyParams(
        *(np.concatenate([getattr(p, f) for p in parts]).astype(np.float64) for f in _FIELDS)
    )


def _slerp_axis_angle(a: np.ndarray, b: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Slerp between rotations a and b (G, J, 3) axis-angle at alpha (G,) -> (G, J, 3)."""
    qa = matrix_to_quaternion(axis_angle_to_matrix(torch.as_tensor(a))).numpy()
    qb = matrix_to_quaternion(axis_angle_to_matrix(torch.as_tensor(b))).numpy()
    dot = (qa * qb).sum(-1, keepdims=True)
    qb = np.where(dot < 0, -qb, qb)  # the shorter way round
    dot = np.abs(dot).clip(max=1.0)
    theta = np.arccos(dot)
    t = np.asarray(alpha, np.float64)[:, None, None]
    small = theta < 1e-6
    s = np.sin(theta)
    wa = np.where(small, 1 - t, np.sin((1 - t) * theta) / np.where(small, 1.0, s))
    wb = np.where(small, t, np.sin(t * theta) / np.where(small, 1.0, s))
    q = wa * qa + wb * qb
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return quaternion_to_axis_angle(torch.as_tensor(q)).numpy()


@dataclass(frozen=True)
class GapCheck:
    """Outcome of checking one interpolated body against its frame's sweep: keep, status (one
    of SUPPORTED, OCCLUDED, UNOBSERVED, SEEN_THROUGH), shift (3,) m applied, support (points on
    its surface), near (the points used for the check)."""

    keep: bool
    status: int
    shift: np.ndarray
    support: int
    behind: int
    front: int


def check_body(vertices_lidar: np.ndarray, points_lidar: np.ndarray, s: GapSettings) -> GapCheck:
    """Check one interpolated body, vertices (V, 3) in its frame's LiDAR frame (m), against that
    frame's sweep points_lidar (N, 3) (same frame; the sensor at the origin). See the module
    docstring."""
    from scipy.spatial import cKDTree

    v = np.asarray(vertices_lidar, np.float64)
    p = np.asarray(points_lidar, np.float64)
    reach = s.align_max_m + s.support_radius_m
    lo, hi = v.min(0) - reach, v.max(0) + reach
    near = p[np.all((p >= lo) & (p <= hi), axis=1)]
    shift = np.zeros(3)
    tree = cKDTree(v)
    if len(near):
        for _ in range(5):
            d, i = tree.query(near - shift, distance_upper_bound=reach)
            ok = np.isfinite(d)
            if ok.sum() < s.min_support_points:
                break
            step = np.median(near[ok] - shift - v[i[ok]], axis=0)
            shift = shift + step
            n = np.linalg.norm(shift)
            if n > s.align_max_m:
                shift *= s.align_max_m / n
            if np.linalg.norm(step) < 1e-3:
                break
        d, _ = tree.query(near - shift)
        support = int((d < s.support_radius_m).sum())
    else:
        support = 0
    if support >= s.min_support_points:
        return GapCheck(True, SUPPORTED, shift, support, 0, 0)
    # the sweep's rays through the body's angular footprint: in front of it, or through it
    vs = _spherical(v)
    ps = _spherical(p)
    az_lo, az_hi = _azimuth_range(vs[:, 0])
    inside = (
        _azimuth_inside(ps[:, 0], az_lo, az_hi)
        & (ps[:, 1] >= vs[:, 1].min())
        & (ps[:, 1] <= vs[:, 1].max())
    )
    body_range = float(np.median(vs[:, 2]))
    r = ps[inside, 2]
    behind = int((r > body_range + s.behind_margin_m).sum())
    front = int((r < body_range - s.behind_margin_m).sum())
    if behind >= s.min_support_points and behind > front + support:
        return GapCheck(False, SEEN_THROUGH, shift, support, behind, front)
    status = OCCLUDED if front >= s.min_support_points else UNOBSERVED
    return GapCheck(True, status, shift, support, behind, front)


def _spherical(x: np.ndarray) -> np.ndarray:
    """(N, 3) azimuth, elevation (rad), range (m) of points (N, 3) seen from the origin."""
    r = np.linalg.norm(x, axis=1)
    return np.stack(
        [np.arctan2(x[:, 1], x[:, 0]), np.arcsin(np.clip(x[:, 2] / np.maximum(r, 1e-9), -1, 1)), r],
        1,
    )


def _azimuth_range(az: np.ndarray) -> tuple[float, float]:
    """The smallest azimuth interval (lo, hi) (rad, lo may exceed hi across +-pi) holding az."""
    a = np.sort(np.mod(az, 2 * np.pi))
    gaps = np.diff(np.r_[a, a[0] + 2 * np.pi])
    k = int(np.argmax(gaps))
    return float(a[(k + 1) % len(a)]), float(a[k])


def _azimuth_inside(az: np.ndarray, lo: float, hi: float) -> np.ndarray:
    a = np.mod(az, 2 * np.pi)
    return (a >= lo) & (a <= hi) if lo <= hi else (a >= lo) | (a <= hi)


def shifted(model, params: BodyParams, shift_lidar: np.ndarray) -> BodyParams:
    """Bodies (LiDAR frame) moved by translations shift_lidar (G, 3) m."""
    return BodyParams(
        params.betas,
        params.global_orient,
        params.body_pose,
        (np.asarray(params.transl, np.float64) + shift_lidar).astype(np.float32),
    )
