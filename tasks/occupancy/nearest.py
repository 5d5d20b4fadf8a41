"""Exact nearest neighbours in 3D for per-sweep label transfer.

A k-d tree (median splits on the widest axis, tight node boxes, ``leaf_size`` points per leaf)
searched depth first, nearer child first, starting from the answer of the previous query as the
bound. LiDAR queries come in scan order, so consecutive queries have nearby answers and that
bound prunes almost every node at once; this matters most for queries far from every source
(points behind the robot labelled from the camera's view ~25 m away), where a best-first search
from an infinite bound visits hundreds of leaves (scipy's cKDTree: ~0.3 s for 56k such queries
against 9k sources, this search ~12 ms, same answers).

Result: for each query the index of the nearest source (Euclidean distance in float64); among
sources at exactly the same distance, the lowest index. The answer does not depend on the query
order or the thread count.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from tasks.occupancy.threads import executor, resolve_threads

#: Points per leaf: 16-32 measured fastest on LiDAR sweeps (8: more nodes, 64: more distances).
LEAF_SIZE = 32
_STACK = 256  # pending nodes of one search: at most one per tree level plus one


@njit(cache=True, inline="always")
def _select(points, perm, lo, hi, k, dim):
    """Reorder perm[lo..hi] so that perm[k] holds the point of rank k - lo along dim, those
    before it are not greater and those after it not smaller (Hoare's quickselect)."""
    while lo < hi:
        pivot = points[perm[(lo + hi) // 2], dim]
        i, j = lo, hi
        while i <= j:
            while points[perm[i], dim] < pivot:
                i += 1
            while points[perm[j], dim] > pivot:
                j -= 1
            if i <= j:
                perm[i], perm[j] = perm[j], perm[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            return


@njit(cache=True)
def _build(points, leaf_size):
    """Tree over points (N, 3) float64: (perm, start, end, left, right, bmin, bmax); leaves hold
    perm[start:end]; left < 0 marks a leaf; bmin / bmax are the tight boxes of each node."""
    n = points.shape[0]
    perm = np.arange(n)
    cap = 4 * (n // max(1, leaf_size) + 1) + 1
    start = np.empty(cap, np.int64)
    end = np.empty(cap, np.int64)
    left = np.full(cap, -1, np.int64)
    right = np.full(cap, -1, np.int64)
    bmin = np.empty((cap, 3))
    bmax = np.empty((cap, 3))
    stack = np.empty(_STACK, np.int64)
    start[0], end[0] = 0, n
    used, sp = 1, 1
    stack[0] = 0
    while sp > 0:
        sp -= 1
        node = stack[sp]
        s, e = start[node], end[node]
        for a in range(3):
            lo, hi = np.inf, -np.inf
            for i in range(s, e):
                v = points[perm[i], a]
                lo = min(lo, v)
                hi = max(hi, v)
            bmin[node, a], bmax[node, a] = lo, hi
        if e - s <= leaf_size:
            continue
        dim = 0
        for a in range(1, 3):
            if bmax[node, a] - bmin[node, a] > bmax[node, dim] - bmin[node, dim]:
                dim = a
        mid = s + (e - s) // 2
        _select(points, perm, s, e - 1, mid, dim)
        lc, rc = used, used + 1
        used += 2
        start[lc], end[lc], start[rc], end[rc] = s, mid, mid, e
        left[node], right[node] = lc, rc
        stack[sp], stack[sp + 1] = lc, rc
        sp += 2
    return perm, start[:used], end[:used], left[:used], right[:used], bmin[:used], bmax[:used]


@njit(cache=True, inline="always")
def _box_d2(bmin, bmax, node, qx, qy, qz):
    d = 0.0
    for a, q in ((0, qx), (1, qy), (2, qz)):
        v = bmin[node, a] - q
        if v > 0.0:
            d += v * v
        else:
            v = q - bmax[node, a]
            if v > 0.0:
                d += v * v
    return d


@njit(cache=True, nogil=True)
def _query(points, perm, start, end, left, right, bmin, bmax, queries, out):
    """out[i] = nearest source of queries[i] (lowest index on ties)."""
    stack = np.empty(_STACK, np.int64)
    bound = np.empty(_STACK)
    prev = perm[0]
    for i in range(queries.shape[0]):
        qx, qy, qz = queries[i, 0], queries[i, 1], queries[i, 2]
        dx, dy, dz = points[prev, 0] - qx, points[prev, 1] - qy, points[prev, 2] - qz
        best = dx * dx + dy * dy + dz * dz  # the previous answer: a bound that is a real source
        arg = prev
        stack[0], bound[0], sp = 0, 0.0, 1
        while sp > 0:
            sp -= 1
            node = stack[sp]
            if bound[sp] > best:  # '>' keeps boxes at exactly the best distance: ties are seen
                continue
            lc = left[node]
            if lc < 0:
                for k in range(start[node], end[node]):
                    j = perm[k]
                    dx, dy, dz = points[j, 0] - qx, points[j, 1] - qy, points[j, 2] - qz
                    d = dx * dx + dy * dy + dz * dz
                    if d < best or (d == best and j < arg):
                        best, arg = d, j
                continue
            rc = right[node]
            dl = _box_d2(bmin, bmax, lc, qx, qy, qz)
            dr = _box_d2(bmin, bmax, rc, qx, qy, qz)
            near, far, dn, df = (lc, rc, dl, dr) if dl <= dr else (rc, lc, dr, dl)
            if df <= best:  # pushed first, popped after the nearer child
                stack[sp], bound[sp], sp = far, df, sp + 1
            if dn <= best:
                stack[sp], bound[sp], sp = near, dn, sp + 1
        out[i] = arg
        prev = arg


def nearest_indices(
    sources: np.ndarray, queries: np.ndarray, threads: int | None = None, leaf_size: int = LEAF_SIZE
) -> np.ndarray:
    """Index of the nearest source of every query.

    sources: (N, 3) float, N >= 1; queries: (M, 3) float, same frame and unit (finite).
    threads: query chunks searched in parallel (None: one per core). Returns (M,) int64 in [0, N);
    on exact distance ties the lowest source index.
    """
    src = np.ascontiguousarray(np.asarray(sources, dtype=np.float64).reshape(-1, 3))
    qry = np.ascontiguousarray(np.asarray(queries, dtype=np.float64).reshape(-1, 3))
    if len(src) == 0:
        raise ValueError("nearest_indices needs at least one source point")
    out = np.empty(len(qry), dtype=np.int64)
    if len(qry) == 0:
        return out
    tree = _build(src, int(leaf_size))
    n = min(resolve_threads(threads), max(1, len(qry) // 4096))
    if n == 1:
        _query(src, *tree, qry, out)
        return out
    bounds = np.linspace(0, len(qry), n + 1).astype(np.int64)
    list(
        executor(n).map(
            lambda k: _query(
                src, *tree, qry[bounds[k] : bounds[k + 1]], out[bounds[k] : bounds[k + 1]]
            ),
            range(n),
        )
    )
    return out
