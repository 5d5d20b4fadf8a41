"""Per-frame fusion into the robot-local grid (paper, "3D Occupancy Representation").

Priority: pedestrian voxels (body-mesh volume + surface, per-instance ids) over static voxels (the
majority label of the static-map points in the voxel) over the rest, which is free in
``semantics``; then no return of this frame is left free (:func:`occupy_returns`: a return with
nothing occupied at or next to its voxel occupies its voxel, UNCLASSIFIED or the class given); the OctoMap state at each voxel centre (-1 unknown / 0 free / 1 occupied) comes
along in ``occupancy_state``. Visibility: ``mask_lidar`` (voxels crossed or hit by this frame's
LiDAR rays) and ``mask_camera`` (voxels seen from cam0 up to the first occupied voxel of a ray).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from tasks.conventions import FREE, PEDESTRIAN, UNCLASSIFIED
from tasks.occupancy.grid import GridSpec
from tasks.occupancy.settings import FuseSettings
from tasks.occupancy.visibility import camera_mask, lidar_mask


class FuseError(ValueError):
    """Bad input to the per-frame fusion."""


@dataclass(frozen=True)
class PedestrianMesh:
    """One person in one frame: a closed body mesh in the base frame.

    instance_id: 1..65535 (0 means "no instance"). vertices_base: (V, 3) float metres, base frame.
    faces: (F, 3) int vertex indices. velocity_base: (2,) float m/s (vx, vy), base frame: the
    person's velocity, every voxel's unless vertex_velocity_base (V, 2) float m/s (vx, vy per
    vertex, base axes) is given; then each voxel takes the mean velocity of the body surface in it
    (:func:`mesh_voxel_velocity`).
    """

    instance_id: int
    vertices_base: np.ndarray
    faces: np.ndarray
    velocity_base: np.ndarray = field(default_factory=lambda: np.zeros(2))
    vertex_velocity_base: np.ndarray | None = None


@dataclass(frozen=True)
class CameraView:
    """The camera of mask_camera: K (3, 3) pixels, image width / height, T_base_from_cam (4, 4)."""

    K: np.ndarray
    width: int
    height: int
    T_base_from_cam: np.ndarray


@dataclass(frozen=True)
class FrameGrids:
    """One frame's robot-local grids, all (X, Y, Z) in [x, y, z] order, base frame.

    semantics: uint8 class ids (FREE where nothing is occupied). instances: uint16 (0 none).
    mask_lidar, mask_camera: uint8 (1 observed). velocity: (X, Y, Z, 2) float16/32 m/s (vx, vy)
    in the base frame, non-zero only at pedestrian voxels. occupancy_state: int8 OctoMap state at
    each voxel centre (-1 unknown / 0 free / 1 occupied), all -1 without an occupancy map.
    """

    semantics: np.ndarray
    instances: np.ndarray
    mask_lidar: np.ndarray
    mask_camera: np.ndarray
    velocity: np.ndarray
    occupancy_state: np.ndarray


def surface_points(vertices: np.ndarray, faces: np.ndarray, spacing_m: float) -> np.ndarray:
    """Points on every triangle at most spacing_m apart (a barycentric lattice per triangle,
    deterministic). vertices (V, 3) float metres, faces (F, 3) int. Returns (P, 3) float64."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if not len(f):
        return v.copy()
    tri = v[f]  # (F, 3, 3)
    edge = np.max(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2), axis=1)
    k = np.clip(np.ceil(edge / spacing_m).astype(np.int64), 1, 256)
    out = [v]
    for kk in np.unique(k):
        i, j = np.meshgrid(np.arange(kk + 1), np.arange(kk + 1), indexing="ij")
        m = (i + j) <= kk
        w = np.stack([i[m], j[m], kk - i[m] - j[m]], axis=1) / kk  # (P, 3) barycentric
        out.append(np.einsum("pk,tkd->tpd", w, tri[k == kk]).reshape(-1, 3))
    return np.concatenate(out)


@njit(cache=True, inline="always")
def _floor_index(x, origin, vs):
    return np.int64(math.floor((x - origin) / vs))


@njit(cache=True)
def _mark_surface(v, f, origin, vs, shape, g0, occ, vel, sums, counts):
    """Mark the voxels of :func:`surface_points` (spacing vs / 2) in occ, a local grid whose
    voxel (0, 0, 0) is grid voxel g0; points outside the grid are skipped. Same lattice and the
    same float64 arithmetic as surface_points (weights i / k, j / k, (k - i - j) / k, summed in
    that order), without materialising the points. With vel (V, D), D > 0, every point also adds
    its velocity (a vertex's own; a triangle point's vertex velocities blended with its weights)
    to sums (occ's shape + (D,)) and 1 to counts (occ's shape); with D = 0 they are not touched."""
    spacing = 0.5 * vs
    nd = vel.shape[1]
    for n in range(v.shape[0]):
        lx, ly, lz, ok = _local_index(v[n, 0], v[n, 1], v[n, 2], origin, vs, shape, g0, occ)
        if ok:
            occ[lx, ly, lz] = 1
            if nd:
                counts[lx, ly, lz] += 1
                for d in range(nd):
                    sums[lx, ly, lz, d] += vel[n, d]
    for t in range(f.shape[0]):
        a, b, c = f[t, 0], f[t, 1], f[t, 2]
        edge = 0.0
        for p, q in ((a, c), (b, a), (c, b)):  # tri - roll(tri, 1): a - c, b - a, c - b
            dx = v[p, 0] - v[q, 0]
            dy = v[p, 1] - v[q, 1]
            dz = v[p, 2] - v[q, 2]
            edge = max(edge, math.sqrt(dx * dx + dy * dy + dz * dz))
        k = min(max(np.int64(math.ceil(edge / spacing)), 1), 256)
        for i in range(k + 1):
            for j in range(k + 1 - i):
                wa = i / k
                wb = j / k
                wc = (k - i - j) / k
                lx, ly, lz, ok = _local_index(
                    (wa * v[a, 0] + wb * v[b, 0]) + wc * v[c, 0],
                    (wa * v[a, 1] + wb * v[b, 1]) + wc * v[c, 1],
                    (wa * v[a, 2] + wb * v[b, 2]) + wc * v[c, 2],
                    origin,
                    vs,
                    shape,
                    g0,
                    occ,
                )
                if ok:
                    occ[lx, ly, lz] = 1
                    if nd:
                        counts[lx, ly, lz] += 1
                        for d in range(nd):
                            sums[lx, ly, lz, d] += (wa * vel[a, d] + wb * vel[b, d]) + wc * vel[
                                c, d
                            ]


@njit(cache=True, inline="always")
def _local_index(x, y, z, origin, vs, shape, g0, occ):
    """(lx, ly, lz, True): the local-grid voxel of a point inside the grid and the local grid,
    else (0, 0, 0, False)."""
    ix = _floor_index(x, origin[0], vs)
    iy = _floor_index(y, origin[1], vs)
    iz = _floor_index(z, origin[2], vs)
    if 0 <= ix < shape[0] and 0 <= iy < shape[1] and 0 <= iz < shape[2]:
        lx, ly, lz = ix - g0[0], iy - g0[1], iz - g0[2]
        if 0 <= lx < occ.shape[0] and 0 <= ly < occ.shape[1] and 0 <= lz < occ.shape[2]:
            return lx, ly, lz, True
    return np.int64(0), np.int64(0), np.int64(0), False


@njit(cache=True, inline="always")
def _edge(v, i, j, x, y):
    """Side of (x, y) w.r.t. the xy line through vertices i, j, oriented from the lower vertex
    index to the higher: the same float operations for both faces that share the edge."""
    if i > j:
        i, j = j, i
    return (v[j, 0] - v[i, 0]) * (y - v[i, 1]) - (v[j, 1] - v[i, 1]) * (x - v[i, 0])


@njit(cache=True, inline="always")
def _covers(v, i, j, r, x, y):
    """(x, y) on the side of edge (i, j) where the face's third vertex r lies; a point exactly on
    the edge belongs to the face on the edge's positive side, so of two faces that meet there
    from opposite sides exactly one counts it (crossings stay consistent along a shared edge)."""
    e = _edge(v, i, j, x, y)
    s = _edge(v, i, j, v[r, 0], v[r, 1])
    return (e > 0.0 and s > 0.0) or (e < 0.0 and s < 0.0) or (e == 0.0 and s > 0.0)


@njit(cache=True)
def _column_crossings(v, f, cx, cy, vs, counts, zs, fill):
    """Heights where the faces cross the vertical line through each column centre (cx[i], cy[j]),
    column i * len(cy) + j. With fill False, counts (columns + 1,) gets each column's crossings
    at [column + 1]; with fill True, counts (columns,) is each column's next free slot in zs."""
    nx, ny = cx.shape[0], cy.shape[0]
    for t in range(f.shape[0]):
        a, b, c = f[t, 0], f[t, 1], f[t, 2]
        nz = (v[b, 0] - v[a, 0]) * (v[c, 1] - v[a, 1]) - (v[b, 1] - v[a, 1]) * (v[c, 0] - v[a, 0])
        if nz == 0.0:  # a vertical face: the lines graze it, its neighbours count
            continue
        xmin = min(v[a, 0], min(v[b, 0], v[c, 0]))
        xmax = max(v[a, 0], max(v[b, 0], v[c, 0]))
        ymin = min(v[a, 1], min(v[b, 1], v[c, 1]))
        ymax = max(v[a, 1], max(v[b, 1], v[c, 1]))
        nxv = (v[b, 1] - v[a, 1]) * (v[c, 2] - v[a, 2]) - (v[b, 2] - v[a, 2]) * (v[c, 1] - v[a, 1])
        nyv = (v[b, 2] - v[a, 2]) * (v[c, 0] - v[a, 0]) - (v[b, 0] - v[a, 0]) * (v[c, 2] - v[a, 2])
        # candidate columns (one column of slack: the exact tests below decide)
        i0 = max(0, np.int64(math.floor((xmin - cx[0]) / vs)))
        i1 = min(nx - 1, np.int64(math.ceil((xmax - cx[0]) / vs)))
        j0 = max(0, np.int64(math.floor((ymin - cy[0]) / vs)))
        j1 = min(ny - 1, np.int64(math.ceil((ymax - cy[0]) / vs)))
        for i in range(i0, i1 + 1):
            x = cx[i]
            if x < xmin or x > xmax:
                continue
            for j in range(j0, j1 + 1):
                y = cy[j]
                if y < ymin or y > ymax:
                    continue
                if not (
                    _covers(v, a, b, c, x, y)
                    and _covers(v, b, c, a, x, y)
                    and _covers(v, c, a, b, x, y)
                ):
                    continue
                col = i * ny + j
                if fill:  # the face's plane at (x, y): n . (p - a) = 0
                    zs[counts[col]] = v[a, 2] - (nxv * (x - v[a, 0]) + nyv * (y - v[a, 1])) / nz
                    counts[col] += 1
                else:
                    counts[col + 1] += 1


@njit(cache=True)
def _fill_inside(starts, zs, cz, nx, ny, g, occ):
    """Mark the voxel centres with an odd number of crossings above them (inside a closed
    surface); g: the local-grid offset of the volume box."""
    for i in range(nx):
        for j in range(ny):
            s, e = starts[i * ny + j], starts[i * ny + j + 1]
            if e - s < 2:
                continue
            col = np.sort(zs[s:e])
            for k in range(cz.shape[0]):
                above = e - s - np.searchsorted(col, cz[k], side="right")
                if above % 2 == 1:
                    occ[g[0] + i, g[1] + j, g[2] + k] = 1


def voxelize_mesh(spec: GridSpec, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Voxels of a closed mesh: the volume (voxels whose centre is inside the mesh) plus the
    surface (voxels holding a point of :func:`surface_points` at half-voxel spacing).

    vertices (V, 3) float metres and faces (F, 3) int in the grid frame; the mesh must be closed
    (watertight) for the volume to mean inside. Returns (M, 3) int64 unique in-bounds voxel
    indices, rows in lexicographic order.

    Inside: the parity of the faces crossed by the vertical line above the centre (for a closed
    surface the parity of any ray's crossings, so this equals a ray cast in any direction, e.g.
    open3d's ``RaycastingScene.compute_occupancy``). The faces are taken at float32 precision,
    like open3d's. A centre on a shared edge's vertical plane is counted by exactly one of the
    two faces (fixed orientation of each edge); a centre exactly on the surface is undecided.
    Cost: one pass over the faces plus one over the mesh's box of voxels (no dense sampling).
    """
    return _voxelize(spec, vertices, faces)[0]


def mesh_voxel_velocity(
    spec: GridSpec,
    vertices: np.ndarray,
    faces: np.ndarray,
    vertex_velocity: np.ndarray,
    voxels: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The velocity of the voxels of a moving closed mesh (a body whose vertices move apart).

    Each voxel takes the mean velocity of the body surface inside it: the points of
    :func:`surface_points` at half-voxel spacing (the lattice that makes a voxel a surface voxel
    in :func:`voxelize_mesh`), each carrying its triangle's vertex velocities blended with its
    barycentric weights. The lattice is uniform over the surface, so the mean weighs the surface
    by area; a mean over the vertices alone would lean to where a body model's vertices crowd
    (face, hands) and leave voxels the surface crosses between vertices without a value. A voxel
    no surface point falls in (inside the body, or a requested voxel the lattice misses) takes
    the velocity of the vertex nearest its centre (the mesh defines no motion inside itself).

    vertices (V, 3) float metres, grid frame; faces (F, 3) int; vertex_velocity (V, D) float (D
    components, e.g. (vx, vy) m/s). voxels: (M, 3) int voxel indices to give velocities for (None:
    the mesh's own, those of :func:`voxelize_mesh`, computed in the same pass). Returns (voxels
    (M, 3) int64, velocity (M, D) float64).
    """
    vel = np.asarray(vertex_velocity, dtype=np.float64)
    if vel.ndim != 2 or len(vel) != len(np.asarray(vertices).reshape(-1, 3)):
        raise FuseError(
            f"vertex_velocity must be (V, D) with V = {len(np.asarray(vertices).reshape(-1, 3))} "
            f"vertices, got {vel.shape}"
        )
    own, g0, sums, counts = _voxelize(spec, vertices, faces, vel)
    idx = own if voxels is None else np.asarray(voxels, dtype=np.int64).reshape(-1, 3)
    out = np.zeros((len(idx), vel.shape[1]), dtype=np.float64)
    if not len(idx):
        return idx, out
    local = idx - g0
    has = np.all((local >= 0) & (local < np.asarray(counts.shape)), axis=1)
    n = np.zeros(len(idx), dtype=np.int64)
    n[has] = counts[tuple(local[has].T)]
    hit = n > 0
    out[hit] = sums[tuple(local[hit].T)] / n[hit, None]
    if not hit.all():
        from scipy.spatial import cKDTree

        v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
        _, nearest = cKDTree(v).query(spec.center_of(idx[~hit]))
        out[~hit] = vel[nearest]
    return idx, out


def _voxelize(
    spec: GridSpec,
    vertices: np.ndarray,
    faces: np.ndarray,
    vertex_velocity: np.ndarray | None = None,
):
    """:func:`voxelize_mesh`'s voxels, and with vertex_velocity (V, D) the surface points'
    velocity sums (local grid + (D,)) and counts (local grid) whose voxel (0, 0, 0) is grid voxel
    g0: (voxels (M, 3) int64, g0 (3,), sums, counts)."""
    v = np.ascontiguousarray(np.asarray(vertices, dtype=np.float64).reshape(-1, 3))
    f = np.ascontiguousarray(np.asarray(faces, dtype=np.int64).reshape(-1, 3))
    vel = (
        np.zeros((len(v), 0))
        if vertex_velocity is None
        else np.ascontiguousarray(np.asarray(vertex_velocity, dtype=np.float64))
    )
    nothing = (
        np.empty((0, 3), dtype=np.int64),
        np.zeros(3, np.int64),
        np.zeros((0, 0, 0, vel.shape[1])),
        np.zeros((0, 0, 0), np.int64),
    )
    if not len(v):
        return nothing
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        raise FuseError(f"faces index vertices 0..{len(v) - 1}, got {f.min()}..{f.max()}")
    shape = np.asarray(spec.shape, dtype=np.int64)
    vmin, vmax = (
        spec.index_of(v.min(axis=0, keepdims=True))[0],
        spec.index_of(v.max(axis=0, keepdims=True))[0],
    )
    # the local grid: the mesh box one voxel wider (rounding of lattice points), inside the grid
    g0 = np.maximum(vmin - 1, 0)
    g1 = np.minimum(vmax + 1, shape - 1)
    if np.any(g1 < g0):
        return nothing
    occ = np.zeros(tuple(g1 - g0 + 1), dtype=np.uint8)
    tracked = vel.shape[1] > 0  # velocity sums over the local grid, else 1-voxel placeholders
    sums = np.zeros((*(occ.shape if tracked else (1, 1, 1)), vel.shape[1]))
    samples = np.zeros(occ.shape if tracked else (1, 1, 1), dtype=np.int64)
    _mark_surface(v, f, spec.origin, spec.voxel_size_m, shape, g0, occ, vel, sums, samples)
    lo, hi = np.maximum(vmin, 0), np.minimum(vmax, shape - 1)
    if len(f) and np.all(hi >= lo):
        v32 = v.astype(np.float32).astype(np.float64)  # open3d's float32 mesh and centres
        cx, cy, cz = (
            (spec.origin[a] + (np.arange(lo[a], hi[a] + 1) + 0.5) * spec.voxel_size_m)
            .astype(np.float32)
            .astype(np.float64)
            for a in range(3)
        )
        counts = np.zeros(len(cx) * len(cy) + 1, dtype=np.int64)
        _column_crossings(v32, f, cx, cy, spec.voxel_size_m, counts, np.empty(0), False)
        starts = np.cumsum(counts)
        zs = np.empty(starts[-1], dtype=np.float64)
        _column_crossings(v32, f, cx, cy, spec.voxel_size_m, starts[:-1].copy(), zs, True)
        _fill_inside(starts, zs, cz, len(cx), len(cy), lo - g0, occ)
    return np.argwhere(occ) + g0, g0, sums, samples


def voxelize_labels(
    spec: GridSpec, points: np.ndarray, labels: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Majority label per voxel (ties: the lower class id).

    points: (N, 3) float metres, grid frame; labels: (N,) uint8 (UNLABELED ignored).
    Returns (flat (M,) int64 C-order voxel indices, label (M,) uint8).
    """
    p = np.asarray(points).reshape(-1, 3)
    lab = np.asarray(labels, dtype=np.uint8).reshape(-1)
    idx = spec.index_of(p)
    ok = spec.in_bounds(idx) & (lab < FREE)
    if not ok.any():
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.uint8)
    flat = spec.flat_index(idx[ok])
    code, count = np.unique(flat * 16 + lab[ok], return_counts=True)
    vflat, vlab = code // 16, (code % 16).astype(np.uint8)
    order = np.lexsort((vlab, -count, vflat))
    vflat, vlab = vflat[order], vlab[order]
    first = np.concatenate([[True], vflat[1:] != vflat[:-1]])
    return vflat[first], vlab[first]


#: the 27 offsets of a voxel and its 26 neighbours
_NEIGHBOURHOOD = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), axis=-1).reshape(
    -1, 3
)


def orphan_returns(occupied: np.ndarray, return_voxels: np.ndarray) -> np.ndarray:
    """(N,) bool: True for the returns whose voxel and its 26 neighbours hold nothing occupied.

    occupied: (X, Y, Z) bool. return_voxels: (N, 3) int64 voxel indices of returns (rows outside
    the grid are never orphans)."""
    occ = np.asarray(occupied, dtype=bool)
    idx = np.asarray(return_voxels, dtype=np.int64).reshape(-1, 3)
    shape = np.asarray(occ.shape, dtype=np.int64)
    inside = np.all((idx >= 0) & (idx < shape), axis=1)
    near = np.zeros(len(idx), dtype=bool)
    padded = np.pad(occ, 1)  # the neighbours of a border voxel outside the grid are not occupied
    for off in _NEIGHBOURHOOD:
        q = idx[inside] + off + 1
        near[inside] |= padded[q[:, 0], q[:, 1], q[:, 2]]
    return inside & ~near


def occupy_returns(
    semantics: np.ndarray, return_voxels: np.ndarray, return_labels: np.ndarray | None = None
) -> np.ndarray:
    """Returns are never free: the voxel of every return of :func:`orphan_returns` (nothing
    occupied at or next to it) takes its label, so each cluster of return voxels has an occupied
    voxel among their 26 neighbours (the voxel convention of storage/SCHEMA.md lets a rule move a
    return's voxel by one, no further).

    semantics: (X, Y, Z) uint8 class ids (FREE where free), not changed. return_voxels: (N, 3)
    int64 voxel indices of this frame's returns. return_labels: (N,) uint8 the class an orphan
    return's voxel takes (None: UNCLASSIFIED; PEDESTRIAN for a confirmed person's returns with no
    fitted body near them). Returns (semantics (X, Y, Z) uint8, a new array)."""
    sem = np.array(semantics, dtype=np.uint8, copy=True)
    idx = np.asarray(return_voxels, dtype=np.int64).reshape(-1, 3)
    lab = (
        np.full(len(idx), UNCLASSIFIED, np.uint8)
        if return_labels is None
        else np.asarray(return_labels, dtype=np.uint8).reshape(-1)
    )
    if len(lab) != len(idx):
        raise FuseError(f"{len(idx)} returns but {len(lab)} return labels")
    if len(lab) and lab.max() >= FREE:
        raise FuseError(f"return label {int(lab.max())} is not an occupied class (0..{FREE - 1})")
    orphan = orphan_returns(sem < FREE, idx)
    if orphan.any():
        # one label per voxel, whatever the order of the points: the lowest class id among the
        # voxel's orphan returns (PEDESTRIAN before UNCLASSIFIED)
        flat = np.ravel_multi_index(tuple(idx[orphan].T), sem.shape)
        out = sem.reshape(-1)
        best = np.full(len(out), FREE, np.uint8)
        np.minimum.at(best, flat, lab[orphan])
        cells = np.unique(flat)
        out[cells] = best[cells]
    return sem


def returns_without_class(
    semantics: np.ndarray, instances: np.ndarray, return_voxels: np.ndarray
) -> tuple[int, int]:
    """(unclassified, pedestrian with no instance): how many distinct voxels of some returns
    (return_voxels (N, 3) int64; rows outside the grid left out) hold UNCLASSIFIED, and
    PEDESTRIAN with instance id 0 (a person's returns no fitted body covers). semantics (X, Y, Z)
    uint8, instances (X, Y, Z) uint16."""
    idx = np.asarray(return_voxels, dtype=np.int64).reshape(-1, 3)
    inside = np.all((idx >= 0) & (idx < np.asarray(semantics.shape)), axis=1)
    vox = np.unique(idx[inside], axis=0).reshape(-1, 3)
    sem, inst = semantics[tuple(vox.T)], instances[tuple(vox.T)]
    return int(np.count_nonzero(sem == UNCLASSIFIED)), int(
        np.count_nonzero((sem == PEDESTRIAN) & (inst == 0))
    )


def fuse_frame(
    spec: GridSpec,
    T_world_from_base: np.ndarray,
    *,
    static_points_world: np.ndarray,
    static_labels: np.ndarray,
    pedestrians: list[PedestrianMesh] = (),
    occupancy=None,
    lidar_points_base: np.ndarray | None = None,
    lidar_origin_base: np.ndarray | None = None,
    camera: CameraView | None = None,
    fusion: FuseSettings = FuseSettings(),
    velocity_dtype=np.float16,
    threads: int | None = None,
    return_labels: np.ndarray | None = None,
) -> FrameGrids:
    """Fuse one frame into the robot-local grid.

    spec: the local grid (base frame). T_world_from_base: (4, 4) float64 pose of this frame.
    static_points_world: (N, 3) float32 metres, world frame, with static_labels (N,) uint8: the
    static map near the robot (e.g.
    ``StaticMap.crop_to_grid(spec, T_world_from_base).sample_points(spec.voxel_size_m)``).
    pedestrians: body meshes of this frame (later ones win where they overlap); a voxel's velocity
    is its person's, or with per-vertex velocities the mean over the body surface in the voxel.
    occupancy: a :class:`tasks.occupancy.freespace.OccupancyMap` (world frame) or None.
    lidar_points_base (M, 3) / lidar_origin_base (3,): this frame's LiDAR endpoints and centre in
    the base frame (None: mask_lidar all 0). camera: the view for mask_camera (None: all 0);
    fusion: its ``camera_method`` and ``camera_pixel_stride`` (see
    :func:`tasks.occupancy.visibility.camera_mask`; "auto": "rays" for voxels >= 0.1 m (exact
    DDA, cheap), "zbuffer" for finer grids (98.8 % agreement with "rays" at 0.05 m, 3.5x faster;
    rays would take seconds per frame at 0.02 m)).
    velocity_dtype: float16 (default, 221 MB at 0.02 m on the benchmark extent) or float32.
    threads: for the visibility rays (None: one thread per core; the grids do not depend on it).
    return_labels: (M,) uint8 per LiDAR point, the class its voxel takes when nothing occupied is
    at or next to it (:func:`occupy_returns`; None: UNCLASSIFIED).
    """
    T = np.asarray(T_world_from_base, dtype=np.float64)
    if T.shape != (4, 4):
        raise FuseError(f"T_world_from_base must be (4, 4), got {T.shape}")
    n = spec.num_voxels
    semantics = np.full(n, FREE, dtype=np.uint8)
    # static voxels: world -> base, majority label per voxel
    sp = np.asarray(static_points_world, dtype=np.float32).reshape(-1, 3)
    if len(sp) != len(np.asarray(static_labels).reshape(-1)):
        raise FuseError(f"{len(sp)} static points but {len(static_labels)} labels")
    T_base_from_world = np.linalg.inv(T)
    sp_base = sp @ T_base_from_world[:3, :3].T.astype(np.float32) + T_base_from_world[:3, 3].astype(
        np.float32
    )
    flat, lab = voxelize_labels(spec, sp_base, static_labels)
    semantics[flat] = lab
    # pedestrians over static
    instances = np.zeros(n, dtype=np.uint16)
    velocity = np.zeros((n, 2), dtype=velocity_dtype)
    for ped in pedestrians:
        if not 1 <= int(ped.instance_id) <= 65535:
            raise FuseError(f"instance_id must be in 1..65535, got {ped.instance_id}")
        if ped.vertex_velocity_base is None:
            idx = voxelize_mesh(spec, ped.vertices_base, ped.faces)
            vel = np.asarray(ped.velocity_base, dtype=np.float64).reshape(2)
        else:
            idx, vel = mesh_voxel_velocity(
                spec,
                ped.vertices_base,
                ped.faces,
                np.asarray(ped.vertex_velocity_base).reshape(-1, 2),
            )
        if not len(idx):
            continue
        f = spec.flat_index(idx)
        semantics[f] = PEDESTRIAN
        instances[f] = ped.instance_id
        velocity[f] = vel
    semantics = semantics.reshape(spec.shape)
    if lidar_points_base is not None:
        pts = np.asarray(lidar_points_base, dtype=np.float64).reshape(-1, 3)
        finite = np.all(np.isfinite(pts), axis=1)
        semantics = occupy_returns(
            semantics,
            spec.index_of(pts[finite]),
            None if return_labels is None else np.asarray(return_labels).reshape(-1)[finite],
        )
    instances = instances.reshape(spec.shape)
    velocity = velocity.reshape(*spec.shape, 2)
    state = (
        occupancy.query_grid(spec, T)
        if occupancy is not None
        else np.full(spec.shape, -1, dtype=np.int8)
    )
    if lidar_points_base is not None:
        if lidar_origin_base is None:
            raise FuseError("lidar_points_base needs lidar_origin_base")
        m_lidar = lidar_mask(spec, lidar_points_base, lidar_origin_base, threads)
    else:
        m_lidar = np.zeros(spec.shape, dtype=np.uint8)
    if camera is not None:
        method = fusion.camera_method
        if method == "auto":
            method = "rays" if spec.voxel_size_m >= 0.1 else "zbuffer"
        m_cam = camera_mask(
            spec,
            semantics != FREE,
            camera.K,
            camera.width,
            camera.height,
            camera.T_base_from_cam,
            fusion.camera_pixel_stride,
            method,
            threads,
        )
    else:
        m_cam = np.zeros(spec.shape, dtype=np.uint8)
    return FrameGrids(semantics, instances, m_lidar, m_cam, velocity, state)
