"""Where the surface lies in the static map's voxels: LiDAR noise told apart from surfaces.

The voxel convention (storage/SCHEMA.md, "Voxel convention"): a static voxel is occupied when a
surface passes through it; a surface lying on a voxel face belongs to the voxel behind it (the
solid's side, as seen from the sensor: the flat ground at z = 0 occupies the layer below it).
Voting LiDAR returns into voxels breaks this wherever a surface lies within a few range-noise
sigmas behind a voxel face: a share of its returns falls into the free voxel in front of it
(measured, issue 30: a car face 7 mm behind a face put a quarter of its returns, and over a
sequence a whole wall of voxels, one voxel too near the robot). With more sweeps (10 Hz) more
of them do. This module finds those voxels from the points themselves.

Each map voxel accumulates the moments of its points (count, sums of the coordinates and of their
products, relative to the voxel's corner, and the sum of the unit vectors from the points to the
sensor), in fixed point (:data:`MOMENT_UNIT_M`), so that moments of any split of the sweeps (the
map's windows and tiles) add up to exactly the same integers. :func:`surface_fit` then decides:

- a voxel's **plane**: that of its own points where they are planar (at least ``min_points``,
  spread across the fitted plane no more than ``2 noise_m``, along it at least ``4 noise_m`` both
  ways), else that of the points of its
  3 x 3 x 3 neighbourhood where those are (sparse far ground); the normal turned towards the
  sensor. Neither (a corner, a pole's arc, a few points): no plane;
- a voxel v is **noise in front of a surface** (dropped) when a neighbour w (or v's own
  neighbourhood) has a plane, v's centroid lies in front of it (on the sensor's side) by at most
  ``3 noise_m``, and the plane does not pass through v (for w's own plane: the plane with w's
  normal through the centroid of v's and w's points together, as w's alone are cut at their
  shared face): the points of v are the near tail of that surface;
- but a voxel v that the own plane of a voxel w sharing a face with it reaches into (w's plane
  flat to the noise, as wide as the voxel, facing v across that face most; through v's and w's
  points together) is **the surface curving on** across the face (a tree's crown bulging a
  centimetre into v: its returns hug the face like a tail's, a few % of w's) and is kept
  whatever the rules above and below say (a neighbour's plane across an edge or a corner, a
  curved surface's tangent, passes in front of it);
- a voxel v with fewer than ``min_points`` points and no plane of its own is **noise** (dropped) when its
  centroid lies within ``3 noise_m`` of every face it shares with a neighbour w that has at least
  ``min_points`` points and lies behind v as seen from the sensor (a tail at a corner of w, where
  no plane fits); with more points but fewer than w's, when its centroid lies within ``noise_m``
  of those faces (the near tail of a surface without a plane, a pole's arc a few cm behind the
  face, over a sequence's sweeps: its points crowd the face, while a surface reaching into v
  puts them at its own depth there).

A plane "passes through" a voxel when it meets the voxel's cube, the plane moved
:data:`FACE_TOLERANCE_M` into the solid first (a surface within that distance in front of a voxel
face belongs to the voxel behind it: the estimate of the ground's height from ~1000 returns
carries ~0.3 mm of noise, and this rounds it to the ground truth's side).

Returns behind a surface fall inside its solid (occupied in the ground truth too) and are kept.
The surviving voxels keep their surface for resampling into robot-local grids
(:mod:`tasks.occupancy.resample`): ``surface`` (K, 6) float32 = (a point of the voxel's plane
relative to its corner (3,) m, unit normal (3,)), or the centroid of its points and a zero normal
where no plane passes through its cube (a thin pole, a corner).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: fixed-point unit of the moments, m (10 um: exact integer sums, no overflow for 1 m voxels and
#: 10^6 points per voxel)
MOMENT_UNIT_M = 1e-5
#: moment columns: count, sum x, y, z, sum xx, xy, xz, yy, yz, zz, sum of unit vectors to the
#: sensor ux, uy, uz (coordinates relative to the voxel's corner, in MOMENT_UNIT_M)
NUM_MOMENTS = 13
#: a surface this close in front of a voxel face belongs to the voxel behind the face, m
FACE_TOLERANCE_M = 0.002

#: a voxel without a plane of its own is a tail of the better-sampled voxel behind it only when
#: it holds less than 1 / TAIL_SHARE of that voxel's points (besides the case of a few points
#: without any plane); measured: a pole 2 cm behind a face throws 1-8 %, one across it ~25 %
TAIL_SHARE = 10

#: a voxel's own plane vouches for the voxel in front of it (a surface curving on across their
#: shared face) only where it spans the voxel: its points spread along it at least this share of
#: the voxel's edge (1 sigma) both ways (spread evenly over a whole face: 0.29; a 16 cm pole's
#: visible arc, or one of its facets: under 0.23 of a 0.2 m voxel), and spread across it no more
#: than WIDE_FLAT_SIGMAS noise sigmas (flat to the noise; a pole's arc seen from several sides
#: over a sequence spreads wider along and across: measured 1.6 sigma, a crown's 0.2-1.0)
WIDE_SPREAD = 0.25
WIDE_FLAT_SIGMAS = 1.5

_IU = np.triu_indices(3)


class SurfaceError(ValueError):
    """Bad input to the surface kernels."""


def point_moments(
    points_world: np.ndarray, keys: np.ndarray, origin_world: np.ndarray, voxel_size_m: float
) -> np.ndarray:
    """Per point moment rows (N, 13) int64 (:data:`NUM_MOMENTS`) of points (N, 3) float (world,
    m) in voxels keys (N, 3) int (``floor(p / voxel_size_m)``), seen from origin_world (3,)."""
    p = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    rel = p - np.asarray(keys, dtype=np.float64).reshape(-1, 3) * voxel_size_m
    q = np.rint(rel / MOMENT_UNIT_M).astype(np.int64)
    to_sensor = np.asarray(origin_world, dtype=np.float64).reshape(3) - p
    norm = np.linalg.norm(to_sensor, axis=1, keepdims=True)
    u = np.rint(to_sensor / np.maximum(norm, 1e-12) / MOMENT_UNIT_M).astype(np.int64)
    out = np.empty((len(p), NUM_MOMENTS), dtype=np.int64)
    out[:, 0] = 1
    out[:, 1:4] = q
    out[:, 4:10] = q[:, _IU[0]] * q[:, _IU[1]]
    out[:, 10:13] = u
    return out


def group_sum(packed: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Moment rows (M, 13) int64 summed per key: packed (M,) int64 keys -> (unique keys (U,)
    ascending, sums (U, 13) int64). Integer sums: exact in any grouping."""
    packed = np.asarray(packed, dtype=np.int64).reshape(-1)
    rows = np.asarray(rows, dtype=np.int64).reshape(-1, NUM_MOMENTS)
    if not len(packed):
        return packed[:0].copy(), np.zeros((0, NUM_MOMENTS), np.int64)
    order = np.argsort(packed, kind="stable")
    pk = packed[order]
    start = np.flatnonzero(np.r_[True, pk[1:] != pk[:-1]])
    return pk[start], np.add.reduceat(rows[order], start, axis=0)


@dataclass(frozen=True)
class SurfaceFit:
    """keep (K,) bool: the voxel holds a surface (False: noise in front of a neighbour's surface);
    surface (K, 6) float32: a point of the voxel's plane relative to the voxel's corner (m) and its
    unit normal towards the sensor, or the centroid of its points and zeros where it has no plane
    through its cube; planar (K,) bool: it has one."""

    keep: np.ndarray
    surface: np.ndarray
    planar: np.ndarray


def _stats(m: np.ndarray):
    """count (K,), centroid (K, 3) m, covariance (K, 3, 3) m^2, sensor direction sum (K, 3) of
    moments (K, 13) (float or int, MOMENT_UNIT_M)."""
    m = np.asarray(m, dtype=np.float64)
    n = np.maximum(m[:, 0], 1.0)
    mean_q = m[:, 1:4] / n[:, None]
    second = np.empty((len(m), 3, 3))
    second[:, _IU[0], _IU[1]] = m[:, 4:10] / n[:, None]
    second[:, _IU[1], _IU[0]] = m[:, 4:10] / n[:, None]
    cov = (second - mean_q[:, :, None] * mean_q[:, None, :]) * MOMENT_UNIT_M**2
    return m[:, 0], mean_q * MOMENT_UNIT_M, cov, m[:, 10:13]


def _shifted(m: np.ndarray, shift_q: np.ndarray) -> np.ndarray:
    """Moments (K, 13) float64 of points moved by shift_q (3,) (MOMENT_UNIT_M): a neighbour's
    moments in this voxel's frame."""
    out = np.array(m, dtype=np.float64)
    n, s1 = out[:, 0], out[:, 1:4].copy()
    out[:, 1:4] += n[:, None] * shift_q
    cross = s1[:, _IU[0]] * shift_q[_IU[1]] + s1[:, _IU[1]] * shift_q[_IU[0]]
    out[:, 4:10] += cross + n[:, None] * (shift_q[_IU[0]] * shift_q[_IU[1]])
    return out


def _plane(count, cov, toward, min_points: int, noise_m: float):
    """(unit normal (K, 3) towards the sensor, planar (K,) bool) of point sets."""
    k = len(count)
    if not k:
        return np.zeros((0, 3)), np.zeros(0, bool)
    lam, vec = np.linalg.eigh(cov)
    normal = vec[:, :, 0]
    normal[np.einsum("ka,ka->k", normal, toward) < 0] *= -1.0
    # thin across the plane (noise), wide along it in both directions (not a line of returns)
    flat = (lam[:, 0] <= (2.0 * noise_m) ** 2) & (lam[:, 1] >= (4.0 * noise_m) ** 2)
    return normal, (count >= min_points) & flat


_OFFSETS = np.array(
    [(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)], dtype=np.int64
)


def _passes(normal: np.ndarray, point_rel: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """(K,) bool: the plane through point_rel (K, 3) (relative to the voxel's corner) with unit
    normal (K, 3) towards the sensor, moved FACE_TOLERANCE_M into the solid, meets the voxel's
    cube (half-open on the sensor's side)."""
    half = 0.5 * voxel_size_m
    s = np.einsum("ka,ka->k", normal, half - (point_rel - FACE_TOLERANCE_M * normal))
    h = half * np.abs(normal).sum(axis=1)
    return (s - h < 0.0) & (s + h >= 0.0)


def surface_fit(
    packed_keys: np.ndarray,
    moments: np.ndarray,
    voxel_size_m: float,
    noise_m: float,
    min_points: int,
) -> SurfaceFit:
    """Which voxels of a map hold a surface and which only hold noise (module docstring).

    packed_keys: (K,) int64 ascending (:func:`tasks.occupancy.static_map.pack_keys`); moments:
    (K, 13) int64 (:func:`point_moments` summed per voxel); voxel_size_m: the map's voxel edge;
    noise_m: the LiDAR range noise (1 sigma, m; 0: nothing is dropped); min_points: points a
    plane needs. Decisions near the edge of the given keys see fewer neighbours: give a halo of
    voxels around the ones used.
    """
    from tasks.occupancy.voxel_keys import key_rows, unpack_keys

    pk = np.asarray(packed_keys, dtype=np.int64)
    m = np.asarray(moments, dtype=np.int64)
    if m.shape != (len(pk), NUM_MOMENTS):
        raise SurfaceError(f"moments must be ({len(pk)}, {NUM_MOMENTS}), got {m.shape}")
    if noise_m < 0 or min_points < 3:
        raise SurfaceError(f"need noise_m >= 0 and min_points >= 3, got {noise_m}, {min_points}")
    k = len(pk)
    keys = unpack_keys(pk)
    count, mean, cov, toward = _stats(m)
    normal, planar = _plane(count, cov, toward, min_points, noise_m)
    # the voxel's 3 x 3 x 3 neighbourhood pooled, in the voxel's frame
    step_q = voxel_size_m / MOMENT_UNIT_M
    rows = [key_rows(pk, keys + d) for d in _OFFSETS] if k else []
    pooled = np.zeros((k, NUM_MOMENTS))
    for d, w in zip(_OFFSETS, rows):
        ok = np.flatnonzero(w >= 0)
        pooled[ok] += _shifted(m[w[ok]], d * step_q)
    p_count, p_mean, p_cov, p_toward = _stats(pooled)
    p_normal, p_planar = _plane(p_count, p_cov, p_toward, min_points, noise_m)
    # each voxel's plane: its own points', else its neighbourhood's
    has_plane = planar | p_planar
    plane_n = np.where(planar[:, None], normal, p_normal)
    plane_at = np.where(planar[:, None], mean, p_mean)
    tail = np.zeros(k, dtype=bool)
    if k and noise_m > 0:
        reach = 3.0 * noise_m
        # a voxel in front of the own plane of a voxel sharing a face with it (the face the
        # plane faces most, its normal's dominant axis) into which that plane reaches (with that
        # voxel's normal through both voxels' points, as below) holds that surface curving on
        # across the face (a tree's crown), not its noise: no other neighbour's plane
        # (extrapolated across an edge or a corner) nor its points' depth makes it a tail
        reached = np.zeros(k, dtype=bool)
        facing = np.argmax(np.abs(normal), axis=1)
        lam = np.linalg.eigvalsh(cov)
        wide = lam[:, 1] >= (WIDE_SPREAD * voxel_size_m) ** 2
        wide &= lam[:, 0] <= (WIDE_FLAT_SIGMAS * noise_m) ** 2
        for d, w in zip(_OFFSETS, rows):
            if np.abs(d).sum() != 1:
                continue
            a = int(np.flatnonzero(d)[0])
            v = np.flatnonzero(w >= 0)
            v = v[planar[w[v]] & ~reached[v]]
            v = v[(facing[w[v]] == a) & (normal[w[v], a] * d[a] < 0) & wide[w[v]]]
            wv = w[v]
            cv, cw = count[v][:, None], count[wv][:, None]
            both = (cv * mean[v] + cw * (mean[wv] + d * voxel_size_m)) / (cv + cw)
            reached[v[_passes(normal[wv], both, voxel_size_m)]] = True
        for d, w in zip(_OFFSETS, rows):
            # the near tail of a plane: its own (another voxel's points) or the neighbourhood's
            v = np.flatnonzero((w >= 0) & ~tail & ~reached)
            v = v[has_plane[w[v]] & ((d != 0).any() | ~planar[v])]
            wv = w[v]
            nw = plane_n[wv]
            at_w = plane_at[wv] + d * voxel_size_m  # in v's frame
            ahead = np.einsum("ka,ka->k", nw, mean[v] - at_w)
            near = (ahead > 0.0) & (ahead <= reach)
            # an own plane through v's and w's points together (w's alone are cut at the face
            # they share); a neighbourhood's plane holds v's points already
            cv, cw = count[v][:, None], count[wv][:, None]
            both = (cv * mean[v] + cw * (mean[wv] + d * voxel_size_m)) / (cv + cw)
            through = np.where(planar[wv][:, None], both, at_w)
            tail[v[near & ~_passes(nw, through, voxel_size_m)]] = True
            if not d.any():
                continue
            # points hugging the faces shared with a well-sampled voxel behind them: a few
            # within 3 sigma (a tail at a corner of w), or more than that but fewer than w's
            # with their centroid within 1 sigma (the near tail of a surface without a plane,
            # a pole's arc, seen over many sweeps; a surface reaching into v puts its points
            # at its own depth there, beyond 1 sigma once it is more than that inside)
            # (a sparse voxel may borrow its neighbourhood's plane: a pole's arc fits a plane
            # that, tilted, reaches into the voxel in front beyond the pole's own extent)
            # Past the first case, a tail also holds few points next to w's: a surface lying
            # within about 1.3 sigma behind the face throws over a tenth of its returns forward,
            # a surface reaching into v more (a pole across a voxel face: about a quarter).
            v = np.flatnonzero((w >= 0) & ~planar & ~tail & ~reached)
            v = v[(count[w[v]] >= min_points) & (toward[v] @ d < 0)]
            first = (count[v] < min_points) & ~has_plane[v]
            v = v[first | (count[v] * TAIL_SHARE < count[w[v]])]
            sparse = count[v] < min_points
            within = np.where(sparse, reach, noise_m)
            hug = np.ones(len(v), dtype=bool)
            for a in range(3):
                if d[a] > 0:
                    hug &= mean[v, a] >= voxel_size_m - within
                elif d[a] < 0:
                    hug &= mean[v, a] <= within
            tail[v[hug]] = True
    # what stands for the voxel in other grids: its plane where one passes through its cube,
    # else the centroid of its points
    sampled = has_plane & _passes(plane_n, plane_at, voxel_size_m)
    surface = np.zeros((k, 6), dtype=np.float32)
    surface[:, :3] = np.where(sampled[:, None], plane_at, mean)
    surface[sampled, 3:] = plane_n[sampled]
    return SurfaceFit(~tail, surface, sampled)


def surface_samples(
    keys: np.ndarray, surface: np.ndarray, voxel_size_m: float, spacing_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Points (world frame, m) that stand for each voxel's surface when it is resampled into
    another grid: a voxel with a plane (non-zero normal) gives points of that plane inside its cube
    (a lattice of spacing <= spacing_m across the plane's dominant axis, the plane moved
    FACE_TOLERANCE_M into the solid as in the fit; a plane that only clips a corner between
    lattice points: its point nearest the cube's centre), one without gives its centroid.

    keys: (K, 3) int64; surface: (K, 6) float32 (:class:`SurfaceFit`). Returns (points (P, 3)
    float64, voxel (P,) int64 row of keys of each point).
    """
    keys = np.asarray(keys, dtype=np.int64).reshape(-1, 3)
    surf = np.asarray(surface, dtype=np.float64).reshape(-1, 6)
    point = surf[:, :3]
    normal = surf[:, 3:]
    has = np.any(normal != 0, axis=1)
    pts = [keys[~has] * voxel_size_m + point[~has]]
    rows = [np.flatnonzero(~has)]
    n = max(1, int(np.ceil(voxel_size_m / spacing_m - 1e-9)))
    g = (np.arange(n) + 0.5) / n * voxel_size_m
    gu, gv = (a.reshape(-1) for a in np.meshgrid(g, g, indexing="ij"))
    at = point - FACE_TOLERANCE_M * normal
    axis = np.argmax(np.abs(normal), axis=1)
    for a in range(3):
        sel = np.flatnonzero(has & (axis == a))
        if not len(sel):
            continue
        b, c = [x for x in range(3) if x != a]
        nn, pp = normal[sel], at[sel]
        w = (
            pp[:, a, None]
            - (
                nn[:, b, None] * (gu[None] - pp[:, b, None])
                + nn[:, c, None] * (gv[None] - pp[:, c, None])
            )
            / nn[:, a, None]
        )
        ok = (w >= 0.0) & (w < voxel_size_m)
        rel = np.empty(w.shape + (3,))
        rel[..., a] = w
        rel[..., b] = gu[None]
        rel[..., c] = gv[None]
        pts.append((rel + (keys[sel] * voxel_size_m)[:, None, :])[ok])
        rows.append(np.broadcast_to(sel[:, None], w.shape)[ok])
    # a plane that only clips a corner of its cube between lattice points: the point of the plane
    # nearest the cube's centre, clamped into the cube
    missed = np.flatnonzero(has & ~np.isin(np.arange(len(keys)), np.concatenate(rows)))
    if len(missed):
        c = np.full(3, 0.5 * voxel_size_m)
        nn = normal[missed]
        foot = c - np.einsum("ka,ka->k", nn, c - at[missed])[:, None] * nn
        foot = np.clip(foot, 1e-4 * voxel_size_m, (1 - 1e-4) * voxel_size_m)
        pts.append(foot + keys[missed] * voxel_size_m)
        rows.append(missed)
    order = np.argsort(np.concatenate(rows), kind="stable")
    return np.concatenate(pts)[order], np.concatenate(rows)[order]
