"""Per-track velocities from positions over time (the paper's pedestrian velocity task)."""

from __future__ import annotations

import numpy as np

from tasks.geometry import transform_points


def track_velocities(
    track_ids: np.ndarray, stamps_s: np.ndarray, positions: np.ndarray
) -> np.ndarray:
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


def velocities_in_base(
    track_ids: np.ndarray,
    stamps_s: np.ndarray,
    positions_lidar: np.ndarray,
    T_world_from_lidar: np.ndarray,
    T_base_from_lidar: np.ndarray,
) -> np.ndarray:
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
    R_base_from_world = np.asarray(T_base_from_lidar, np.float64)[:3, :3] @ np.transpose(
        T[:, :3, :3], (0, 2, 1)
    )
    return np.einsum("rij,rj->ri", R_base_from_world, v_world)[:, :2]


def track_neighbours(
    track_ids: np.ndarray, stamps_s: np.ndarray, max_gap_s: float = np.inf
) -> tuple[np.ndarray, np.ndarray]:
    """The row of the same track just before and just after each row in time.

    track_ids: (R,) int; stamps_s: (R,) float seconds. A neighbour farther than ``max_gap_s`` from
    the row is not used (-1), so a difference never spans a long run of frames whose fit is
    missing or was dropped. Returns (previous (R,), next (R,)) int64 row indices, -1 = none.
    """
    ids = np.asarray(track_ids).reshape(-1)
    t = np.asarray(stamps_s, np.float64).reshape(-1)
    if len(ids) != len(t):
        raise ValueError(f"track_neighbours: {len(ids)} ids, {len(t)} stamps")
    prev = np.full(len(ids), -1, np.int64)
    nxt = np.full(len(ids), -1, np.int64)
    order = np.lexsort((t, ids))
    same = ids[order[1:]] == ids[order[:-1]]
    gap = t[order[1:]] - t[order[:-1]]
    ok = same & (gap > 0) & (gap <= max_gap_s)
    prev[order[1:][ok]] = order[:-1][ok]
    nxt[order[:-1][ok]] = order[1:][ok]
    return prev, nxt


def vertex_velocities_in_base(
    vertices_lidar: list,
    T_world_from_lidar: list,
    stamps_s: list,
    T_base_from_lidar: np.ndarray,
    fallback_base: np.ndarray,
) -> np.ndarray:
    """Per-vertex velocity of one body in one frame from its neighbours along the track.

    vertices_lidar: [previous, this, next] (or [.., second previous, previous, this, next, second
    next, ..], this in the middle): (V, 3) float metres (the same topology), each in the
    LiDAR frame of its own frame, whose pose is the matching T_world_from_lidar (4, 4) float64;
    previous / next None where the track has none (:func:`track_neighbours`). stamps_s: the three
    times, seconds. The vertices go to the world (robot motion removed), then: with more than
    three frames, the slope at this frame of the polynomial through all of them
    (:func:`derivative_weights`; five equal steps: (x-2 - 8 x-1 + 8 x1 - x2) / 12 h, which damps
    a sine of 1 Hz at 5 Hz by 7 %, the central difference by 24 %); central difference with both
    direct neighbours, one-sided with one, ``fallback_base`` (3,) m/s base axes (e.g. the
    person's velocity) with none. Returns (V, 3) float64 m/s in the base axes of this frame.
    """
    world = [
        None
        if v is None
        else transform_points(np.asarray(T, np.float64), np.asarray(v, np.float64))
        for v, T in zip(vertices_lidar, T_world_from_lidar)
    ]
    R_base_from_world = (
        np.asarray(T_base_from_lidar, np.float64)[:3, :3]
        @ np.asarray(T_world_from_lidar[len(world) // 2], np.float64)[:3, :3].T
    )
    c = len(world) // 2  # the centre: this frame
    have = [i for i, w in enumerate(world) if w is not None]
    if len(have) > 3:  # more than one neighbour on a side: the interpolating polynomial's slope
        tau = np.array([float(stamps_s[i]) - float(stamps_s[c]) for i in have])
        w = derivative_weights(tau)
        v = sum(wi * world[i] for wi, i in zip(w, have))
        return v @ R_base_from_world.T
    world = world[c - 1 : c + 2]
    stamps_s = list(stamps_s[c - 1 : c + 2])
    a = 0 if world[0] is not None else 1
    b = 2 if world[2] is not None else 1
    if a == b:
        return np.broadcast_to(
            np.asarray(fallback_base, np.float64).reshape(3), (len(world[1]), 3)
        ).copy()
    dt = float(stamps_s[b]) - float(stamps_s[a])
    if not dt > 0:
        raise ValueError(f"vertex_velocities_in_base: times {stamps_s} do not increase")
    return ((world[b] - world[a]) / dt) @ R_base_from_world.T


def derivative_weights(tau) -> np.ndarray:
    """Weights w (n,) with sum_i w_i f(tau_i) = f'(0) exactly for every polynomial f of degree
    < n: tau (n,) distinct times (s) relative to the frame (one of them 0)."""
    tau = np.asarray(tau, np.float64)
    n = len(tau)
    V = np.vander(tau, n, increasing=True).T  # V[k, i] = tau_i^k
    e = np.zeros(n)
    e[1] = 1.0
    return np.linalg.solve(V, e)
