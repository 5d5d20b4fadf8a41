"""Free / unknown / occupied space with OctoMap's semantics over a sparse voxel map.

Semantics (OctoMap 1.10 ``insertPointCloud``, the defaults of ``AbstractOccupancyOcTree``):

- per voxel a float32 log-odds, starting at 0 when first updated; a hit adds
  ``logit(prob_hit)`` (+0.847), a miss adds ``logit(prob_miss)`` (-0.405); the value is clamped to
  ``[logit(clamp_min), logit(clamp_max)]`` = [-2.0, +3.5]; occupied iff log-odds >= 0; a voxel that
  was never updated is unknown;
- per scan: a 3D DDA (Amanatides & Woo, as OctoMap's ``computeRayKeys``) from the sensor origin to
  each endpoint; the origin voxel is on the ray, the end voxel is not; every voxel is updated at
  most once per scan and a voxel holding an endpoint is never freed by the same scan (occupied
  wins); a point farther than ``max_range_m`` is not inserted: its ray is cut at ``max_range_m`` and
  only frees;
- voxels are aligned to multiples of the resolution around 0 (OctoMap's key = floor(x / res) +
  2^15), so with the same resolution our voxels coincide with OctoMap's.

Storage: voxels are grouped in 8 x 8 x 8 blocks; an open-addressing hash table (int64 block key ->
row) indexes a block pool (log-odds float32 (B, 512), NaN = unknown). A scan first marks its voxels
in two 64-byte bitsets per block (on a ray / holds an endpoint), then applies one update per marked
voxel (hit wins). Memory grows with the observed volume (about 2.2 KiB per touched block, i.e. per
(8 * voxel_size_m)^3 of space crossed by any ray), not with the number of scans.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from tasks.occupancy.settings import FreeSpaceParams
from tasks.occupancy.threads import executor, resolve_threads

_BLOCK_SHIFT = 3
_BLOCK_CELLS = 1 << (3 * _BLOCK_SHIFT)  # 512
# Block keys pack 21 bits per axis with an offset of 2^20 blocks: +-8.4 M voxels per axis.


class OccupancyError(ValueError):
    """Bad input to the occupancy map (shapes, non-finite values, parameters)."""


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


@njit(cache=True, inline="always")
def _block_key(kx, ky, kz):
    return (((kx >> 3) + 1048576) << 42) | (((ky >> 3) + 1048576) << 21) | ((kz >> 3) + 1048576)


@njit(cache=True, inline="always")
def _cell(kx, ky, kz):
    return ((kx & 7) << 6) | ((ky & 7) << 3) | (kz & 7)


_KEY_OFFSET = 1 << 20  # packing voxel keys into one int64 (21 bits per axis)
_KEY_MASK = (1 << 21) - 1


@njit(cache=True, inline="always")
def _slot(bk, mask):
    # splitmix64-style mixing (every key bit reaches the low bits), then a power-of-two mask.
    h = np.uint64(bk)
    h ^= h >> np.uint64(31)
    h *= np.uint64(0xBF58476D1CE4E5B9)
    h ^= h >> np.uint64(29)
    return np.int64(h & np.uint64(mask))


@njit(cache=True, inline="always")
def _find(hkeys, hvals, bk):
    """Pool row of block ``bk`` or -1."""
    mask = hkeys.shape[0] - 1
    s = _slot(bk, mask)
    while True:
        k = hkeys[s]
        if k == bk:
            return hvals[s]
        if k == -1:
            return -1
        s = (s + 1) & mask


@njit(cache=True, inline="always")
def _find_or_add(hkeys, hvals, bkeys, nused, bk):
    """Pool row of block ``bk``, adding it when absent; -1 when the pool is full."""
    mask = hkeys.shape[0] - 1
    s = _slot(bk, mask)
    while True:
        k = hkeys[s]
        if k == bk:
            return hvals[s]
        if k == -1:
            b = nused[0]
            if b >= bkeys.shape[0]:
                return -1
            hkeys[s] = bk
            hvals[s] = b
            bkeys[b] = bk
            nused[0] = b + 1
            return b
        s = (s + 1) & mask


@njit(cache=True)
def _rehash(bkeys, nused, hkeys, hvals):
    mask = hkeys.shape[0] - 1
    for b in range(nused):
        bk = bkeys[b]
        s = _slot(bk, mask)
        while hkeys[s] != -1:
            s = (s + 1) & mask
        hkeys[s] = bk
        hvals[s] = b


@njit(cache=True, inline="always")
def _touch_block(hkeys, hvals, bkeys, nused, bstamp, touched, ntouched, bk, scan_id):
    """Pool row of block ``bk`` (added if absent, -1 when the pool is full), listed as touched."""
    b = _find_or_add(hkeys, hvals, bkeys, nused, bk)
    if b >= 0 and bstamp[b] != scan_id:
        bstamp[b] = scan_id
        touched[ntouched[0]] = b
        ntouched[0] += 1
    return b


@njit(cache=True, inline="always")
def _outside(kx, ky, rb):
    """Is voxel key (kx, ky, .) outside the region of blocks rb = (bx0, bx1, by0, by1)?"""
    bx = kx >> 3
    by = ky >> 3
    return bx < rb[0] or bx >= rb[1] or by < rb[2] or by >= rb[3]


@njit(cache=True, inline="always")
def _dense_row(kx, ky, kz, b0, nb):
    """Row of voxel key (kx, ky, kz)'s block in a dense box of blocks, -1 outside it."""
    bx = (kx >> 3) - b0[0]
    by = (ky >> 3) - b0[1]
    bz = (kz >> 3) - b0[2]
    if bx < 0 or by < 0 or bz < 0 or bx >= nb[0] or by >= nb[1] or bz >= nb[2]:
        return np.int64(-1)
    return (bx * nb[1] + by) * nb[2] + bz


@njit(cache=True, inline="always")
def _ray_end(ox, oy, oz, px, py, pz, max_range):
    """Where the ray to endpoint p stops: p, or (OctoMap) origin + direction * max_range when p
    is farther (that ray only frees). Returns (ex, ey, ez, length)."""
    dx = px - ox
    dy = py - oy
    dz = pz - oz
    length = math.sqrt(dx * dx + dy * dy + dz * dz)
    if max_range >= 0.0 and length > max_range:
        s = max_range / length
        px = ox + dx * s
        py = oy + dy * s
        pz = oz + dz * s
        dx = px - ox
        dy = py - oy
        dz = pz - oz
        length = math.sqrt(dx * dx + dy * dy + dz * dz)
    return px, py, pz, length


@njit(cache=True, inline="always")
def _walk_ray(
    ox,
    oy,
    oz,
    ex,
    ey,
    ez,
    length,
    res,
    scan_id,
    hkeys,
    hvals,
    bkeys,
    nused,
    bstamp,
    touched,
    ntouched,
    fbits,
    ckeys,
    crows,
    dense,
    b0,
    nb,
    rb,
):
    """Set the free bit of every voxel on the ray origin -> end, end voxel excluded: the 3D DDA
    of OctoMap's computeRayKeys (the origin voxel is on the ray). Returns 0 when done, -1 when
    the block pool is full, -2 when a voxel is outside the dense box.

    rb: the region, blocks [rb[0], rb[1]) x [rb[2], rb[3]) in x / y: voxels outside it are
    walked through but not marked (no block is made for them).

    Block rows: a dense box row, or a pool row found through ckeys / crows, a direct-mapped cache
    of this scan's blocks (1024 slots, stays in L1: rays from one origin revisit the same
    blocks, so most block changes skip the hash table). The lookup is written out here, not
    called: a call per block change passing the pool's arrays costs as much as the walk itself.
    """
    inv = 1.0 / res
    cx = np.int64(math.floor(ox * inv))
    cy = np.int64(math.floor(oy * inv))
    cz = np.int64(math.floor(oz * inv))
    kex = np.int64(math.floor(ex * inv))
    key = np.int64(math.floor(ey * inv))
    kez = np.int64(math.floor(ez * inv))
    if cx == kex and cy == key and cz == kez:
        return 0
    dx = (ex - ox) / length
    dy = (ey - oy) / length
    dz = (ez - oz) / length
    big = 1e300
    sx = 1 if dx > 0 else (-1 if dx < 0 else 0)
    sy = 1 if dy > 0 else (-1 if dy < 0 else 0)
    sz = 1 if dz > 0 else (-1 if dz < 0 else 0)
    tmx, tdx, tmy, tdy, tmz, tdz = big, big, big, big, big, big
    if sx != 0:
        tmx = ((cx + 0.5) * res + sx * res * 0.5 - ox) / dx
        tdx = res / abs(dx)
    if sy != 0:
        tmy = ((cy + 0.5) * res + sy * res * 0.5 - oy) / dy
        tdy = res / abs(dy)
    if sz != 0:
        tmz = ((cz + 0.5) * res + sz * res * 0.5 - oz) / dz
        tdz = res / abs(dz)
    # a step enters a new block when the stepped coordinate's low 3 bits wrap
    wx = 0 if sx > 0 else 7
    wy = 0 if sy > 0 else 7
    wz = 0 if sz > 0 else 7
    b = np.int64(-1)
    new_block = True
    while True:
        if new_block:
            new_block = False
            if _outside(cx, cy, rb):
                b = -1
            elif dense:
                b = _dense_row(cx, cy, cz, b0, nb)
                if b < 0:
                    return -2
            else:
                bk = _block_key(cx, cy, cz)
                slot = ((cx >> 3) & 15) | (((cy >> 3) & 15) << 4) | (((cz >> 3) & 3) << 8)
                if ckeys[slot] == bk:
                    b = crows[slot]
                else:
                    b = _touch_block(
                        hkeys, hvals, bkeys, nused, bstamp, touched, ntouched, bk, scan_id
                    )
                    if b < 0:
                        return -1
                    ckeys[slot] = bk
                    crows[slot] = b
        if b >= 0:
            c = _cell(cx, cy, cz)
            fbits[b, c >> 6] |= np.uint64(1) << np.uint64(c & 63)
        if tmx < tmy:
            if tmx < tmz:
                cx += sx
                tmx += tdx
                new_block = (cx & 7) == wx
            else:
                cz += sz
                tmz += tdz
                new_block = (cz & 7) == wz
        elif tmy < tmz:
            cy += sy
            tmy += tdy
            new_block = (cy & 7) == wy
        else:
            cz += sz
            tmz += tdz
            new_block = (cz & 7) == wz
        if cx == kex and cy == key and cz == kez:
            return 0
        if min(tmx, min(tmy, tmz)) > length:
            return 0


@njit(cache=True, inline="always")
def _mark_endpoints(
    points,
    i0,
    ox,
    oy,
    oz,
    max_range,
    res,
    scan_id,
    hkeys,
    hvals,
    bkeys,
    nused,
    bstamp,
    touched,
    ntouched,
    hbits,
    dense,
    b0,
    nb,
    rb,
):
    """Set the hit bit of the voxel of every endpoint points[i0:] within max_range. Returns -1
    when done, else the endpoint where the pool ran out (-1 - i: outside the dense box)."""
    inv = 1.0 / res
    last_bk = np.int64(-1)
    b = np.int64(-1)
    for i in range(i0, points.shape[0]):
        px = points[i, 0]
        py = points[i, 1]
        pz = points[i, 2]
        if (
            max_range >= 0.0
            and math.sqrt((px - ox) ** 2 + (py - oy) ** 2 + (pz - oz) ** 2) > max_range
        ):
            continue
        kx = np.int64(math.floor(px * inv))
        ky = np.int64(math.floor(py * inv))
        kz = np.int64(math.floor(pz * inv))
        bk = _block_key(kx, ky, kz)
        if bk != last_bk:  # consecutive endpoints mostly share a block
            if _outside(kx, ky, rb):
                b = -1
            elif dense:
                b = _dense_row(kx, ky, kz, b0, nb)
                if b < 0:
                    return -1 - i
            else:
                b = _touch_block(hkeys, hvals, bkeys, nused, bstamp, touched, ntouched, bk, scan_id)
                if b < 0:
                    return i
            last_bk = bk
        if b >= 0:
            c = _cell(kx, ky, kz)
            hbits[b, c >> 6] |= np.uint64(1) << np.uint64(c & 63)
    return -1


@njit(cache=True, nogil=True)
def _mark_scan(
    points,
    origin,
    max_range,
    res,
    scan_id,
    hkeys,
    hvals,
    bkeys,
    nused,
    bstamp,
    touched,
    ntouched,
    fbits,
    hbits,
    phase0,
    ray0,
    dense,
    b0,
    nb,
    rb,
):
    """Mark one scan's voxels in per-block bitsets: fbits = on a ray, hbits = holds an endpoint.

    Phase 0 walks the rays, phase 1 marks the endpoints (within max_range). Returns (phase, ray)
    where the block pool ran out, or (2, 0) when done; resuming a ray after the pool grew sets
    the same bits again. One 64-byte bitset per block keeps the marks of a scan in L1 cache: the
    walk runs close to the speed of the bare DDA.

    dense: the bitsets are a private dense box of blocks instead of the map's pool: block
    (bx, by, bz) is row ((bx - b0[0]) * nb[1] + by - b0[1]) * nb[2] + bz - b0[2]; the map is not
    touched (so several threads can mark disjoint rays at once, nogil). Returns (3, ray) if a
    voxel falls outside the box. rb: the region marked (see :func:`_walk_ray`).
    """
    ox, oy, oz = origin[0], origin[1], origin[2]
    ckeys = np.full(1024, -1, dtype=np.int64)
    crows = np.zeros(1024, dtype=np.int64)
    n = points.shape[0]
    for i in range(ray0 if phase0 == 0 else n, n):
        ex, ey, ez, length = _ray_end(
            ox, oy, oz, points[i, 0], points[i, 1], points[i, 2], max_range
        )
        status = _walk_ray(
            ox,
            oy,
            oz,
            ex,
            ey,
            ez,
            length,
            res,
            scan_id,
            hkeys,
            hvals,
            bkeys,
            nused,
            bstamp,
            touched,
            ntouched,
            fbits,
            ckeys,
            crows,
            dense,
            b0,
            nb,
            rb,
        )
        if status < 0:
            return (3 if status == -2 else 0), i
    stop = _mark_endpoints(
        points,
        0 if phase0 == 0 else ray0,
        ox,
        oy,
        oz,
        max_range,
        res,
        scan_id,
        hkeys,
        hvals,
        bkeys,
        nused,
        bstamp,
        touched,
        ntouched,
        hbits,
        dense,
        b0,
        nb,
        rb,
    )
    if stop >= 0:
        return 1, stop
    if stop < -1:
        return 3, -1 - stop
    return 2, 0


@njit(cache=True, inline="always")
def _apply_word(logodds, b, w, hw, fw, hit, miss, lo_min, lo_max):
    """Update the voxels of word w of pool block b: hits in hw, misses in fw (hit wins)."""
    one = np.uint64(1)
    for j in range(64):
        bit = one << np.uint64(j)
        hit_here = (hw & bit) != 0
        if hit_here or (fw & bit) != 0:
            c = w * 64 + j
            v = logodds[b, c]
            if v != v:  # first update of an unknown voxel
                v = np.float32(0.0)
            if hit_here:
                v = min(v + hit, lo_max)
            else:
                v = max(v + miss, lo_min)
            logodds[b, c] = v


@njit(cache=True)
def _apply_marks(touched, ntouched, fbits, hbits, logodds, hit, miss, lo_min, lo_max):
    """One update per marked voxel of the touched blocks (occupied wins), then clear the marks."""
    for t in range(ntouched[0]):
        b = touched[t]
        for w in range(_BLOCK_CELLS // 64):
            hw = hbits[b, w]
            fw = fbits[b, w]
            hbits[b, w] = 0
            fbits[b, w] = 0
            if hw != 0 or fw != 0:
                _apply_word(logodds, b, w, hw, fw, hit, miss, lo_min, lo_max)
    ntouched[0] = 0


@njit(cache=True)
def _apply_dense(
    fbits, hbits, b0, nb, row0, hkeys, hvals, bkeys, nused, logodds, hit, miss, lo_min, lo_max
):
    """Apply the union of per-thread dense marks (T, rows, 8) to the map, from box row ``row0``.

    Returns the row where the block pool ran out (grow and resume there), or -1 when done.
    """
    nt = fbits.shape[0]
    words = _BLOCK_CELLS // 64
    for r in range(row0, fbits.shape[1]):
        any_mark = False
        for t in range(nt):
            for w in range(words):
                if fbits[t, r, w] != 0 or hbits[t, r, w] != 0:
                    any_mark = True
        if not any_mark:
            continue
        bz = r % nb[2] + b0[2]
        by = (r // nb[2]) % nb[1] + b0[1]
        bx = r // (nb[1] * nb[2]) + b0[0]
        b = _find_or_add(hkeys, hvals, bkeys, nused, _block_key(bx << 3, by << 3, bz << 3))
        if b < 0:
            return r
        for w in range(words):
            hw = np.uint64(0)
            fw = np.uint64(0)
            for t in range(nt):
                hw |= hbits[t, r, w]
                fw |= fbits[t, r, w]
            if hw != 0 or fw != 0:
                _apply_word(logodds, b, w, hw, fw, hit, miss, lo_min, lo_max)
    return -1


@njit(cache=True, inline="always")
def _state(hkeys, hvals, logodds, kx, ky, kz, thres):
    b = _find(hkeys, hvals, _block_key(kx, ky, kz))
    if b < 0:
        return -1
    v = logodds[b, _cell(kx, ky, kz)]
    if v != v:
        return -1
    return 1 if v >= thres else 0


@njit(cache=True)
def _query_points(points, res, hkeys, hvals, logodds, thres, out):
    inv = 1.0 / res
    for i in range(points.shape[0]):
        kx = np.int64(math.floor(points[i, 0] * inv))
        ky = np.int64(math.floor(points[i, 1] * inv))
        kz = np.int64(math.floor(points[i, 2] * inv))
        out[i] = _state(hkeys, hvals, logodds, kx, ky, kz, thres)


@njit(cache=True)
def _query_grid(R, t, lo, vs, nx, ny, nz, res, hkeys, hvals, logodds, thres, out):
    inv = 1.0 / res
    last_bk = np.int64(-1)
    last_b = np.int64(-1)
    for i in range(nx):
        gx = lo[0] + (i + 0.5) * vs
        for j in range(ny):
            gy = lo[1] + (j + 0.5) * vs
            for k in range(nz):
                gz = lo[2] + (k + 0.5) * vs
                kx = np.int64(math.floor((R[0, 0] * gx + R[0, 1] * gy + R[0, 2] * gz + t[0]) * inv))
                ky = np.int64(math.floor((R[1, 0] * gx + R[1, 1] * gy + R[1, 2] * gz + t[1]) * inv))
                kz = np.int64(math.floor((R[2, 0] * gx + R[2, 1] * gy + R[2, 2] * gz + t[2]) * inv))
                bk = _block_key(kx, ky, kz)
                if bk != last_bk:  # neighbouring grid voxels mostly share a map block
                    last_bk = bk
                    last_b = _find(hkeys, hvals, bk)
                if last_b < 0:
                    out[i, j, k] = -1
                    continue
                v = logodds[last_b, _cell(kx, ky, kz)]
                if v != v:
                    out[i, j, k] = -1
                else:
                    out[i, j, k] = 1 if v >= thres else 0


@njit(cache=True)
def _export(bkeys, logodds, nused):
    count = 0
    for b in range(nused):
        for c in range(_BLOCK_CELLS):
            if logodds[b, c] == logodds[b, c]:
                count += 1
    keys = np.empty((count, 3), dtype=np.int64)
    vals = np.empty(count, dtype=np.float32)
    n = 0
    for b in range(nused):
        bk = bkeys[b]
        bx = ((bk >> 42) & 2097151) - 1048576
        by = ((bk >> 21) & 2097151) - 1048576
        bz = (bk & 2097151) - 1048576
        for c in range(_BLOCK_CELLS):
            v = logodds[b, c]
            if v == v:
                keys[n, 0] = (bx << 3) | (c >> 6)
                keys[n, 1] = (by << 3) | ((c >> 3) & 7)
                keys[n, 2] = (bz << 3) | (c & 7)
                vals[n] = v
                n += 1
    return keys, vals


@njit(cache=True)
def _import(keys, vals, start, hkeys, hvals, bkeys, logodds, nused):
    """Write voxels keys[start:] into the pool; returns the row where the pool ran out (grow and
    resume there) or -1 when done."""
    last_bk = np.int64(-1)
    b = np.int64(-1)
    for i in range(start, keys.shape[0]):
        kx = keys[i, 0]
        ky = keys[i, 1]
        kz = keys[i, 2]
        bk = _block_key(kx, ky, kz)
        if bk != last_bk:  # exported maps list a block's voxels together
            b = _find_or_add(hkeys, hvals, bkeys, nused, bk)
            if b < 0:
                return i
            last_bk = bk
        logodds[b, _cell(kx, ky, kz)] = vals[i]
    return -1


_NO_BOX = np.zeros(3, dtype=np.int64)
#: the whole plane as a region of blocks (bx0, bx1, by0, by1): block keys hold +-2^20 blocks per axis
_EVERYWHERE = np.array([-(1 << 40), 1 << 40, -(1 << 40), 1 << 40], dtype=np.int64)
#: a ray's voxels lie inside the box of its origin and end voxels grown by this many voxels (the
#: DDA steps at most one voxel past a face in float corner cases; a block of margin)
_RAY_MARGIN_VOXELS = 8
#: Dense marking boxes above this many blocks (x threads) use the sparse path: 2 bitsets of 64 B
#: per block, so at most 32 MiB; a 20 m OS1-128 scan needs ~6,000 blocks at 0.2 m, ~300,000 at 0.05 m.
_DENSE_MAX_BLOCKS = 1 << 18
_MIN_RAYS_PER_THREAD = 4096
_CHUNKS_PER_THREAD = 8


@njit(cache=True, nogil=True)
def _scan_box(pts, origin, max_range_m, res):
    """Blocks (b0 (3,) int64, nb (3,) int64) of a box holding every voxel the scan's rays can
    touch: the origin and the (range-cut) endpoints, with one block of margin."""
    lo = origin.copy()
    hi = origin.copy()
    for i in range(pts.shape[0]):
        d0 = pts[i, 0] - origin[0]
        d1 = pts[i, 1] - origin[1]
        d2 = pts[i, 2] - origin[2]
        length = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        s = 1.0
        if max_range_m >= 0.0 and length > max_range_m:
            s = max_range_m / length
        e = (origin[0] + d0 * s, origin[1] + d1 * s, origin[2] + d2 * s)
        for a in range(3):
            lo[a] = min(lo[a], e[a])
            hi[a] = max(hi[a], e[a])
    b0 = np.empty(3, dtype=np.int64)
    nb = np.empty(3, dtype=np.int64)
    for a in range(3):
        b0[a] = (np.int64(math.floor(lo[a] / res)) >> _BLOCK_SHIFT) - 1
        nb[a] = (np.int64(math.floor(hi[a] / res)) >> _BLOCK_SHIFT) + 2 - b0[a]
    return b0, nb


def _region_blocks(region) -> np.ndarray:
    """(bx0, bx1, by0, by1) blocks of a region given in voxel keys (multiples of 8)."""
    r = np.asarray(region, dtype=np.int64).reshape(-1)
    if r.shape != (4,) or np.any(r % 8) or r[0] >= r[1] or r[2] >= r[3]:
        raise OccupancyError(
            f"region must be (kx0, kx1, ky0, ky1) with kx0 < kx1, ky0 < ky1, "
            f"multiples of 8 voxels; got {tuple(region)}"
        )
    return r >> _BLOCK_SHIFT


def _rays_reaching(pts: np.ndarray, origin: np.ndarray, res: float, region) -> np.ndarray:
    """(N,) bool: rays origin -> pts[i] whose voxel box (grown by _RAY_MARGIN_VOXELS) meets the
    region's keys in x and y; the others cannot touch a voxel of the region."""
    inv = 1.0 / res
    m = _RAY_MARGIN_VOXELS
    ok = np.ones(len(pts), dtype=bool)
    for a in range(2):
        k = np.floor(pts[:, a] * inv).astype(np.int64)
        ko = int(math.floor(origin[a] * inv))
        ok &= (np.maximum(k, ko) + m >= region[2 * a]) & (np.minimum(k, ko) - m < region[2 * a + 1])
    return ok


class OccupancyMap:
    """A sparse occupancy map of one sequence in the world frame, fed scan by scan.

    params: its resolution (``voxel_size_m``, OctoMap's ``res``) and sensor model (``prob_hit``,
    ``prob_miss``, ``clamp_min``, ``clamp_max``, ``occupancy_threshold``: OctoMap's
    probabilities, OctoMap's defaults); ``max_range_m`` and ``discretize`` are given per scan
    (:meth:`insert_scan`, as OctoMap's ``insertPointCloud`` takes them).
    State lives on the instance; ``insert_scan`` advances it by one scan.
    """

    def __init__(
        self,
        params: FreeSpaceParams,
        initial_blocks: int = 1024,
        threads: int | None = None,
    ) -> None:
        p = params
        if not p.voxel_size_m > 0:
            raise OccupancyError(f"voxel_size_m must be > 0, got {p.voxel_size_m}")
        for name, value in (
            ("prob_hit", p.prob_hit),
            ("prob_miss", p.prob_miss),
            ("clamp_min", p.clamp_min),
            ("clamp_max", p.clamp_max),
            ("occupancy_threshold", p.occupancy_threshold),
        ):
            if not 0.0 < value < 1.0:
                raise OccupancyError(f"{name} must be in (0, 1), got {value}")
        if not (p.prob_miss < 0.5 < p.prob_hit and p.clamp_min < p.clamp_max):
            raise OccupancyError(
                f"expected prob_miss < 0.5 < prob_hit and clamp_min < clamp_max, got "
                f"{p.prob_miss}, {p.prob_hit}, {p.clamp_min}, {p.clamp_max}"
            )
        if threads is not None and threads < 1:
            raise OccupancyError(f"threads must be >= 1, got {threads}")
        #: threads marking a scan's rays (None: one per core, os.cpu_count(); a Dask worker passes
        #: its allotment); the map does not depend on it
        self.threads = resolve_threads(threads)
        self.params = params
        self.voxel_size_m = float(p.voxel_size_m)
        self._hit = np.float32(_logit(p.prob_hit))
        self._miss = np.float32(_logit(p.prob_miss))
        self._lo_min = np.float32(_logit(p.clamp_min))
        self._lo_max = np.float32(_logit(p.clamp_max))
        self._thres = np.float32(_logit(p.occupancy_threshold))
        cap = 1 << max(4, int(np.ceil(np.log2(max(1, initial_blocks)))))
        self._logodds = np.full((cap, _BLOCK_CELLS), np.nan, dtype=np.float32)
        self._fbits = np.zeros((cap, _BLOCK_CELLS // 64), dtype=np.uint64)
        self._hbits = np.zeros((cap, _BLOCK_CELLS // 64), dtype=np.uint64)
        self._bstamp = np.full(cap, -1, dtype=np.int32)
        self._touched = np.zeros(cap, dtype=np.int64)
        self._ntouched = np.zeros(1, dtype=np.int64)
        self._bkeys = np.full(cap, -1, dtype=np.int64)
        self._hkeys = np.full(2 * cap, -1, dtype=np.int64)
        self._hvals = np.full(2 * cap, -1, dtype=np.int64)
        self._nused = np.zeros(1, dtype=np.int64)
        self.num_scans = 0

    # -- state ---------------------------------------------------------------------------------
    def _grow(self) -> None:
        n = self._logodds.shape[0]
        self._logodds = np.concatenate(
            [self._logodds, np.full((n, _BLOCK_CELLS), np.nan, dtype=np.float32)]
        )
        self._fbits = np.concatenate(
            [self._fbits, np.zeros((n, _BLOCK_CELLS // 64), dtype=np.uint64)]
        )
        self._hbits = np.concatenate(
            [self._hbits, np.zeros((n, _BLOCK_CELLS // 64), dtype=np.uint64)]
        )
        self._bstamp = np.concatenate([self._bstamp, np.full(n, -1, dtype=np.int32)])
        self._touched = np.concatenate([self._touched, np.zeros(n, dtype=np.int64)])
        self._bkeys = np.concatenate([self._bkeys, np.full(n, -1, dtype=np.int64)])
        # Keep the hash table at most half full.
        self._hkeys = np.full(4 * n, -1, dtype=np.int64)
        self._hvals = np.full(4 * n, -1, dtype=np.int64)
        _rehash(self._bkeys, int(self._nused[0]), self._hkeys, self._hvals)

    @property
    def memory_bytes(self) -> int:
        """Bytes held by the block pool and its hash table (allocated capacity)."""
        arrays = (
            self._logodds,
            self._fbits,
            self._hbits,
            self._bstamp,
            self._touched,
            self._bkeys,
            self._hkeys,
            self._hvals,
        )
        return sum(a.nbytes for a in arrays)

    def insert_scan(
        self,
        points_world: np.ndarray,
        origin_world: np.ndarray,
        *,
        max_range_m: float,
        discretize: bool,
        region: tuple[int, int, int, int] | None = None,
    ) -> None:
        """Insert one scan (OctoMap ``insertPointCloud``).

        points_world: (N, 3) float, metres, world frame: the scan's endpoints (human-free points
        for the static map). origin_world: (3,) float, the sensor origin in the world frame.
        max_range_m: < 0 for no limit. discretize: OctoMap's ``discretize`` (one ray per distinct
        endpoint voxel, aimed at its centre).

        region: (kx0, kx1, ky0, ky1) voxel keys, multiples of 8 (whole blocks): only voxels with
        kx0 <= kx < kx1 and ky0 <= ky < ky1 (any z) are updated, each exactly as the whole scan
        would update it; rays that cannot reach the region are not walked. Maps of disjoint
        regions fed the same scans in the same order are the pieces of the map of the whole
        plane (the map stage builds its tiles this way, in parallel).
        """
        pts = np.asarray(points_world)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise OccupancyError(f"points_world must be (N, 3), got shape {pts.shape}")
        origin = np.asarray(origin_world, dtype=np.float64).reshape(-1)
        if origin.shape != (3,) or not np.all(np.isfinite(origin)):
            raise OccupancyError(f"origin_world must be 3 finite values, got {origin_world}")
        # OctoMap holds points as float32; do the same so rays start and end where its do.
        pts = pts.astype(np.float32).astype(np.float64)
        origin = origin.astype(np.float32).astype(np.float64)
        finite = np.all(np.isfinite(pts), axis=1)
        if not finite.all():
            pts = pts[finite]
        if discretize and len(pts):
            keys = np.floor(pts * (1.0 / self.voxel_size_m)).astype(np.int64) + _KEY_OFFSET
            packed = np.unique((keys[:, 0] << 42) | (keys[:, 1] << 21) | keys[:, 2])
            keys = np.stack([packed >> 42, (packed >> 21) & _KEY_MASK, packed & _KEY_MASK], axis=1)
            pts = (keys - _KEY_OFFSET + 0.5) * self.voxel_size_m
        rb = _EVERYWHERE
        if region is not None:
            rb = _region_blocks(region)
            pts = pts[_rays_reaching(pts, origin, self.voxel_size_m, region)]
        pts = np.ascontiguousarray(pts)
        if not (len(pts) and self._insert_dense(pts, origin, float(max_range_m), rb)):
            self._insert_sparse(pts, origin, float(max_range_m), rb)
        self.num_scans += 1

    def _insert_sparse(
        self, pts: np.ndarray, origin: np.ndarray, max_range_m: float, rb: np.ndarray = _EVERYWHERE
    ) -> None:
        """One thread, marks straight in the map's block pool (any extent)."""
        scan_id = np.int32(self.num_scans % (2**31 - 1))
        phase, ray = 0, 0
        while True:
            phase, ray = _mark_scan(
                pts,
                origin,
                max_range_m,
                self.voxel_size_m,
                scan_id,
                self._hkeys,
                self._hvals,
                self._bkeys,
                self._nused,
                self._bstamp,
                self._touched,
                self._ntouched,
                self._fbits,
                self._hbits,
                phase,
                ray,
                False,
                _NO_BOX,
                _NO_BOX,
                rb,
            )
            if phase == 2:
                break
            self._grow()
        _apply_marks(
            self._touched,
            self._ntouched,
            self._fbits,
            self._hbits,
            self._logodds,
            self._hit,
            self._miss,
            self._lo_min,
            self._lo_max,
        )

    def _insert_dense(
        self, pts: np.ndarray, origin: np.ndarray, max_range_m: float, rb: np.ndarray = _EVERYWHERE
    ) -> bool:
        """Rays split over threads, each marking a private dense box of blocks around the scan
        (cut to the region rb); the union is then applied once. False (nothing changed) when the
        box would be too big."""
        b0, nb = _scan_box(pts, origin, max_range_m, self.voxel_size_m)
        for a in range(2):  # x / y: only the region's blocks
            lo, hi = max(b0[a], rb[2 * a]), min(b0[a] + nb[a], rb[2 * a + 1])
            b0[a], nb[a] = lo, max(0, hi - lo)
        threads = max(1, min(self.threads, len(pts) // _MIN_RAYS_PER_THREAD))
        if int(np.prod(nb)) * threads > _DENSE_MAX_BLOCKS:
            return False
        words = _BLOCK_CELLS // 64
        fbits = np.zeros((threads, int(np.prod(nb)), words), dtype=np.uint64)
        hbits = np.zeros_like(fbits)
        bounds = np.linspace(0, len(pts), threads * _CHUNKS_PER_THREAD + 1).astype(np.int64)
        chunks = list(zip(bounds[:-1], bounds[1:]))
        scan_id = np.int32(0)

        def mark(t: int) -> bool:
            for lo, hi in chunks[t::threads]:
                phase, _ = _mark_scan(
                    pts[lo:hi],
                    origin,
                    max_range_m,
                    self.voxel_size_m,
                    scan_id,
                    self._hkeys,
                    self._hvals,
                    self._bkeys,
                    self._nused,
                    self._bstamp,
                    self._touched,
                    self._ntouched,
                    fbits[t],
                    hbits[t],
                    0,
                    0,
                    True,
                    b0,
                    nb,
                    rb,
                )
                if phase != 2:
                    return False
            return True

        if threads == 1:
            inside = mark(0)
        else:
            inside = all(executor(threads).map(mark, range(threads)))
        if not inside:  # a ray left the box (float corner cases): the sparse path is exact anyway
            return False
        row = 0
        while True:
            row = _apply_dense(
                fbits,
                hbits,
                b0,
                nb,
                row,
                self._hkeys,
                self._hvals,
                self._bkeys,
                self._nused,
                self._logodds,
                self._hit,
                self._miss,
                self._lo_min,
                self._lo_max,
            )
            if row < 0:
                return True
            self._grow()

    # -- queries -------------------------------------------------------------------------------
    def query(self, points_world: np.ndarray) -> np.ndarray:
        """State at points: (N, 3) float metres, world frame -> (N,) int8, -1 unknown / 0 free /
        1 occupied (octomap-python's ``getLabels``)."""
        # float32 like OctoMap's point3d, so a point on a voxel face lands where OctoMap puts it.
        pts = np.ascontiguousarray(
            np.asarray(points_world).reshape(-1, 3).astype(np.float32).astype(np.float64)
        )
        out = np.empty(len(pts), dtype=np.int8)
        _query_points(
            pts, self.voxel_size_m, self._hkeys, self._hvals, self._logodds, self._thres, out
        )
        return out

    def query_grid(self, spec, T_world_from_grid: np.ndarray) -> np.ndarray:
        """State at the centres of every voxel of a grid.

        spec: :class:`tasks.occupancy.grid.GridSpec` in its own frame (e.g. base).
        T_world_from_grid: (4, 4) float64. Returns (X, Y, Z) int8, -1 unknown / 0 free /
        1 occupied; centres are computed on the fly (no dense float temporaries).
        """
        T = np.asarray(T_world_from_grid, dtype=np.float64)
        if T.shape != (4, 4):
            raise OccupancyError(f"T_world_from_grid must be (4, 4), got {T.shape}")
        nx, ny, nz = spec.shape
        out = np.empty((nx, ny, nz), dtype=np.int8)
        _query_grid(
            np.ascontiguousarray(T[:3, :3]),
            np.ascontiguousarray(T[:3, 3]),
            spec.origin,
            spec.voxel_size_m,
            nx,
            ny,
            nz,
            self.voxel_size_m,
            self._hkeys,
            self._hvals,
            self._logodds,
            self._thres,
            out,
        )
        return out

    # -- persistence (storage/ writes these arrays) ----------------------------------------------
    def to_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """Known voxels: keys (K, 3) int64 (voxel = [k, k+1) * voxel_size_m, world frame) and
        their log-odds (K,) float32."""
        return _export(self._bkeys, self._logodds, int(self._nused[0]))

    @classmethod
    def from_arrays(
        cls,
        params: FreeSpaceParams,
        keys: np.ndarray,
        logodds: np.ndarray,
        threads: int | None = None,
    ) -> OccupancyMap:
        """Rebuild a map from :meth:`to_arrays` output (scan count restarts at 0)."""
        keys = np.ascontiguousarray(np.asarray(keys, dtype=np.int64).reshape(-1, 3))
        vals = np.ascontiguousarray(np.asarray(logodds, dtype=np.float32).reshape(-1))
        if len(keys) != len(vals):
            raise OccupancyError(f"{len(keys)} keys but {len(vals)} log-odds values")
        # a guess of the block count (exports hold ~100-500 voxels per block); the pool grows
        m = cls(params, initial_blocks=max(1, len(keys) // 128), threads=threads)
        row = 0
        while row >= 0:
            row = _import(keys, vals, row, m._hkeys, m._hvals, m._bkeys, m._logodds, m._nused)
            if row >= 0:
                m._grow()
        return m

    def __getstate__(self):
        keys, vals = self.to_arrays()
        return {
            "params": self.params,
            "keys": keys,
            "logodds": vals,
            "num_scans": self.num_scans,
            "threads": self.threads,
        }

    def __setstate__(self, state):
        other = OccupancyMap.from_arrays(
            state["params"], state["keys"], state["logodds"], threads=state.get("threads")
        )
        self.__dict__.update(other.__dict__)
        self.num_scans = state["num_scans"]
