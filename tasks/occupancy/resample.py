"""The static map (world frame) resampled into a robot-local grid."""

from __future__ import annotations

import numpy as np

from tasks.conventions import UNLABELED, transform_points
from tasks.occupancy.grid import GridSpec
from tasks.occupancy.static_map import StaticMap, lookup_labels


def static_in_grid(smap: StaticMap, spec: GridSpec, T_world_from_base: np.ndarray,
                   reach_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The static map as labelled points (world frame) that land one per cell of the local grid.

    A map as coarse as the grid or coarser is resampled by the grid's cell centres (every cell
    takes the label of the map voxel under its centre: no holes where the grids are offset); a
    finer map is pushed as points filling each map voxel within ``reach_m`` (xy) of the robot.
    Returns points (N, 3) float32 world frame and labels (N,) uint8.
    """
    if smap.voxel_size_m < spec.voxel_size_m - 1e-9:
        return smap.crop(T_world_from_base[:3, 3], reach_m).sample_points(spec.voxel_size_m)
    pts, labels = [], []
    axes = [spec.range_min[a] + (np.arange(n) + 0.5) * spec.voxel_size_m for a, n in enumerate(spec.shape)]
    gy, gz = np.meshgrid(axes[1], axes[2], indexing="ij")
    for x in axes[0]:  # one x slab of cell centres at a time bounds memory at fine resolutions
        slab = np.stack([np.full(gy.size, x), gy.ravel(), gz.ravel()], axis=1)
        world = transform_points(T_world_from_base, slab).astype(np.float32)
        lab = lookup_labels(smap, world)
        hit = lab != UNLABELED
        pts.append(world[hit])
        labels.append(lab[hit])
    return np.concatenate(pts), np.concatenate(labels)


def grid_reach_m(spec: GridSpec) -> float:
    """Horizontal distance from the grid's origin to its farthest corner, plus 1 m."""
    corners = np.abs(np.array([spec.range_min, spec.range_max], np.float64)).max(axis=0)
    return float(np.linalg.norm(corners[:2])) + 1.0
