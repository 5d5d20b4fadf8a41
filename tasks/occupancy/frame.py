"""One frame of the fuse stage: the static map around the robot, the people, the masks."""

from __future__ import annotations

import numpy as np

from tasks.conventions import FREE, NUM_CLASSES
from tasks.geometry import transform_points
from tasks.occupancy.fuse import CameraView, PedestrianMesh, fuse_frame
from tasks.occupancy.grid import GridSpec
from tasks.occupancy.resample import grid_reach_m, static_in_grid
from tasks.occupancy.settings import FuseSettings
from tasks.occupancy.static_map import StaticMap


def relative_pose(T_a_from_b: np.ndarray, T_c_from_b: np.ndarray) -> np.ndarray:
    """``T_a_from_c = T_a_from_b @ inv(T_c_from_b)``: frame c in frame a, from frame b's pose in
    each (e.g. T_world_from_base from T_world_from_lidar and T_base_from_lidar). (..., 4, 4)
    float64 (a stack of poses against one, or one against one)."""
    return T_a_from_b @ np.linalg.inv(T_c_from_b)


def local_grids(
    spec: GridSpec,
    T_world_from_base: np.ndarray,
    static: StaticMap,
    occupancy,
    people: list[PedestrianMesh],
    points_lidar: np.ndarray,
    T_base_from_lidar: np.ndarray,
    camera: CameraView | None,
    fusion: FuseSettings,
    threads: int | None = None,
    return_labels: np.ndarray | None = None,
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The dataset's grids of one frame (arrays of storage/SCHEMA.md) and its class counts.

    mask_lidar is the union of this frame's LiDAR rays (traversed or hit voxels), the voxels
    the sequence's occupancy map has observed (known free or occupied) and the occupied voxels
    (a label is LiDAR evidence: static voxels come from returns, a body from its fit to the
    person's returns, and it fills the voxels behind the visible surface too), so "unknown" means
    never observed and semantics is free wherever mask_lidar is 0; mask_camera is cam0's visibility restricted to mask_lidar (Occ3D: camera-visible =
    seen by the camera and observed by the LiDAR, so no voxel is called free without LiDAR
    evidence). class_counts (NUM_CLASSES,) int64: voxels per class among those with mask_lidar = 1.
    No return of this frame is left free (:func:`tasks.occupancy.fuse.occupy_returns`; return_labels
    (N,) uint8 per point of points_lidar: the class an orphan return's voxel takes, None:
    UNCLASSIFIED).
    points_lidar: (N, 3) float32 this frame's sweep, LiDAR frame; the rest as
    :func:`tasks.occupancy.fuse.fuse_frame` (threads: for its rays; the grids do not depend on it).
    """
    static_pts, static_labels = static_in_grid(static, spec, T_world_from_base, grid_reach_m(spec))
    grids = fuse_frame(
        spec,
        T_world_from_base,
        static_points_world=static_pts,
        static_labels=static_labels,
        pedestrians=people,
        occupancy=occupancy,
        lidar_points_base=transform_points(T_base_from_lidar, points_lidar),
        lidar_origin_base=T_base_from_lidar[:3, 3],
        camera=camera,
        fusion=fusion,
        threads=threads,
        return_labels=return_labels,
    )
    mask_lidar = (
        grids.mask_lidar.astype(bool) | (grids.occupancy_state >= 0) | (grids.semantics != FREE)
    )
    counts = np.bincount(grids.semantics[mask_lidar], minlength=NUM_CLASSES).astype(np.int64)
    return {
        "semantics": grids.semantics,
        "instances": grids.instances,
        "mask_lidar": mask_lidar.astype(np.uint8),
        "mask_camera": grids.mask_camera & mask_lidar,
        "velocity": grids.velocity.astype(np.float16),
    }, counts
