"""Visibility masks of a robot-local grid: voxels crossed by this frame's LiDAR rays, and voxels
seen from the camera (along the ray from the camera centre, voxels up to and including the first
occupied one are observed; voxels behind it or outside the image stay unobserved).

Rays are walked with a 3D DDA (Amanatides & Woo) clipped to the grid box, in grid units.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from tasks.occupancy.threads import executor, resolve_threads


@njit(cache=True, inline="always")
def _walk(o0, o1, o2, e0, e1, e2, shape, occupied, out, stop_at_occupied):
    """Mark voxels of out crossed by the segment o -> e (grid units: the voxel [i, i + 1) per
    axis). out, occupied: the (X, Y, Z) grids flattened in C order (uint8). With
    stop_at_occupied, stop after the first voxel with occupied != 0."""
    dx = e0 - o0
    dy = e1 - o1
    dz = e2 - o2
    t0 = 0.0
    t1 = 1.0
    d = (dx, dy, dz)
    o = (o0, o1, o2)
    for a in range(3):
        if d[a] == 0.0:
            if o[a] < 0.0 or o[a] >= shape[a]:
                return
        else:
            ta = (0.0 - o[a]) / d[a]
            tb = (shape[a] - o[a]) / d[a]
            if ta > tb:
                ta, tb = tb, ta
            if ta > t0:
                t0 = ta
            if tb < t1:
                t1 = tb
    if t0 > t1:
        return
    # start in the voxel just inside the box along the ray
    tm = t0 + 1e-9 * (t1 - t0) if t1 > t0 else t0
    cx = min(max(int(math.floor(o0 + dx * tm)), 0), shape[0] - 1)
    cy = min(max(int(math.floor(o1 + dy * tm)), 0), shape[1] - 1)
    cz = min(max(int(math.floor(o2 + dz * tm)), 0), shape[2] - 1)
    big = 1e300
    if dx > 0:
        sx, tmx, tdx = 1, (cx + 1 - o0) / dx, 1.0 / dx
    elif dx < 0:
        sx, tmx, tdx = -1, (cx - o0) / dx, -1.0 / dx
    else:
        sx, tmx, tdx = 0, big, big
    if dy > 0:
        sy, tmy, tdy = 1, (cy + 1 - o1) / dy, 1.0 / dy
    elif dy < 0:
        sy, tmy, tdy = -1, (cy - o1) / dy, -1.0 / dy
    else:
        sy, tmy, tdy = 0, big, big
    if dz > 0:
        sz, tmz, tdz = 1, (cz + 1 - o2) / dz, 1.0 / dz
    elif dz < 0:
        sz, tmz, tdz = -1, (cz - o2) / dz, -1.0 / dz
    else:
        sz, tmz, tdz = 0, big, big
    # flat C-order index, stepped with the axis; only the stepped axis can leave the box
    s1 = shape[2]
    s0 = shape[1] * s1
    flat = (cx * shape[1] + cy) * s1 + cz
    while True:
        out[flat] = 1
        if stop_at_occupied and occupied[flat] != 0:
            return
        if tmx < tmy:
            if tmx < tmz:
                if tmx > t1:
                    return
                cx += sx
                tmx += tdx
                if cx < 0 or cx >= shape[0]:
                    return
                flat += sx * s0
            else:
                if tmz > t1:
                    return
                cz += sz
                tmz += tdz
                if cz < 0 or cz >= shape[2]:
                    return
                flat += sz
        elif tmy < tmz:
            if tmy > t1:
                return
            cy += sy
            tmy += tdy
            if cy < 0 or cy >= shape[1]:
                return
            flat += sy * s1
        else:
            if tmz > t1:
                return
            cz += sz
            tmz += tdz
            if cz < 0 or cz >= shape[2]:
                return
            flat += sz


@njit(cache=True, nogil=True)
def _walk_all(origin, ends, shape, occupied, out, stop_at_occupied, r0, r1):
    # Rays only ever store 1, so the result depends neither on the ray order nor on how the rays
    # are split over threads sharing ``out``.
    for i in range(r0, r1):
        _walk(
            origin[0],
            origin[1],
            origin[2],
            ends[i, 0],
            ends[i, 1],
            ends[i, 2],
            shape,
            occupied,
            out,
            stop_at_occupied,
        )


@njit(cache=True, nogil=True)
def _walk_camera(origin, Kinv, R, us, vs, far, shape, occupied, out, r0, r1):
    """Rays r0..r1 of one ray per sampled pixel (ray r: us[r % len(us)], vs[r // len(us)]),
    directions R @ Kinv @ (u, v, 1), from origin (grid units) to far (grid units) or the first
    occupied voxel."""
    nu = us.shape[0]
    for r in range(r0, r1):
        u = us[r % nu]
        v = vs[r // nu]
        cx = Kinv[0, 0] * u + Kinv[0, 1] * v + Kinv[0, 2]
        cy = Kinv[1, 0] * u + Kinv[1, 1] * v + Kinv[1, 2]
        cz = Kinv[2, 0] * u + Kinv[2, 1] * v + Kinv[2, 2]
        dx = R[0, 0] * cx + R[0, 1] * cy + R[0, 2] * cz
        dy = R[1, 0] * cx + R[1, 1] * cy + R[1, 2] * cz
        dz = R[2, 0] * cx + R[2, 1] * cy + R[2, 2] * cz
        n = math.sqrt(dx * dx + dy * dy + dz * dz)
        _walk(
            origin[0],
            origin[1],
            origin[2],
            origin[0] + dx / n * far,
            origin[1] + dy / n * far,
            origin[2] + dz / n * far,
            shape,
            occupied,
            out,
            True,
        )


#: rays per thread below which splitting the rays over threads does not pay
_MIN_RAYS_PER_THREAD = 8192


def _split_rays(walk, n_rays: int, threads: int | None) -> None:
    """Run walk(r0, r1) over [0, n_rays) in contiguous parts, one per thread (all share the
    output; every write stores 1, so the result is the same for any split)."""
    n = min(resolve_threads(threads), max(1, n_rays // _MIN_RAYS_PER_THREAD))
    bounds = np.linspace(0, n_rays, n + 1).astype(np.int64)
    if n == 1:
        walk(0, n_rays)
        return
    list(executor(n).map(lambda k: walk(bounds[k], bounds[k + 1]), range(n)))


def lidar_mask(
    spec, points_base: np.ndarray, origin_base: np.ndarray, threads: int | None = None
) -> np.ndarray:
    """Voxels traversed or hit by this frame's LiDAR rays.

    spec: GridSpec (base frame). points_base: (N, 3) float metres, base frame (the endpoints).
    origin_base: (3,) the LiDAR centre in the base frame. threads: rays walked in parallel (None:
    one thread per core). Returns (X, Y, Z) uint8 (1 observed).
    """
    shape = np.asarray(spec.shape, dtype=np.int64)
    out = np.zeros(spec.shape, dtype=np.uint8)
    p = np.asarray(points_base, dtype=np.float64).reshape(-1, 3)
    p = p[np.all(np.isfinite(p), axis=1)]
    if len(p):
        g = np.ascontiguousarray((p - spec.origin) / spec.voxel_size_m)
        o = (np.asarray(origin_base, dtype=np.float64) - spec.origin) / spec.voxel_size_m
        flat = out.reshape(-1)
        _split_rays(
            lambda r0, r1: _walk_all(o, g, shape, flat, flat, False, r0, r1), len(g), threads
        )
    return out


def auto_pixel_stride(spec, K: np.ndarray, T_base_from_cam: np.ndarray) -> int:
    """Largest pixel stride whose rays are at most one voxel apart at the grid's farthest corner."""
    corners = (
        np.array(np.meshgrid(*zip(spec.range_min, spec.range_max), indexing="ij")).reshape(3, -1).T
    )
    far = np.linalg.norm(corners - np.asarray(T_base_from_cam)[:3, 3], axis=1).max()
    f = float(min(K[0, 0], K[1, 1]))
    return max(1, int(spec.voxel_size_m * f / far))


@njit(cache=True)
def _zbuffer(occ_idx, lo, vs, R, t, fx, fy, cx, cy, zbuf):
    """Per pixel the smallest camera distance of an occupied voxel centre whose square footprint
    (half-width vs / 2 projected at the centre's depth) covers the pixel."""
    H, W = zbuf.shape
    for n in range(occ_idx.shape[0]):
        bx = lo[0] + (occ_idx[n, 0] + 0.5) * vs
        by = lo[1] + (occ_idx[n, 1] + 0.5) * vs
        bz = lo[2] + (occ_idx[n, 2] + 0.5) * vs
        x = R[0, 0] * bx + R[0, 1] * by + R[0, 2] * bz + t[0]
        y = R[1, 0] * bx + R[1, 1] * by + R[1, 2] * bz + t[1]
        z = R[2, 0] * bx + R[2, 1] * by + R[2, 2] * bz + t[2]
        if z <= 1e-6:
            continue
        d = math.sqrt(x * x + y * y + z * z)
        u = fx * x / z + cx
        v = fy * y / z + cy
        hu = 0.5 * vs * fx / z
        hv = 0.5 * vs * fy / z
        u0 = max(int(math.floor(u - hu + 0.5)), 0)
        u1 = min(int(math.floor(u + hu + 0.5)), W - 1)
        v0 = max(int(math.floor(v - hv + 0.5)), 0)
        v1 = min(int(math.floor(v + hv + 0.5)), H - 1)
        for pv in range(v0, v1 + 1):
            for pu in range(u0, u1 + 1):
                if d < zbuf[pv, pu]:
                    zbuf[pv, pu] = d


@njit(cache=True)
def _visible(nx, ny, nz, lo, vs, R, t, fx, fy, cx, cy, zbuf, out):
    """A voxel is observed when its centre projects into the image and no occupied footprint on
    that pixel is nearer (one ray per voxel centre)."""
    H, W = zbuf.shape
    for i in range(nx):
        bx = lo[0] + (i + 0.5) * vs
        for j in range(ny):
            by = lo[1] + (j + 0.5) * vs
            for k in range(nz):
                bz = lo[2] + (k + 0.5) * vs
                z = R[2, 0] * bx + R[2, 1] * by + R[2, 2] * bz + t[2]
                if z <= 1e-6:
                    continue
                x = R[0, 0] * bx + R[0, 1] * by + R[0, 2] * bz + t[0]
                y = R[1, 0] * bx + R[1, 1] * by + R[1, 2] * bz + t[1]
                pu = int(math.floor(fx * x / z + cx + 0.5))
                pv = int(math.floor(fy * y / z + cy + 0.5))
                if pu < 0 or pv < 0 or pu >= W or pv >= H:
                    continue
                if math.sqrt(x * x + y * y + z * z) <= zbuf[pv, pu] * (1.0 + 1e-12):
                    out[i, j, k] = 1


def camera_mask(
    spec,
    occupied: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    T_base_from_cam: np.ndarray,
    pixel_stride: int | None,
    method: str,
    threads: int | None = None,
) -> np.ndarray:
    """Voxels visible from the camera.

    spec: GridSpec (base frame). occupied: (X, Y, Z) bool/uint8, non-zero where a voxel blocks the
    view. K: (3, 3); width, height: image size (pixels). T_base_from_cam: (4, 4) float64.
    method "zbuffer": one ray per voxel centre; a voxel is observed when it projects into
    the image and no occupied voxel in front covers that pixel (occupied voxels splat square
    footprints into a depth buffer whose pixels are no larger than a voxel at the grid's farthest
    corner). method "rays": one ray per sampled pixel (pixel_stride, None: auto) walked with a DDA
    up to and including the first occupied voxel; threads: rays walked in parallel (None: one
    thread per core). Returns (X, Y, Z) uint8, 1 observed.
    """
    if occupied.shape != spec.shape:
        raise ValueError(f"occupied has shape {occupied.shape}, grid is {spec.shape}")
    if method not in ("zbuffer", "rays"):
        raise ValueError(f"method must be 'zbuffer' or 'rays', got {method!r}")
    K = np.asarray(K, dtype=np.float64)
    T = np.asarray(T_base_from_cam, dtype=np.float64)
    corners = (
        np.array(np.meshgrid(*zip(spec.range_min, spec.range_max), indexing="ij")).reshape(3, -1).T
    )
    far_m = np.linalg.norm(corners - T[:3, 3], axis=1).max()
    out = np.zeros(spec.shape, dtype=np.uint8)
    if method == "zbuffer":
        # image pixels no larger than a voxel at the farthest corner (and no finer than the camera)
        scale = min(1.0, far_m / spec.voxel_size_m / min(K[0, 0], K[1, 1]))
        W, H = max(1, int(np.ceil(width * scale))), max(1, int(np.ceil(height * scale)))
        fx, fy = K[0, 0] * W / width, K[1, 1] * H / height
        cx, cy = (K[0, 2] + 0.5) * W / width - 0.5, (K[1, 2] + 0.5) * H / height - 0.5
        T_cam_from_base = np.linalg.inv(T)
        R, t = (
            np.ascontiguousarray(T_cam_from_base[:3, :3]),
            np.ascontiguousarray(T_cam_from_base[:3, 3]),
        )
        zbuf = np.full((H, W), np.inf)
        occ_idx = np.argwhere(occupied).astype(np.int64)
        _zbuffer(occ_idx, spec.origin, spec.voxel_size_m, R, t, fx, fy, cx, cy, zbuf)
        nx, ny, nz = spec.shape
        _visible(nx, ny, nz, spec.origin, spec.voxel_size_m, R, t, fx, fy, cx, cy, zbuf, out)
        return out
    stride = auto_pixel_stride(spec, K, T) if pixel_stride is None else pixel_stride
    stride = max(1, int(stride))
    far = far_m / spec.voxel_size_m + 1.0
    o = (T[:3, 3] - spec.origin) / spec.voxel_size_m
    us = np.arange(stride / 2 - 0.5, width - 0.5, stride)  # centres of stride x stride pixel blocks
    vs = np.arange(stride / 2 - 0.5, height - 0.5, stride)
    occ = np.ascontiguousarray(occupied.astype(np.uint8, copy=False))
    Kinv, R, shape = (
        np.linalg.inv(K),
        np.ascontiguousarray(T[:3, :3]),
        np.asarray(spec.shape, dtype=np.int64),
    )
    occ_flat, out_flat = occ.reshape(-1), out.reshape(-1)
    _split_rays(
        lambda r0, r1: _walk_camera(o, Kinv, R, us, vs, far, shape, occ_flat, out_flat, r0, r1),
        len(us) * len(vs),
        threads,
    )
    return out
