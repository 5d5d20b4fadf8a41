"""Exact ground truth of a synthetic frame: semantic occupancy, keypoints, visibility.

Occupancy rule (the voxel convention of storage/SCHEMA.md and storage/GT_FORMAT.md): a voxel is
occupied when a surface passes through it or a solid meets its interior; a surface lying on a
voxel face belongs to the voxel on its solid's side. This is computed as the union of (a) voxels
holding a surface sample (every triangle sampled with gaps below a quarter voxel, voxel index
``floor((p - range_min) / voxel_size)``, each sample moved ``CLOSED_TOL_M`` to the solid's side
first, so a face lying on a voxel face counts only for the voxel behind it) and (b) voxels whose
centre lies inside a solid. The ground is the top of the earth: its solid side is below it, so the
flat ground at z = 0 (a voxel face of the benchmark grid) occupies the layer just below it, not the
one above. Label precedence: pedestrians, then the other solids (most samples wins, interiors count
as full), then the ground surfaces (most samples wins).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tasks import conventions as C
from tasks.sim.geometry import sample_triangles

CLOSED_TOL_M = 1e-4
_INTERIOR_WEIGHT = 1 << 20


@dataclass(frozen=True)
class GridSpec:
    """A voxel grid in the base frame: range_min (3,) m, voxel_size_m, shape (3,) [x, y, z]."""

    range_min: tuple[float, float, float] = (0.4, -4.8, -1.0)
    voxel_size_m: float = 0.2
    shape: tuple[int, int, int] = (48, 48, 24)

    @property
    def range_max(self) -> np.ndarray:
        return np.asarray(self.range_min) + self.voxel_size_m * np.asarray(self.shape)

    def centres(self) -> np.ndarray:
        """(X*Y*Z, 3) float64 voxel centres in the base frame, C order over [x, y, z]."""
        axes = [
            self.range_min[a] + self.voxel_size_m * (np.arange(self.shape[a]) + 0.5)
            for a in range(3)
        ]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def _flat_indices(
    points_base: np.ndarray, grid: GridSpec, closed: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) base points -> flat voxel indices (M,) int64 of every voxel whose cube holds a
    point, with the sample index (M,) of each. closed: a point within CLOSED_TOL_M of a face also
    counts for the neighbour (else the half-open floor rule)."""
    q = (points_base - np.asarray(grid.range_min)) / grid.voxel_size_m
    idx = np.floor(q).astype(np.int64)
    src = np.arange(len(q))
    tol = CLOSED_TOL_M / grid.voxel_size_m
    for axis in range(3 if closed else 0):
        frac = q[:, axis] - idx[:, axis]
        lo = frac < tol
        hi = frac > 1 - tol
        extra_lo = idx[lo].copy()
        extra_lo[:, axis] -= 1
        extra_hi = idx[hi].copy()
        extra_hi[:, axis] += 1
        q_lo, q_hi = q[lo], q[hi]
        idx = np.concatenate([idx, extra_lo, extra_hi])
        src = np.concatenate([src, src[lo], src[hi]])
        q = np.concatenate([q, q_lo, q_hi])
    shape = np.asarray(grid.shape)
    inside = np.all((idx >= 0) & (idx < shape), axis=1)
    idx, src = idx[inside], src[inside]
    return np.ravel_multi_index(idx.T, grid.shape), src


@dataclass(frozen=True)
class OccupancyInput:
    """Geometry of one frame in the base frame.

    static_tris: list of (vertices (V, 3) float64, faces (F, 3) int, class_id, is_ground) of the
    static things near the grid; static_planes: list of (planes (P, 4) float64, class_id, lo (3,),
    hi (3,) bounding box) convex solids for the centre-inside test; people: list of
    (vertices (V, 3), track_id); person_faces (F, 3) shared by all people; people_inside: (X*Y*Z,) int32 track id whose body contains the voxel
    centre (0 none), from the caller's mesh-inside test.
    """

    static_tris: list
    static_planes: list
    people: list
    person_faces: np.ndarray
    people_inside: np.ndarray


def occupancy_grid(inp: OccupancyInput, grid: GridSpec) -> tuple[np.ndarray, np.ndarray]:
    """Semantic occupancy (X, Y, Z) uint8 (class ids, 10 free) and pedestrian instance grid
    (X, Y, Z) uint16 (track id, 0 none), base frame, see the module doc for the rule."""
    n_vox = int(np.prod(grid.shape))
    spacing = grid.voxel_size_m / 4
    counts_obj = np.zeros((n_vox, C.NUM_CLASSES), dtype=np.int64)
    counts_ground = np.zeros((n_vox, C.NUM_CLASSES), dtype=np.int64)
    for verts, faces, cls, is_ground in inp.static_tris:
        pts = sample_triangles(verts, faces, spacing)
        # Move samples a hair to the solid's side, so a face lying on a voxel face only occupies
        # the voxel behind it: into the (convex) solid, or below the ground (its tiles face up,
        # the earth lies under them).
        if is_ground:
            towards = np.broadcast_to([0.0, 0.0, -1.0], pts.shape)
        else:
            towards = verts.mean(axis=0) - pts
        pts = pts + CLOSED_TOL_M * towards / np.maximum(
            np.linalg.norm(towards, axis=1, keepdims=True), 1e-12
        )
        flat, _ = _flat_indices(pts, grid)
        target = counts_ground if is_ground else counts_obj
        target[:, cls] += np.bincount(flat, minlength=n_vox)
    centres = grid.centres().reshape(*grid.shape, 3)
    flat_ids = np.arange(n_vox).reshape(grid.shape)
    for planes, cls, lo, hi in inp.static_planes:
        # Only the centres inside the solid's bounding box can be inside it.
        i0 = np.clip(np.floor((lo - grid.range_min) / grid.voxel_size_m).astype(int), 0, grid.shape)
        i1 = np.clip(np.ceil((hi - grid.range_min) / grid.voxel_size_m).astype(int), 0, grid.shape)
        if np.any(i1 <= i0):
            continue
        box = (slice(i0[0], i1[0]), slice(i0[1], i1[1]), slice(i0[2], i1[2]))
        c = centres[box].reshape(-1, 3)
        inside = np.all(c @ planes[:, :3].T + planes[:, 3] <= 0.0, axis=1)
        counts_obj[flat_ids[box].reshape(-1)[inside], cls] += _INTERIOR_WEIGHT
    sem = np.full(n_vox, C.FREE, dtype=np.uint8)
    has_ground = counts_ground.sum(1) > 0
    sem[has_ground] = np.argmax(counts_ground[has_ground], axis=1)
    has_obj = counts_obj.sum(1) > 0
    sem[has_obj] = np.argmax(counts_obj[has_obj], axis=1)
    # Pedestrians take precedence; between people, most samples wins (interior = full).
    inst = np.zeros(n_vox, dtype=np.uint16)
    if inp.people:
        ids = np.array([tid for _, tid in inp.people], dtype=np.int64)
        pcount = np.zeros((n_vox, len(ids)), dtype=np.int64)
        for k, (verts, _) in enumerate(inp.people):
            pts = np.concatenate([verts, sample_triangles(verts, inp.person_faces, spacing)])
            flat, _ = _flat_indices(pts, grid, closed=False)
            pcount[:, k] += np.bincount(flat, minlength=n_vox)
        for k, tid in enumerate(ids):
            pcount[inp.people_inside == tid, k] += _INTERIOR_WEIGHT
        any_p = pcount.sum(1) > 0
        sem[any_p] = C.PEDESTRIAN
        inst[any_p] = ids[np.argmax(pcount[any_p], axis=1)]
    return sem.reshape(grid.shape), inst.reshape(grid.shape)


def project(points_cam: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) camera-frame points -> pixels (N, 2) float64 (u, v) and depth (N,) (z, m)."""
    z = points_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (points_cam[:, :2] / z[:, None]) * K[[0, 1], [0, 1]] + K[:2, 2]
    return uv, z


def keypoint_visibility(
    uv: np.ndarray,
    depth: np.ndarray,
    track_id: int,
    depth_image: np.ndarray,
    instance_image: np.ndarray,
    occluder_margin_m: float = 0.3,
) -> np.ndarray:
    """COCO visibility flags (N,) uint8 of keypoints at pixels uv (N, 2) with camera depth (N,):
    0 outside the image (or behind the camera), 2 visible (the pixel shows this person, or nothing
    nearer than depth - occluder_margin_m), 1 occluded."""
    H, W = depth_image.shape
    px = np.rint(uv).astype(np.int64) if len(uv) else np.zeros((0, 2), np.int64)
    inside = (depth > 0.05) & (px[:, 0] >= 0) & (px[:, 0] < W) & (px[:, 1] >= 0) & (px[:, 1] < H)
    flags = np.zeros(len(uv), dtype=np.uint8)
    u, v = px[inside, 0], px[inside, 1]
    own = instance_image[v, u] == track_id
    clear = depth_image[v, u] >= depth[inside] - occluder_margin_m
    flags[inside] = np.where(own | clear, 2, 1)
    return flags


def occlusion_level(visible_fraction: float, in_view: bool) -> str:
    """CODa ``isOccluded`` attribute from the visible-pixel fraction in cam0."""
    if not in_view:
        return "Unknown"
    if visible_fraction >= 0.9:
        return "None"
    if visible_fraction >= 0.6:
        return "Light"
    if visible_fraction >= 0.3:
        return "Medium"
    if visible_fraction > 0.0:
        return "Heavy"
    return "Full"
