"""How much of each instance in a voxel grid a camera sees: the visible fraction of its silhouette.

Definition (the fraction binned into nuScenes' visibility levels by the nuScenes export): every
occupied voxel is drawn as the square footprint of its centre, ``voxel_size_m`` wide at the
centre's depth (the camera mask's z-buffer, :mod:`tasks.occupancy.visibility`), on a pixel grid
``oversample`` times finer than one voxel at the grid's farthest corner (never finer than the
camera). An instance's silhouette is the union of its own footprints on an unbounded image plane
(so parts outside the image count as not visible); its visible part is the set of pixels inside
the image where its footprint is the nearest of all occupied voxels' (static ones included).

    visible_fraction = |visible part| / |silhouette|   (0 for an instance with nothing in front of the camera)

An instance with no voxel in the grid (beyond its range) can be given as points, e.g. the voxel
centres its 3D box would take (:func:`box_lattice`), drawn like voxels.

Self-occlusion does not count (the whole silhouette of a lone person in the image is visible: 1.0);
truncation by the image border and occlusion by anything nearer do.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def _footprint(bx, by, bz, R, t, fx, fy, cx, cy, vs):
    """Camera distance and the (u0, u1, v0, v1) pixel rectangle of a voxel centre's footprint
    (unclipped); distance -1 when the centre is not in front of the camera."""
    x = R[0, 0] * bx + R[0, 1] * by + R[0, 2] * bz + t[0]
    y = R[1, 0] * bx + R[1, 1] * by + R[1, 2] * bz + t[1]
    z = R[2, 0] * bx + R[2, 1] * by + R[2, 2] * bz + t[2]
    if z <= 1e-6:
        return -1.0, 0, -1, 0, -1
    u = fx * x / z + cx
    v = fy * y / z + cy
    hu = 0.5 * vs * fx / z
    hv = 0.5 * vs * fy / z
    return (
        math.sqrt(x * x + y * y + z * z),
        int(math.floor(u - hu + 0.5)),
        int(math.floor(u + hu + 0.5)),
        int(math.floor(v - hv + 0.5)),
        int(math.floor(v + hv + 0.5)),
    )


@njit(cache=True)
def _nearest_id(centres, occ_id, vs, R, t, fx, fy, cx, cy, zbuf, idbuf):
    H, W = zbuf.shape
    for n in range(centres.shape[0]):
        d, u0, u1, v0, v1 = _footprint(
            centres[n, 0], centres[n, 1], centres[n, 2], R, t, fx, fy, cx, cy, vs
        )
        if d < 0:
            continue
        for pv in range(max(v0, 0), min(v1, H - 1) + 1):
            for pu in range(max(u0, 0), min(u1, W - 1) + 1):
                if d < zbuf[pv, pu]:
                    zbuf[pv, pu] = d
                    idbuf[pv, pu] = occ_id[n]


@njit(cache=True)
def _silhouette_area(centres, vs, R, t, fx, fy, cx, cy):
    """Pixels covered by the union of the footprints of these voxel centres, unbounded image plane."""
    n = centres.shape[0]
    rects = np.empty((n, 4), np.int64)
    m = 0
    for k in range(n):
        d, u0, u1, v0, v1 = _footprint(
            centres[k, 0], centres[k, 1], centres[k, 2], R, t, fx, fy, cx, cy, vs
        )
        if d >= 0 and u1 >= u0 and v1 >= v0:
            rects[m, 0], rects[m, 1], rects[m, 2], rects[m, 3] = u0, u1, v0, v1
            m += 1
    if m == 0:
        return 0
    umin, umax = rects[:m, 0].min(), rects[:m, 1].max()
    vmin, vmax = rects[:m, 2].min(), rects[:m, 3].max()
    canvas = np.zeros((vmax - vmin + 1, umax - umin + 1), np.uint8)
    for k in range(m):
        canvas[
            rects[k, 2] - vmin : rects[k, 3] - vmin + 1, rects[k, 0] - umin : rects[k, 1] - umin + 1
        ] = 1
    return int(canvas.sum())


def box_lattice(center, size_lwh, yaw: float, pitch_m: float) -> np.ndarray:
    """(M, 3) float64 points filling an upright box (centre (3,), size l w h, yaw about z) at
    ``pitch_m`` spacing (cell centres; at least one cell per side): the voxel centres the box
    would take in a grid of that voxel size."""
    axes = [
        (np.arange(n) + 0.5) * (s / n) - s / 2
        for s, n in ((float(v), max(1, int(np.ceil(float(v) / pitch_m)))) for v in size_lwh)
    ]
    local = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return local @ R.T + np.asarray(center, np.float64)


def visible_fractions(
    range_min,
    voxel_size_m: float,
    occupied: np.ndarray,
    instances: np.ndarray,
    ids,
    K: np.ndarray,
    width: int,
    height: int,
    T_base_from_cam: np.ndarray,
    outside: dict | None = None,
    oversample: int = 4,
) -> np.ndarray:
    """Visible fraction of each instance (see the module docstring).

    range_min: (3,) m, lower corner of the grid, base frame; voxel_size_m: edge, m.
    occupied: (X, Y, Z) bool / uint8, non-zero where a voxel blocks the view (any class).
    instances: (X, Y, Z) integer instance id per voxel (0 none); an instance's voxels count as occupied.
    ids: (N,) instance ids to measure. K: (3, 3) px; width, height: image size px.
    T_base_from_cam: (4, 4) float64.
    outside: {id: (M, 3) base-frame points} standing in for instances with no voxel in the grid
    (e.g. :func:`box_lattice` of their box at the voxel size), drawn like voxel centres.
    Returns (N,) float64 in [0, 1].
    """
    occupied = np.asarray(occupied).astype(bool)
    instances = np.asarray(instances)
    if occupied.shape != instances.shape or occupied.ndim != 3:
        raise ValueError(
            f"occupied {occupied.shape} and instances {instances.shape} must be the same (X, Y, Z)"
        )
    ids = np.asarray(ids, dtype=np.int64).reshape(-1)
    out = np.zeros(len(ids), np.float64)
    if len(ids) == 0:
        return out
    K = np.asarray(K, dtype=np.float64)
    T_cam_from_base = np.linalg.inv(np.asarray(T_base_from_cam, dtype=np.float64))
    R, t = (
        np.ascontiguousarray(T_cam_from_base[:3, :3]),
        np.ascontiguousarray(T_cam_from_base[:3, 3]),
    )
    lo = np.asarray(range_min, dtype=np.float64)
    vs = float(voxel_size_m)
    hi = lo + np.asarray(occupied.shape) * vs
    corners = np.array(np.meshgrid(*zip(lo, hi), indexing="ij")).reshape(3, -1).T
    far_m = np.linalg.norm(corners - np.asarray(T_base_from_cam)[:3, 3], axis=1).max()
    scale = min(1.0, far_m / vs / min(K[0, 0], K[1, 1]) * max(1, int(oversample)))
    W, H = max(1, int(np.ceil(width * scale))), max(1, int(np.ceil(height * scale)))
    fx, fy = K[0, 0] * W / width, K[1, 1] * H / height
    cx, cy = (K[0, 2] + 0.5) * W / width - 0.5, (K[1, 2] + 0.5) * H / height - 0.5
    blocking = occupied | (instances != 0)
    centres = [lo + (np.argwhere(blocking) + 0.5) * vs]
    occ_id = [instances[blocking].astype(np.int64)]
    for i, pts in (outside or {}).items():
        if int(i) in ids and not (occ_id[0] == int(i)).any():
            pts = np.asarray(pts, np.float64).reshape(-1, 3)
            centres.append(pts)
            occ_id.append(np.full(len(pts), int(i), np.int64))
    centres, occ_id = np.ascontiguousarray(np.concatenate(centres)), np.concatenate(occ_id)
    zbuf = np.full((H, W), np.inf)
    idbuf = np.zeros((H, W), np.int64)
    _nearest_id(centres, occ_id, vs, R, t, fx, fy, cx, cy, zbuf, idbuf)
    seen = np.bincount(idbuf.ravel(), minlength=int(max(ids.max(), 0)) + 1)
    for n, i in enumerate(ids):
        if i <= 0:
            continue
        area = _silhouette_area(
            np.ascontiguousarray(centres[occ_id == i]), vs, R, t, fx, fy, cx, cy
        )
        if area > 0:
            out[n] = min(1.0, seen[i] / area)
    return out
