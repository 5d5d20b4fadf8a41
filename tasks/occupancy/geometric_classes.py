"""Weight-free per-point classes of one LiDAR sweep from its geometry (and intensity).

The label source of the map stage when no image segmenter is configured (``map.point_classes``:
``geometry``, or ``camera+geometry`` where the camera's labels win and this fills the rest).

Input: one sweep's points (N, 3) float32 metres in a z-up frame whose origin is the sensor (the
LiDAR frame of a level sensor, or the LiDAR frame rotated by the rotation of
``T_world_from_lidar``: :func:`gravity_aligned`); intensities (N,) in the sensor's units or None.
Output: (N,) uint8 class ids of :mod:`tasks.conventions`, :data:`UNLABELED` wherever the geometry
cannot tell (the classifier never guesses).

Steps (lengths in metres, heights above the local ground):

1. Ground, per ``ground_cell_m`` cell of the xy plane: the seed is the lowest z that at least
   ``ground_min_support`` points of the cell lie within ``ground_band_m`` above (so a few returns
   below the road, multipath, never become the ground, as the per-cell minimum would); a
   least-squares plane through the points of that band, refitted through those within 3 robust
   sigma of it (at least ``MIN_INLIER_M``, at most ``ground_tolerance_m``). Points on a surface
   clearly steeper than ground (|n_z| < ``ground_min_nz`` of the normal below: a wall's foot, a
   wheel) are neither ground nor in the fit. A cell whose plane lies more than
   ``ground_step_m`` + ``ground_max_slope`` x distance above a neighbour's within
   ``ground_window_cells`` cells is the top of something (a car's roof), not ground; a cell
   without ground (under or behind an object) borrows the mean height of the nearest cells with
   ground within ``ground_borrow_m``. Points within ``ground_tolerance_m`` of their cell's plane
   are ground; points farther below are UNLABELED (returns below the ground are multipath).
2. ROAD vs TERRAIN on ground points: a cell whose robust residual sigma exceeds
   ``terrain_min_roughness_m`` is TERRAIN (grass, gravel); else the intensity corrected for
   incidence (a return's intensity ~ reflectivity x (f + (1 - f) |cos incidence|), f =
   ``intensity_incidence_floor``), median over the ``intensity_neighbours`` nearest ground
   points: <= ``road_max_intensity`` ROAD, in [``terrain_min_intensity``,
   ``terrain_max_intensity``] TERRAIN, anything else UNLABELED (also every smooth ground point
   when intensities are None).
3. The other points (above the ground) are clustered (voxels of ``cluster_voxel_m`` linked within
   ``cluster_tol_m``); each cluster of at least ``min_cluster_points`` points gets one class from
   its size and shape: its footprint (PCA of xy, 2-98 percentile extents: length >= width), its
   top and foot (98th / 2nd percentile height), the share of its ``column_m`` xy columns whose
   lowest point lies within ``clearance_m`` of the ground ("grounded": a wall stands on the
   ground, a car on wheels), whether the sensor's top beam reaches it (within ``top_margin_deg``:
   then its top may be unseen), and per point the normal of the ``normal_neighbours`` nearest
   centroids of ``normal_voxel_m`` voxels (vertical plane: |n_z| < ``vertical_max_nz`` and
   scattering lambda3 / lambda1 < ``scattering_min``; sloped or scattered: |n_z| in
   [vertical_max_nz, ``sloped_max_nz``] or scattering >= scattering_min):

   - POLE: length <= ``pole_max_width_m``, top >= ``pole_min_height_m``, foot <=
     ``pole_max_bottom_m``;
   - VEGETATION: sloped / scattered share >= ``vegetation_min_share``, top >=
     ``vegetation_min_height_m``, length >= ``vegetation_min_length_m`` (a wide, curved or
     porous mass above head height: a crown);
   - OTHER_STRUCTURE: vertical-plane share >= ``structure_min_share``, longer than a pole, and
     either top >= ``structure_min_height_m`` (a building's face, taller than vehicles) or a thin
     wall under the top beam (width <= ``wall_max_width_m``, length >= ``wall_min_length_m``,
     grounded share >= ``grounded_min_share``);
   - CAR: under the top beam, top in [``car_min_height_m``, ``car_max_height_m``], length in
     [``car_min_length_m``, ``car_max_length_m``], grounded share < ``grounded_min_share``;
   - anything else (trucks, two-wheelers, people, fragments): UNLABELED.

Deterministic; no randomness. The defaults are set on the simulator's sweeps (its ground is flat,
its road and lawn differ only in reflectivity, 0.2 vs 0.3: road_max / terrain_min intensity sit
between 255 x 0.2 and 255 x 0.3): on a real sensor measure the road's and the lawn's corrected
intensity first (docs/geometric-classes.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from tasks.bounds import AtLeastOne, NonNegative, Positive, PositiveFraction, Probability
from tasks.conventions import (
    CAR,
    OTHER_STRUCTURE,
    POLE,
    ROAD,
    TERRAIN,
    UNLABELED,
    VEGETATION,
)
from tasks.perception.lidar_clusters import cluster_points

#: a neighbourhood with lambda2 / lambda1 below this is a line (one scan ring): it has no normal
LINEAR = 0.05
#: the narrowest gate (m) of the ground's second fit (a LiDAR's range noise is ~1-3 cm)
MIN_INLIER_M = 0.03
#: cells without ground of their own take the mean height of this many nearest cells with ground
GROUND_BORROW = 4


@dataclass(frozen=True)
class GeometricClassSettings:
    """Settings of :func:`geometric_classes` (what each does: the module docstring). Lengths in
    metres, heights above the local ground, intensities in the sensor's units."""

    ground_cell_m: Positive = 1.0
    ground_band_m: Positive = 0.15
    ground_min_support: AtLeastOne = 5
    ground_tolerance_m: Positive = 0.08
    ground_window_cells: AtLeastOne = 3
    ground_max_slope: NonNegative = 0.3
    ground_step_m: NonNegative = 0.2
    ground_min_nz: PositiveFraction = 0.85
    ground_borrow_m: Positive = 10.0
    terrain_min_roughness_m: Positive = 0.025
    intensity_incidence_floor: Probability = 0.2
    intensity_neighbours: AtLeastOne = 5
    road_max_intensity: NonNegative = 60.0
    terrain_min_intensity: NonNegative = 68.0
    terrain_max_intensity: NonNegative = 100.0
    cluster_voxel_m: Positive = 0.1
    cluster_tol_m: Positive = 0.25
    min_cluster_points: AtLeastOne = 20
    normal_neighbours: AtLeastOne = 12
    normal_voxel_m: Positive = 0.1
    vertical_max_nz: PositiveFraction = 0.3
    sloped_max_nz: PositiveFraction = 0.9
    scattering_min: PositiveFraction = 0.1
    clearance_m: Positive = 0.1
    column_m: Positive = 0.25
    grounded_min_share: Probability = 0.6
    top_margin_deg: NonNegative = 1.0
    pole_max_width_m: Positive = 0.6
    pole_min_height_m: Positive = 2.2
    pole_max_bottom_m: Positive = 0.5
    vegetation_min_share: Probability = 0.35
    vegetation_min_height_m: Positive = 2.0
    vegetation_min_length_m: Positive = 1.0
    structure_min_share: Probability = 0.5
    structure_min_height_m: Positive = 3.6
    wall_max_width_m: Positive = 0.6
    wall_min_length_m: Positive = 2.5
    car_min_height_m: Positive = 1.2
    car_max_height_m: Positive = 2.1
    car_min_length_m: Positive = 2.5
    car_max_length_m: Positive = 6.0


@dataclass(frozen=True)
class GroundModel:
    """The local ground of a sweep, per point: ground (N,) bool, below (N,) bool (more than the
    tolerance below the ground: multipath), height (N,) float64 m above the ground (NaN where no
    ground is known nearby), roughness (N,) float64 m (robust residual sigma of the point's ground
    cell, NaN where the cell has no ground), normal (N, 3) float64 unit ground normal (z up)."""

    ground: np.ndarray
    below: np.ndarray
    height: np.ndarray
    roughness: np.ndarray
    normal: np.ndarray


def gravity_aligned(T_world_from_lidar: np.ndarray, points_lidar: np.ndarray) -> np.ndarray:
    """(N, 3) float32: points_lidar (N, 3) rotated by the rotation of T_world_from_lidar (4, 4):
    z up, the sensor at the origin (the frame :func:`geometric_classes` takes)."""
    R = np.asarray(T_world_from_lidar, np.float64)[:3, :3]
    return (np.asarray(points_lidar, np.float64) @ R.T).astype(np.float32)


def _pack(cells: np.ndarray) -> np.ndarray:
    """(M,) int64 keys of (M, 2) int64 cells, in the order of np.unique(cells, axis=0)."""
    return (cells[:, 0] + 2**30) * 2**31 + (cells[:, 1] + 2**30)


def _offsets(r: int) -> np.ndarray:
    g = np.arange(-r, r + 1)
    return np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)


def _cell_sigma(cid: np.ndarray, res: np.ndarray, use: np.ndarray, m: int) -> np.ndarray:
    """(m,) robust sigma (1.4826 x the median absolute value) of res (N,) over the points use
    (N,) bool of each of m cells (NaN: none)."""
    out = np.full(m, np.nan)
    i = np.flatnonzero(use)
    if len(i):
        o = i[np.lexsort((np.abs(res[i]), cid[i]))]
        cells, start, num = np.unique(cid[o], return_index=True, return_counts=True)
        out[cells] = 1.4826 * np.abs(res[o[start + num // 2]])
    return out


def _fit_planes(
    cid: np.ndarray, d: np.ndarray, z: np.ndarray, use: np.ndarray, m: int, max_slope: float
) -> tuple[np.ndarray, np.ndarray]:
    """(coefficients (m, 3): z = a dx + b dy + c, points used (m,)) of each of m cells: least
    squares through the points ``use`` (N,) bool; flat (a = b = 0, c the mean) where the points
    do not span the cell or the slope exceeds max_slope; c NaN where a cell has no point."""
    b = np.flatnonzero(use)
    cols = np.stack([d[b, 0], d[b, 1], np.ones(len(b))], 1)
    A = np.zeros((m, 3, 3))
    y = np.zeros((m, 3))
    np.add.at(A, cid[b], cols[:, :, None] * cols[:, None, :])
    np.add.at(y, cid[b], cols * z[b, None])
    count = A[:, 2, 2]
    coef = np.zeros((m, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        coef[:, 2] = y[:, 2] / count
    # a plane where the points span the cell (a sliver of points would tilt it), else flat
    well = (count >= 3) & (np.abs(np.linalg.det(A)) > 1e-9 * np.maximum(count, 1) ** 3)
    if well.any():
        sol = np.linalg.solve(A[well], y[well][:, :, None])[:, :, 0]
        steep = np.hypot(sol[:, 0], sol[:, 1]) > max_slope
        sol[steep] = np.c_[np.zeros((steep.sum(), 2)), coef[well][steep, 2]]
        coef[well] = sol
    return coef, count


def ground_model(
    points: np.ndarray, s: GeometricClassSettings, steep: np.ndarray | None = None
) -> GroundModel:
    """The local ground (:class:`GroundModel`) of points (N, 3) float32, z up, metres (step 1 of
    the module docstring). steep: (N,) bool, points on a surface steeper than the ground may be
    (a wall's foot): never ground, nor part of the ground's fit (None: none)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    n = len(p)
    flat = np.ones(n, bool) if steep is None else ~np.asarray(steep, bool)
    nan = np.full(n, np.nan)
    up = np.tile([0.0, 0.0, 1.0], (n, 1))
    if n == 0:
        return GroundModel(np.zeros(0, bool), np.zeros(0, bool), nan, nan, up)
    cells = np.floor(p[:, :2] / s.ground_cell_m).astype(np.int64)
    ucells, cid = np.unique(cells, axis=0, return_inverse=True)
    cid = cid.reshape(-1)
    m = len(ucells)
    # seed: per cell the lowest z with ground_min_support points within ground_band_m above it
    order = np.lexsort((p[:, 2], cid))
    order = order[flat[order]]
    z, c = p[order, 2], cid[order]
    span = float(z.max() - z.min()) + 2 * s.ground_band_m + 1.0
    key = c * span + (z - z.min())
    support = np.searchsorted(key, key + s.ground_band_m, side="right") - np.arange(len(key))
    ok = np.flatnonzero(support >= s.ground_min_support)
    seeded, first = np.unique(c[ok], return_index=True)
    seed = np.full(m, np.nan)
    seed[seeded] = z[ok[first]]
    # plane z = a dx + b dy + c0 through the band points (dx dy from the cell's centre), then
    # again through those within the tolerance of it (an object's base in the band tilts the
    # first); roughness: the median absolute residual of the inliers (x 1.4826: sigma)
    centre = (ucells + 0.5) * s.ground_cell_m
    d = p[:, :2] - centre[cid]
    band = flat & (p[:, 2] >= seed[cid]) & (p[:, 2] <= seed[cid] + s.ground_band_m)
    coef, count = _fit_planes(cid, d, p[:, 2], band, m, s.ground_max_slope)
    res = p[:, 2] - (coef[cid, 0] * d[:, 0] + coef[cid, 1] * d[:, 1] + coef[cid, 2])
    # refit through the points within 3 robust sigma of the first plane (at least
    # MIN_INLIER_M, at most the tolerance): the foot of a wall or a wheel in the band, a few
    # centimetres up, would otherwise lift the plane beside it
    sigma = _cell_sigma(cid, res, band & (np.abs(res) <= s.ground_tolerance_m), m)
    gate = np.clip(3.0 * np.nan_to_num(sigma, nan=s.ground_tolerance_m), MIN_INLIER_M, None)
    inlier = band & (np.abs(res) <= np.minimum(gate, s.ground_tolerance_m)[cid])
    coef, count = _fit_planes(cid, d, p[:, 2], inlier, m, s.ground_max_slope)
    res = p[:, 2] - (coef[cid, 0] * d[:, 0] + coef[cid, 1] * d[:, 1] + coef[cid, 2])
    has = np.isfinite(seed) & (count > 0)
    rough = _cell_sigma(cid, res, band & (np.abs(res) <= s.ground_tolerance_m), m)
    # a cell above a neighbour by more than the step and the slope allows is an object's top
    valid = has.copy()
    h0 = np.where(has, coef[:, 2], np.inf)
    packed = _pack(ucells)  # ascending: np.unique sorted the cells
    nb_min = np.full(m, np.inf)
    for off in _offsets(s.ground_window_cells):
        if not off.any():
            continue
        want = _pack(ucells + off)
        j = np.minimum(np.searchsorted(packed, want), m - 1)
        hn = np.where(packed[j] == want, h0[j], np.inf)
        nb_min = np.minimum(
            nb_min, hn + s.ground_max_slope * float(np.hypot(*off)) * s.ground_cell_m
        )
    valid &= h0 <= nb_min + s.ground_step_m
    # cells without valid ground (under an object, in a wall's shadow) borrow the mean height of
    # the GROUND_BORROW nearest valid cells within ground_borrow_m (no slope)
    borrowed = np.full(m, np.nan)
    vi, wi = np.flatnonzero(valid), np.flatnonzero(~valid)
    if len(vi) and len(wi):
        k = min(GROUND_BORROW, len(vi))
        dist, j = cKDTree(centre[vi]).query(centre[wi], k=k, distance_upper_bound=s.ground_borrow_m)
        dist, j = dist.reshape(len(wi), k), j.reshape(len(wi), k)
        near = np.isfinite(dist)
        h = np.where(near, coef[vi[np.minimum(j, len(vi) - 1)], 2], 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            borrowed[wi] = np.where(near.any(1), h.sum(1) / near.sum(1), np.nan)
    v = valid[cid]
    height = np.where(v, res, p[:, 2] - borrowed[cid])
    ground = v & flat & (np.abs(height) <= s.ground_tolerance_m)
    below = np.isfinite(height) & (height < -s.ground_tolerance_m)
    normal = np.c_[-coef[cid, 0], -coef[cid, 1], np.ones(n)]
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return GroundModel(ground, below, height, np.where(v, rough[cid], np.nan), normal)


def corrected_intensity(
    points: np.ndarray, intensities: np.ndarray, normal: np.ndarray, floor: float
) -> np.ndarray:
    """(N,) float64: intensities (N,) divided by (floor + (1 - floor) |cos incidence|), the
    incidence between the ray from the origin to each point (N, 3) and its surface normal (N, 3)
    unit: what the intensity would be head-on."""
    p = np.asarray(points, np.float64)
    r = np.linalg.norm(p, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.abs(np.sum(p * normal, axis=1)) / r
    cos = np.nan_to_num(cos, nan=1.0)
    return np.asarray(intensities, np.float64) / (floor + (1.0 - floor) * cos)


def _ground_classes(
    p: np.ndarray,
    intensities: np.ndarray | None,
    g: GroundModel,
    s: GeometricClassSettings,
) -> np.ndarray:
    """Class of each ground point of g (step 2), (G,) uint8 in the order of np.flatnonzero(g.ground)."""
    idx = np.flatnonzero(g.ground)
    out = np.full(len(idx), UNLABELED, np.uint8)
    if not len(idx):
        return out
    if intensities is not None:
        corr = corrected_intensity(
            p[idx], intensities[idx], g.normal[idx], s.intensity_incidence_floor
        )
        k = min(s.intensity_neighbours, len(idx))
        if k > 1:
            _, nb = cKDTree(p[idx]).query(p[idx], k=k)
            corr = np.median(corr[nb], axis=1)
        out[corr <= s.road_max_intensity] = ROAD
        out[(corr >= s.terrain_min_intensity) & (corr <= s.terrain_max_intensity)] = TERRAIN
    out[g.roughness[idx] > s.terrain_min_roughness_m] = TERRAIN
    return out


def _normals(p: np.ndarray, k: int, voxel_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(|n_z| (N,), scattering lambda3 / lambda1 (N,), linear (N,) bool: lambda2 / lambda1 <
    LINEAR, no normal) of each point: the PCA of the k nearest
    centroids of ``voxel_m`` voxels around its voxel's centroid. Centroids, not points: near the
    sensor the returns lie a centimetre apart, the range noise's size, and k nearest points would
    look scattered on any surface; centroids span the same ~voxel_m x k**0.5 at every range."""
    keys = np.floor(p / voxel_m).astype(np.int64)
    _, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    count = np.bincount(inv)
    c = np.stack([np.bincount(inv, p[:, i]) for i in range(3)], 1) / count[:, None]
    k = min(k, len(c))
    if k < 3:
        return np.zeros(len(p)), np.zeros(len(p)), np.ones(len(p), bool)
    _, nb = cKDTree(c).query(c, k=k)
    q = c[nb] - c[nb].mean(axis=1, keepdims=True)
    w, v = np.linalg.eigh(np.einsum("nki,nkj->nij", q, q) / k)
    with np.errstate(invalid="ignore", divide="ignore"):
        scattering = np.nan_to_num(w[:, 0] / w[:, 2])
        linear = ~(w[:, 1] >= LINEAR * w[:, 2])
    return np.abs(v[:, 2, 0])[inv], scattering[inv], linear[inv]


def _cluster_classes(
    p: np.ndarray,
    height: np.ndarray,
    nz: np.ndarray,
    scattering: np.ndarray,
    top_elevation: float,
    s: GeometricClassSettings,
) -> np.ndarray:
    """Class of each point above the ground (step 3): p (M, 3) float64 (sensor at the origin),
    height (M,) m, nz / scattering (M,) of :func:`_normals`; top_elevation: the sweep's highest
    beam, rad."""
    out = np.full(len(p), UNLABELED, np.uint8)
    if not len(p):
        return out
    label = cluster_points(p, s.cluster_voxel_m, s.cluster_tol_m)
    vertical = (nz < s.vertical_max_nz) & (scattering < s.scattering_min)
    sloped = ((nz >= s.vertical_max_nz) & (nz <= s.sloped_max_nz)) | (
        scattering >= s.scattering_min
    )
    elevation = np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))
    cut_at = top_elevation - np.radians(s.top_margin_deg)
    column = np.floor(p[:, :2] / s.column_m).astype(np.int64)
    order = np.argsort(label, kind="stable")
    cut = np.flatnonzero(np.diff(label[order])) + 1
    for rows in np.split(order, cut):
        if len(rows) < s.min_cluster_points:
            continue
        xy = p[rows, :2] - p[rows, :2].mean(axis=0)
        _, vec = np.linalg.eigh(xy.T @ xy)
        along = np.percentile(xy @ vec, [2, 98], axis=0)
        width, length = np.sort(along[1] - along[0])
        h = height[rows]
        top, bottom = (float(v) for v in np.percentile(h, [98, 2]))
        # the sensor's highest beam reaches it: its top may be higher than seen
        cut_off = bool(np.any(elevation[rows] >= cut_at))
        # share of its columns that reach down to the ground (a wall does, a car on wheels not)
        cols, inv = np.unique(column[rows], axis=0, return_inverse=True)
        lowest = np.full(len(cols), np.inf)
        np.minimum.at(lowest, inv.reshape(-1), h)
        grounded = float(np.mean(lowest <= s.clearance_m))
        v_share, s_share = float(vertical[rows].mean()), float(sloped[rows].mean())
        if (
            length <= s.pole_max_width_m
            and top >= s.pole_min_height_m
            and bottom <= s.pole_max_bottom_m
        ):
            cls = POLE
        elif (
            s_share >= s.vegetation_min_share
            and top >= s.vegetation_min_height_m
            and length >= s.vegetation_min_length_m
        ):
            cls = VEGETATION
        elif (
            v_share >= s.structure_min_share
            and length > s.pole_max_width_m
            and (
                top >= s.structure_min_height_m
                or (
                    not cut_off
                    and width <= s.wall_max_width_m
                    and length >= s.wall_min_length_m
                    and grounded >= s.grounded_min_share
                )
            )
        ):
            cls = OTHER_STRUCTURE
        elif (
            not cut_off
            and s.car_min_height_m <= top <= s.car_max_height_m
            and s.car_min_length_m <= length <= s.car_max_length_m
            and grounded < s.grounded_min_share
        ):
            cls = CAR
        else:
            continue
        out[rows] = cls
    return out


def geometric_classes(
    points: np.ndarray,
    intensities: np.ndarray | None,
    settings: GeometricClassSettings = GeometricClassSettings(),
) -> np.ndarray:
    """(N,) uint8 class ids (:mod:`tasks.conventions`, UNLABELED where the geometry cannot tell)
    of one sweep. points: (N, 3) float32 metres, z up, the sensor at the origin
    (:func:`gravity_aligned`); intensities: (N,) float in the sensor's units, or None (ground
    points then get ROAD / TERRAIN only from roughness)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    if intensities is not None and len(intensities) != len(p):
        raise ValueError(f"intensities has {len(intensities)} values for {len(p)} points")
    out = np.full(len(p), UNLABELED, np.uint8)
    finite = np.all(np.isfinite(p), axis=1)
    if not finite.any():
        return out
    rows = np.flatnonzero(finite)
    q = p[rows]
    nz, scattering, linear = _normals(q, settings.normal_neighbours, settings.normal_voxel_m)
    # a surface clearly steeper than the ground may be (a wall's foot, a kerb's face, a wheel):
    # neither ground nor part of its fit; a linear neighbourhood (one scan ring) has no normal
    steep = (nz < settings.ground_min_nz) & ~linear
    g = ground_model(q, settings, steep)
    inten = None if intensities is None else np.asarray(intensities, np.float64)[rows]
    sub = np.full(len(q), UNLABELED, np.uint8)
    sub[g.ground] = _ground_classes(q, inten, g, settings)
    above = np.flatnonzero(~g.ground & ~g.below & np.isfinite(g.height))
    top = float(np.max(np.arctan2(q[:, 2], np.hypot(q[:, 0], q[:, 1]))))
    sub[above] = _cluster_classes(
        q[above], g.height[above], nz[above], scattering[above], top, settings
    )
    out[rows] = sub
    return out
