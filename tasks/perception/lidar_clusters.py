"""The ``lidar-clusters`` provider: weight-free LiDAR pedestrian boxes from one sweep.

Steps: (1) ground height per ``ground_cell_m`` grid cell = the lowest point in the cell's 3 x 3
neighbourhood (so a cell filled by an object borrows its neighbours' ground); points less than
``ground_tol_m`` above it are ground, points more than ``ceiling_m`` above it are dropped (tree
canopies, overhangs), which also caps tall walls / poles at ``ceiling_m`` so the height gate
rejects them. (2) Euclidean clustering: points are binned into ``voxel_m`` voxels, voxels closer
than ``cluster_tol_m`` are linked (scipy cKDTree pairs + connected components). (3) Gates: height
above ground in [min_height_m, max_height_m], oriented footprint (PCA in xy) longest side
<= ``max_footprint_m``, at least ``min_points`` points.

Deterministic (no random sampling). A person under a tree or touching a wall merges with it and is
missed; LiDAR boxes only complement the image detections (people outside the camera frustum).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from tasks.bounds import AtLeastOne, NonNegative, Positive
from tasks.perception.types import LidarDetections


@dataclass(frozen=True)
class LidarClusterParams:
    """Settings of :func:`detect_pedestrians_lidar` (steps and gates: the module docstring).
    Lengths in metres, heights above the local ground."""

    ground_cell_m: Positive = 2.0
    ground_tol_m: NonNegative = 0.2
    ceiling_m: Positive = 2.4
    voxel_m: Positive = 0.1
    cluster_tol_m: Positive = 0.3
    min_points: AtLeastOne = 10
    min_height_m: Positive = 1.0
    max_height_m: Positive = 2.1
    max_footprint_m: Positive = 1.2
    #: points farther (horizontally) from the sensor are not clustered
    max_range_m: Positive = 40.0


def ground_height(points_lidar: np.ndarray, cell_m: float) -> np.ndarray:
    """Local ground height under each point.

    points_lidar: (N, 3) float32 metres, LiDAR frame (z up). Returns (N,) float64 metres, the lowest
    z in the point's cell and its 8 neighbours.
    """
    points = np.asarray(points_lidar, np.float64)
    if points.shape[0] == 0:
        return np.zeros(0)
    cells = np.floor(points[:, :2] / cell_m).astype(np.int64)
    origin = cells.min(axis=0) - 1
    cells -= origin
    shape = tuple(cells.max(axis=0) + 2)
    grid = np.full(shape, np.inf)
    np.minimum.at(grid, (cells[:, 0], cells[:, 1]), points[:, 2])
    grid = ndimage.minimum_filter(grid, size=3, mode="constant", cval=np.inf)
    return grid[cells[:, 0], cells[:, 1]]


def cluster_points(points: np.ndarray, voxel_m: float, cluster_tol_m: float) -> np.ndarray:
    """Euclidean cluster labels.

    points: (N, 3) float metres. Returns (N,) int64 labels 0..C-1, numbered by each cluster's first
    voxel in sorted voxel order (deterministic).
    """
    if points.shape[0] == 0:
        return np.zeros(0, np.int64)
    keys = np.floor(np.asarray(points, np.float64) / voxel_m).astype(np.int64)
    unique, inverse = np.unique(keys, axis=0, return_inverse=True)
    centres = (unique + 0.5) * voxel_m
    pairs = cKDTree(centres).query_pairs(cluster_tol_m, output_type="ndarray")
    count = unique.shape[0]
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(count, count))
    _, voxel_labels = connected_components(graph, directed=False)
    return voxel_labels[inverse.reshape(-1)].astype(np.int64)


def detect_pedestrians_lidar(
    points_lidar: np.ndarray, params: LidarClusterParams = LidarClusterParams()
) -> LidarDetections:
    """Pedestrian-like clusters of one sweep as 3D boxes.

    points_lidar: (N, 3) float32 metres, LiDAR frame, z up. Returns LidarDetections in the LiDAR
    frame: box bottom on the local ground, (l, w) the oriented footprint (l >= w), yaw of l's axis,
    score = min(1, points / (5 * min_points)) * 0.5 + 0.5.
    """
    p = params
    points = np.asarray(points_lidar, np.float64).reshape(-1, 3)
    points = points[np.linalg.norm(points[:, :2], axis=1) <= p.max_range_m]
    ground = ground_height(points, p.ground_cell_m)
    height = points[:, 2] - ground
    keep = (height >= p.ground_tol_m) & (height <= p.ceiling_m)
    objects, object_ground = points[keep], ground[keep]
    labels = cluster_points(objects, p.voxel_m, p.cluster_tol_m)
    if labels.size == 0:
        return LidarDetections.empty()
    order = np.argsort(labels, kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(labels[order]) != 0])
    centers, sizes, yaws, scores = [], [], [], []
    for members in np.split(order, starts[1:]):
        if members.size < p.min_points:
            continue
        cluster = objects[members]
        base = float(np.min(object_ground[members]))
        top = float(cluster[:, 2].max())
        if not (p.min_height_m <= top - base <= p.max_height_m):
            continue
        xy = cluster[:, :2]
        mean = xy.mean(axis=0)
        _, vectors = np.linalg.eigh(np.cov((xy - mean).T) + 1e-9 * np.eye(2))
        axis = vectors[:, 1]
        yaw = float(np.arctan2(axis[1], axis[0]))
        rot = np.array([[np.cos(yaw), np.sin(yaw)], [-np.sin(yaw), np.cos(yaw)]])
        local = (xy - mean) @ rot.T
        lo, hi = local.min(axis=0), local.max(axis=0)
        length, width = hi - lo
        if max(length, width) > p.max_footprint_m:
            continue
        centre_xy = mean + ((lo + hi) / 2) @ rot
        centers.append([centre_xy[0], centre_xy[1], (base + top) / 2])
        sizes.append([max(length, 0.05), max(width, 0.05), top - base])
        yaws.append(yaw)
        scores.append(0.5 + 0.5 * min(1.0, members.size / (5.0 * p.min_points)))
    if not centers:
        return LidarDetections.empty()
    return LidarDetections(
        centers=np.asarray(centers, np.float32),
        sizes=np.asarray(sizes, np.float32),
        yaws=np.asarray(yaws, np.float32),
        scores=np.asarray(scores, np.float32),
    )
