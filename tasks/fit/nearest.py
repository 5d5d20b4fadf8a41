"""Exact nearest neighbours between small point sets on the CPU (numba): a uniform grid per set.

The body fit pairs each person's ~3,000 visible vertices with its ~100-5,000 LiDAR points both
ways every few steps. For sets this small a k-d tree spends most of its time descending; a
uniform grid over the data set (counting sort by cell) and a search over growing shells of
cells around the query's cell is several times faster. The search is exact: after the shells
up to Chebyshev radius r are scanned, every other data point is at least r x cell from the query
(the query lies in, or beyond the grid behind, its clamped cell), so it stops once the best
distance found is within that bound; a query with nothing found within ``_MAX_SHELL`` shells
scans every data point. Ties go to the lowest index scanned first (any of the equidistant points
is a nearest one).
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: grid cells per axis at most (the cell grows for a wide set)
_MAX_CELLS_PER_AXIS = 16
#: smallest cell edge (m): measured fastest on Ouster-128 persons (4-8 cm between vertices and
#: their nearest returns)
_MIN_CELL_M = 0.08
#: shells searched before a full scan of the set
_MAX_SHELL = 3


@njit(cache=True, nogil=True)
def _build_grid(data):
    """Grid of data (m, 3) float64: origin (3,), cell edge, dims (3,), cell start (C + 1,), order (m,)."""
    lo = np.empty(3)
    hi = np.empty(3)
    for a in range(3):
        lo[a] = data[:, a].min()
        hi[a] = data[:, a].max()
    cell = max(_MIN_CELL_M, (hi - lo).max() / _MAX_CELLS_PER_AXIS * (1.0 + 1e-9))
    dims = np.empty(3, np.int64)
    for a in range(3):
        dims[a] = min(int((hi[a] - lo[a]) / cell) + 1, _MAX_CELLS_PER_AXIS)
    m = data.shape[0]
    cid = np.empty(m, np.int64)
    for i in range(m):
        c = 0
        for a in range(3):
            k = min(max(int((data[i, a] - lo[a]) / cell), 0), dims[a] - 1)
            c = c * dims[a] + k
        cid[i] = c
    n_cells = dims[0] * dims[1] * dims[2]
    start = np.zeros(n_cells + 1, np.int64)
    for i in range(m):
        start[cid[i] + 1] += 1
    for c in range(n_cells):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(m, np.int64)
    for i in range(m):
        order[fill[cid[i]]] = i
        fill[cid[i]] += 1
    return lo, cell, dims, start, order


@njit(cache=True, nogil=True)
def _scan_cell(q, data, start, order, c, best, best_i):
    for s in range(start[c], start[c + 1]):
        i = order[s]
        d = (data[i, 0] - q[0]) ** 2 + (data[i, 1] - q[1]) ** 2 + (data[i, 2] - q[2]) ** 2
        if d < best or (d == best and i < best_i):
            best, best_i = d, i
    return best, best_i


@njit(cache=True, nogil=True, inline="always")
def _box_d2(q, lo, cell, x, y, z):
    """Squared distance from q to grid cell (x, y, z) (0 inside)."""
    d = 0.0
    for a, i in ((0, x), (1, y), (2, z)):
        b0 = lo[a] + i * cell
        if q[a] < b0:
            d += (b0 - q[a]) ** 2
        elif q[a] > b0 + cell:
            d += (q[a] - b0 - cell) ** 2
    return d


@njit(cache=True, nogil=True)
def _nearest_one(q, data, lo, cell, dims, start, order, max_d2=np.inf):
    """Index of the point of data nearest to q (3,) (exact), and its squared distance; with a
    finite max_d2 the search may stop once nothing within it can be found (then the returned
    point, if any, is farther than sqrt(max_d2) or the index is -1)."""
    c0 = np.empty(3, np.int64)
    for a in range(3):
        c0[a] = min(max(int(np.floor((q[a] - lo[a]) / cell)), 0), dims[a] - 1)
    best, best_i = np.inf, -1
    for r in range(_MAX_SHELL + 1):
        for dx in range(-r, r + 1):
            x = c0[0] + dx
            if x < 0 or x >= dims[0]:
                continue
            for dy in range(-r, r + 1):
                y = c0[1] + dy
                if y < 0 or y >= dims[1]:
                    continue
                edge = abs(dx) == r or abs(dy) == r
                dz = -r
                while dz <= r:
                    z = c0[2] + dz
                    if 0 <= z < dims[2] and _box_d2(q, lo, cell, x, y, z) <= best:
                        best, best_i = _scan_cell(
                            q, data, start, order, (x * dims[1] + y) * dims[2] + z, best, best_i
                        )
                    dz = dz + 1 if edge or r == 0 else dz + 2 * r
        if best_i >= 0 and best <= (r * cell) ** 2:
            return best_i, best
        if r >= dims.max() or (r * cell) ** 2 >= max_d2:  # every cell scanned / nothing closer
            return best_i, best
    for i in range(data.shape[0]):  # far from every data point: scan them all
        d = (data[i, 0] - q[0]) ** 2 + (data[i, 1] - q[1]) ** 2 + (data[i, 2] - q[2]) ** 2
        if d < best or (d == best and i < best_i):
            best, best_i = d, i
    return best_i, best


@njit(cache=True, nogil=True)
def nearest_indices(queries, data):
    """For each row of queries (n, 3) float64, the index of its nearest row of data (m >= 1, 3)."""
    lo, cell, dims, start, order = _build_grid(data)
    out = np.empty(queries.shape[0], np.int64)
    for i in range(queries.shape[0]):
        out[i], _ = _nearest_one(queries[i], data, lo, cell, dims, start, order)
    return out


@njit(cache=True, nogil=True)
def chamfer_pairs(vertices, vertex_mask, points, bounds):
    """Nearest pairs both ways for K persons, reduced to per-vertex sums (see
    ``tasks.fit.losses.ChamferTargets``).

    vertices (K, N, 3) float64, vertex_mask (K, N) bool, points (P, 3) float64 grouped by person,
    person k's rows bounds[k]:bounds[k + 1]. Returns target (K, N, 3) (nearest point of each
    masked vertex), count (K, N), mean (K, N, 3), rest (K,) (float64; zero where unused). A
    person without a masked vertex or without points gets zeros.
    """
    K, N = vertex_mask.shape
    target = np.zeros((K, N, 3))
    count = np.zeros((K, N))
    mean = np.zeros((K, N, 3))
    rest = np.zeros(K)
    for k in range(K):
        pk = points[bounds[k] : bounds[k + 1]]
        ids = np.flatnonzero(vertex_mask[k])
        if len(ids) == 0 or pk.shape[0] == 0:
            continue
        vk = vertices[k][ids]
        j = nearest_indices(vk, pk)
        for a in range(len(ids)):
            target[k, ids[a]] = pk[j[a]]
        j = nearest_indices(pk, vk)
        for s in range(pk.shape[0]):
            n = ids[j[s]]
            count[k, n] += 1.0
            for c in range(3):
                mean[k, n, c] += pk[s, c]
        for a in range(len(ids)):
            n = ids[a]
            if count[k, n] > 0:
                for c in range(3):
                    mean[k, n, c] /= count[k, n]
        for s in range(pk.shape[0]):
            n = ids[j[s]]
            rest[k] += (
                (pk[s, 0] - mean[k, n, 0]) ** 2
                + (pk[s, 1] - mean[k, n, 1]) ** 2
                + (pk[s, 2] - mean[k, n, 2]) ** 2
            )
    return target, count, mean, rest


@njit(cache=True, nogil=True)
def pairs_within(queries, query_mask, points, bounds, max_m):
    """For K persons: the nearest point of each masked query within max_m (metres).

    queries (K, N, 3) float64, query_mask (K, N) bool, points (P, 3) float64 grouped by person
    (rows bounds[k]:bounds[k + 1]). Returns index (K, N) int64 into points (-1: none within
    max_m, or not masked) and squared distance (K, N) float64 (inf where none)."""
    return pairs_within_ranges(queries, query_mask, points, bounds[:-1], bounds[1:], max_m)


@njit(cache=True, nogil=True)
def pairs_within_ranges(queries, query_mask, points, starts, ends, max_m):
    """:func:`pairs_within` with person k's points at rows starts[k]:ends[k] of points (any
    subset of persons of one grouped array, e.g. those an ICP still moves); a person with no
    masked query is skipped (no grid built)."""
    K, N = query_mask.shape
    index = np.full((K, N), -1, np.int64)
    d2 = np.full((K, N), np.inf)
    lim = max_m * max_m
    for k in range(K):
        if ends[k] == starts[k] or not query_mask[k].any():
            continue
        pk = points[starts[k] : ends[k]]
        lo, cell, dims, start, order = _build_grid(pk)
        for n in range(N):
            if query_mask[k, n]:
                i, d = _nearest_one(queries[k, n], pk, lo, cell, dims, start, order, lim)
                if i >= 0 and d <= lim:
                    index[k, n] = starts[k] + i
                    d2[k, n] = d
    return index, d2
