"""The sequence's static map resampled into a frame's robot-local grid.

A map that knows where its surfaces lie (``StaticMap.surface``, the map stage's) is pushed as
points on those surfaces (:func:`tasks.occupancy.surface.surface_samples`): each grid cell that a
surface passes through gets it, wherever the grid lies against the map's voxels (a robot that moves
half a voxel between frames, as at 10 Hz, cuts every map voxel in two, and the surface lies in one
half). A voxel without its own plane stands as its centroid; one coarser than the grid fills the
cells it covers.

A map without surfaces as coarse as the grid or coarser is pulled by the grid's cell centres:
every cell takes the label of the map voxel under its centre (nearest-voxel resampling, no holes
where the two grids are offset, see :func:`tasks.occupancy.static_map.lookup_labels`). A finer one
is pushed as points filling each map voxel (the fusion then votes per cell).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from tasks.conventions import UNLABELED
from tasks.occupancy.grid import GridSpec
from tasks.occupancy.static_map import StaticMap, lookup_packed, sorted_table
from tasks.occupancy.surface import surface_samples


@njit(cache=True, inline="always")
def _centre_world(R, t, origin, vs, i, j, k):
    """World position (float32, as the fused points are) of the centre of grid cell (i, j, k)."""
    x = origin[0] + (i + 0.5) * vs
    y = origin[1] + (j + 0.5) * vs
    z = origin[2] + (k + 0.5) * vs
    return (
        np.float32(R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + t[0]),
        np.float32(R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + t[1]),
        np.float32(R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + t[2]),
    )


@njit(cache=True)
def _pull_labels(R, t, origin, vs, shape, map_vs, table, labels, out):
    """out[i, j, k] = label of the map voxel holding the centre of cell (i, j, k), UNLABELED
    where the map (a :func:`sorted_table`) has none."""
    for i in range(shape[0]):
        for j in range(shape[1]):
            for k in range(shape[2]):
                wx, wy, wz = _centre_world(R, t, origin, vs, i, j, k)
                out[i, j, k] = lookup_packed(
                    table,
                    labels,
                    np.int64(np.floor(np.float64(wx) / map_vs)),
                    np.int64(np.floor(np.float64(wy) / map_vs)),
                    np.int64(np.floor(np.float64(wz) / map_vs)),
                )


@njit(cache=True)
def _centres_world(R, t, origin, vs, shape, flat, out):
    for n in range(flat.shape[0]):
        f = flat[n]
        k = f % shape[2]
        j = (f // shape[2]) % shape[1]
        i = f // (shape[1] * shape[2])
        out[n, 0], out[n, 1], out[n, 2] = _centre_world(R, t, origin, vs, i, j, k)


def static_labels_at_cells(
    smap: StaticMap, spec: GridSpec, T_world_from_grid: np.ndarray
) -> np.ndarray:
    """Label of the map voxel under each cell centre of a grid.

    smap: the static map (world frame). spec: the grid in its own frame (base).
    T_world_from_grid: (4, 4) float64. Returns (X, Y, Z) uint8 class ids, UNLABELED where the map
    has no voxel. The centres are taken in float32 in the world frame (the precision of the fused
    static points).
    """
    T = np.asarray(T_world_from_grid, dtype=np.float64)
    table, labels = sorted_table(smap)
    out = np.empty(spec.shape, dtype=np.uint8)
    _pull_labels(
        np.ascontiguousarray(T[:3, :3]),
        np.ascontiguousarray(T[:3, 3]),
        spec.origin,
        spec.voxel_size_m,
        np.asarray(spec.shape, dtype=np.int64),
        smap.voxel_size_m,
        table,
        labels,
        out,
    )
    return out


def static_in_grid(
    smap: StaticMap, spec: GridSpec, T_world_from_base: np.ndarray, reach_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """The static map as labelled points (world frame) for one frame's local grid.

    smap: the static map (world frame). spec: the local grid (base frame). T_world_from_base:
    (4, 4) float64 pose of the frame. reach_m: horizontal radius around the robot that holds the
    grid (used for a finer map). Returns (points (N, 3) float32 world frame, labels (N,) uint8).
    A map as coarse as the grid or coarser: one point per labelled cell, at the cell centre, with
    the label of the map voxel under it (cells in C order); a finer map: points filling each map
    voxel within reach_m (:meth:`StaticMap.sample_points` at the grid's voxel size). A map with
    surfaces: points on them (module docstring), at a quarter of the grid's voxel apart.
    """
    if smap.surface is not None:
        return _surface_points(smap.crop(np.asarray(T_world_from_base)[:3, 3], reach_m), spec)
    if smap.voxel_size_m < spec.voxel_size_m - 1e-9:
        return smap.crop(np.asarray(T_world_from_base)[:3, 3], reach_m).sample_points(
            spec.voxel_size_m
        )
    labels = static_labels_at_cells(smap, spec, T_world_from_base).reshape(-1)
    flat = np.flatnonzero(labels != UNLABELED)
    T = np.asarray(T_world_from_base, dtype=np.float64)
    pts = np.empty((len(flat), 3), dtype=np.float32)
    _centres_world(
        np.ascontiguousarray(T[:3, :3]),
        np.ascontiguousarray(T[:3, 3]),
        spec.origin,
        spec.voxel_size_m,
        np.asarray(spec.shape, dtype=np.int64),
        flat,
        pts,
    )
    return pts, labels[flat]


def _surface_points(smap: StaticMap, spec: GridSpec) -> tuple[np.ndarray, np.ndarray]:
    """(points (N, 3) float32 world frame, labels (N,) uint8) standing for a map with surfaces in
    a grid of spec's voxel size: planes sampled at a quarter of the grid's voxel; a voxel without
    a plane as its centroid, or, coarser than the grid, as points filling it."""
    vs = smap.voxel_size_m
    planar = np.any(smap.surface[:, 3:] != 0, axis=1)
    coarse = ~planar if vs > spec.voxel_size_m + 1e-9 else np.zeros(len(planar), bool)
    pts, rows = surface_samples(
        smap.keys[~coarse], smap.surface[~coarse], vs, min(vs, spec.voxel_size_m) / 4
    )
    labels = smap.labels[~coarse][rows]
    if coarse.any():
        fill, fill_labels = StaticMap(
            vs, smap.keys[coarse], smap.labels[coarse], smap.counts[coarse], 0
        ).sample_points(spec.voxel_size_m)
        pts = np.concatenate([pts.astype(np.float32), fill])
        labels = np.concatenate([labels, fill_labels])
    return pts.astype(np.float32), labels.astype(np.uint8)


def grid_reach_m(spec: GridSpec) -> float:
    """Horizontal distance from the grid's origin (the robot) to its farthest corner, plus 1 m:
    the radius around the robot that holds the local grid."""
    corners = np.abs(np.array([spec.range_min, spec.range_max], np.float64)).max(axis=0)
    return float(np.linalg.norm(corners[:2])) + 1.0
