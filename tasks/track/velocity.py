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


def velocities_in_base(track_ids: np.ndarray, stamps_s: np.ndarray, positions_lidar: np.ndarray,
                       T_world_from_lidar: np.ndarray, T_base_from_lidar: np.ndarray) -> np.ndarray:
    """Ground-plane velocity of every row in the robot's base frame at that row's frame.

    positions_lidar: (R, 3) float metres, each in the LiDAR frame of its own frame, whose pose is
    T_world_from_lidar (R, 4, 4) float64. Velocities come from :func:`track_velocities` on the
    world positions (robot motion removed), then rotated into the base frame of the row's frame.
    Returns (R, 2) float64 (vx, vy) m/s.
    """
    T = np.asarray(T_world_from_lidar, np.float64).reshape(-1, 4, 4)
    p = np.asarray(positions_lidar, np.float64).reshape(-1, 3)
    world = np.einsum("rij,rj->ri", T[:, :3, :3], p) + T[:, :3, 3]
    v_world = track_velocities(track_ids, stamps_s, world)
    R_base_from_world = np.asarray(T_base_from_lidar, np.float64)[:3, :3] @ np.transpose(T[:, :3, :3], (0, 2, 1))
    return np.einsum("rij,rj->ri", R_base_from_world, v_world)[:, :2]
