"""Per-frame fusion into the robot-local grid (paper, "3D Occupancy Representation").

Priority: pedestrian voxels (body-mesh volume + surface, per-instance ids) over static voxels (the
majority label of the static-map points in the voxel) over the rest, which is free in
``semantics``; the OctoMap state at each voxel centre (-1 unknown / 0 free / 1 occupied) comes
along in ``occupancy_state``. Visibility: ``mask_lidar`` (voxels crossed or hit by this frame's
LiDAR rays) and ``mask_camera`` (voxels seen from cam0 up to the first occupied voxel of a ray).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from tasks.conventions import FREE, PEDESTRIAN
from tasks.occupancy.grid import GridSpec
from tasks.occupancy.settings import FuseSettings
from tasks.occupancy.visibility import camera_mask, lidar_mask


class FuseError(ValueError):
    """Bad input to the per-frame fusion."""


@dataclass(frozen=True)
class PedestrianMesh:
    """One person in one frame: a closed body mesh in the base frame.

    instance_id: 1..65535 (0 means "no instance"). vertices_base: (V, 3) float metres, base frame.
    faces: (F, 3) int vertex indices. velocity_base: (2,) float m/s (vx, vy), base frame.
    """

    instance_id: int
    vertices_base: np.ndarray
    faces: np.ndarray
    velocity_base: np.ndarray = field(default_factory=lambda: np.zeros(2))


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


def voxelize_mesh(spec: GridSpec, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Voxels of a closed mesh: the volume (open3d occupancy at voxel centres) plus the surface
    (lattice points at half-voxel spacing). vertices (V, 3) float metres and faces (F, 3) int in
    the grid frame. Returns (M, 3) int64 unique in-bounds voxel indices."""
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if not len(v):
        return np.empty((0, 3), dtype=np.int64)
    surf = spec.index_of(surface_points(v, f, 0.5 * spec.voxel_size_m))
    surf = surf[spec.in_bounds(surf)]
    lo = np.maximum(spec.index_of(v.min(axis=0, keepdims=True))[0], 0)
    hi = np.minimum(spec.index_of(v.max(axis=0, keepdims=True))[0], np.asarray(spec.shape) - 1)
    vol = np.empty((0, 3), dtype=np.int64)
    if len(f) and np.all(hi >= lo):
        axes = [np.arange(lo[a], hi[a] + 1) for a in range(3)]
        idx = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)),
                            o3d.core.Tensor(f.astype(np.uint32)))
        occ = scene.compute_occupancy(o3d.core.Tensor(spec.center_of(idx).astype(np.float32))).numpy()
        vol = idx[occ > 0.5]
    return np.unique(np.concatenate([surf, vol]), axis=0)


def voxelize_labels(spec: GridSpec, points: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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
    pixel_stride: int | None = None,
    camera_method: str = FuseSettings.camera_method,
    velocity_dtype=np.float16,
) -> FrameGrids:
    """Fuse one frame into the robot-local grid.

    spec: the local grid (base frame). T_world_from_base: (4, 4) float64 pose of this frame.
    static_points_world: (N, 3) float32 metres, world frame, with static_labels (N,) uint8: the
    static map near the robot (e.g.
    ``StaticMap.crop_to_grid(spec, T_world_from_base).sample_points(spec.voxel_size_m)``).
    pedestrians: body meshes of this frame (later ones win where they overlap).
    occupancy: a :class:`tasks.occupancy.freespace.OccupancyMap` (world frame) or None.
    lidar_points_base (M, 3) / lidar_origin_base (3,): this frame's LiDAR endpoints and centre in
    the base frame (None: mask_lidar all 0). camera: the view for mask_camera (None: all 0);
    camera_method / pixel_stride: see :func:`tasks.occupancy.visibility.camera_mask`; "auto":
    "rays" for voxels >= 0.1 m (exact DDA, cheap), "zbuffer" for finer grids (98.8 % agreement
    with "rays" at 0.05 m, 3.5x faster; rays would take seconds per frame at 0.02 m).
    velocity_dtype: float16 (default, 221 MB at 0.02 m on the benchmark extent) or float32.
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
    sp_base = sp @ T_base_from_world[:3, :3].T.astype(np.float32) + T_base_from_world[:3, 3].astype(np.float32)
    flat, lab = voxelize_labels(spec, sp_base, static_labels)
    semantics[flat] = lab
    # pedestrians over static
    instances = np.zeros(n, dtype=np.uint16)
    velocity = np.zeros((n, 2), dtype=velocity_dtype)
    for ped in pedestrians:
        if not 1 <= int(ped.instance_id) <= 65535:
            raise FuseError(f"instance_id must be in 1..65535, got {ped.instance_id}")
        idx = voxelize_mesh(spec, ped.vertices_base, ped.faces)
        if not len(idx):
            continue
        f = spec.flat_index(idx)
        semantics[f] = PEDESTRIAN
        instances[f] = ped.instance_id
        velocity[f] = np.asarray(ped.velocity_base, dtype=np.float64).reshape(2)
    semantics = semantics.reshape(spec.shape)
    instances = instances.reshape(spec.shape)
    velocity = velocity.reshape(*spec.shape, 2)
    state = (occupancy.query_grid(spec, T) if occupancy is not None
             else np.full(spec.shape, -1, dtype=np.int8))
    if lidar_points_base is not None:
        if lidar_origin_base is None:
            raise FuseError("lidar_points_base needs lidar_origin_base")
        m_lidar = lidar_mask(spec, lidar_points_base, lidar_origin_base)
    else:
        m_lidar = np.zeros(spec.shape, dtype=np.uint8)
    if camera is not None:
        method = camera_method
        if method == "auto":
            method = "rays" if spec.voxel_size_m >= 0.1 else "zbuffer"
        m_cam = camera_mask(spec, semantics != FREE, camera.K, camera.width, camera.height,
                            camera.T_base_from_cam, pixel_stride, method)
    else:
        m_cam = np.zeros(spec.shape, dtype=np.uint8)
    return FrameGrids(semantics, instances, m_lidar, m_cam, velocity, state)
