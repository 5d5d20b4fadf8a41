"""The ``lidar-clusters`` provider: weight-free LiDAR pedestrian boxes from one sweep.

Steps: (1) the ground (:func:`robust_ground_height`): per ``ground_cell_m`` grid cell a low
percentile (``ground_percentile``) of its points' z, not the minimum: a few returns below the road
(multipath: on a KITTI HDL-64 sweep 83 of them, 0.07 %, put a minimum-based ground 5.16 m under a
person 8.4 m ahead, who then measured 3.5-5.4 m tall and was dropped) move a percentile little;
a cell whose value lies more than ``ground_max_drop_m`` below each of its 8 neighbours' (those
holding points) is an outlier and left out, points more than ``ground_max_drop_m`` below the
resulting model are outliers and the percentile is taken again without them; a point's ground is the lowest accepted value in
its cell's 3 x 3 neighbourhood (so a cell filled by an object borrows its neighbours' ground).
``ground_percentile = 0`` with ``ground_max_drop_m`` huge is the old per-cell minimum. Points less
than ``ground_tol_m`` above the ground are ground, points more than ``ceiling_m`` above it are
dropped (tree canopies, overhangs), which also caps tall walls / poles at ``ceiling_m`` so the
height gate rejects them; points below the ground are dropped. (2) Euclidean clustering: points are
binned into ``voxel_m`` voxels, voxels closer than ``cluster_tol_m`` are linked (scipy cKDTree
pairs + connected components). (3) Gates: height above ground in [min_height_m, max_height_m],
oriented footprint (PCA in xy) longest side <= ``max_footprint_m``, at least ``min_points``
points. (4) A person score in [0, 1] from the cluster's shape (:func:`person_score`); clusters
scoring below ``min_score`` are dropped.

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

from tasks.bounds import AtLeastOne, NonNegative, Positive, Probability
from tasks.perception.types import LidarDetections


@dataclass(frozen=True)
class LidarClusterParams:
    """Settings of :func:`detect_pedestrians_lidar` (steps and gates: the module docstring).
    Lengths in metres, heights above the local ground."""

    ground_cell_m: Positive = 2.0
    ground_tol_m: NonNegative = 0.2
    #: step 1: a cell's ground is this quantile of its points' z (0 = the minimum)
    ground_percentile: Probability = 0.1
    #: step 1: cells / points this far below the neighbours' ground are outliers (multipath)
    ground_max_drop_m: Positive = 0.5
    ceiling_m: Positive = 2.4
    voxel_m: Positive = 0.1
    cluster_tol_m: Positive = 0.3
    min_points: AtLeastOne = 10
    min_height_m: Positive = 1.0
    max_height_m: Positive = 2.1
    max_footprint_m: Positive = 1.2
    #: points farther (horizontally) from the sensor are not clustered
    max_range_m: Positive = 40.0
    #: step 4: clusters whose person score (:func:`person_score`) is lower are not reported
    min_score: Probability = 0.3


def ground_height(points_lidar: np.ndarray, cell_m: float) -> np.ndarray:
    """Local ground height under each point (the plain minimum; the detector uses
    :func:`robust_ground_height`).

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


def _cell_quantile(flat: np.ndarray, z: np.ndarray, size: int, q: float) -> np.ndarray:
    """(size,) the q-quantile (lower) of z per flat cell index, NaN for empty cells."""
    out = np.full(size, np.nan)
    if flat.size == 0:
        return out
    order = np.lexsort((z, flat))
    cells = flat[order]
    starts = np.flatnonzero(np.r_[True, np.diff(cells) != 0])
    counts = np.diff(np.r_[starts, cells.size])
    pick = starts + np.floor(q * (counts - 1)).astype(np.int64)
    out[cells[starts]] = z[order][pick]
    return out


#: the 8 neighbours of a cell (itself excluded)
_RING = np.array([[1, 1, 1], [1, 0, 1], [1, 1, 1]], bool)


def robust_ground_height(
    points_lidar: np.ndarray, cell_m: float, percentile: float, max_drop_m: float
) -> np.ndarray:
    """Local ground height under each point, robust to returns below the ground (step 1 of the
    module docstring).

    points_lidar: (N, 3) float metres, LiDAR frame (z up). cell_m: cell size, metres; percentile:
    the quantile in [0, 1] of a cell's z taken as its ground; max_drop_m: a cell this far below
    every neighbour holding points, and then a point this far below its neighbourhood's ground,
    is an outlier. Returns (N,) float64 metres.
    """
    points = np.asarray(points_lidar, np.float64).reshape(-1, 3)
    if points.shape[0] == 0:
        return np.zeros(0)
    cells = np.floor(points[:, :2] / cell_m).astype(np.int64)
    cells -= cells.min(axis=0) - 1
    shape = tuple(int(v) for v in cells.max(axis=0) + 2)
    flat = np.ravel_multi_index((cells[:, 0], cells[:, 1]), shape)
    size = shape[0] * shape[1]
    z = points[:, 2]
    inlier = np.ones(z.size, bool)
    for _ in range(2):  # the second pass without the points below the first model
        grid = _cell_quantile(flat[inlier], z[inlier], size, percentile).reshape(shape)
        filled = np.where(np.isnan(grid), np.inf, grid)
        # a cell sunk more than max_drop_m below every neighbour holding points is an outlier
        lowest_neighbour = ndimage.minimum_filter(
            filled, footprint=_RING, mode="constant", cval=np.inf
        )
        filled[filled < lowest_neighbour - max_drop_m] = np.inf
        model = ndimage.minimum_filter(filled, size=3, mode="constant", cval=np.inf)
        inlier = z >= model.reshape(-1)[flat] - max_drop_m
    ground = model.reshape(-1)[flat]
    # a point whose whole neighbourhood was rejected keeps its own cell's raw quantile
    lost = ~np.isfinite(ground)
    if lost.any():
        raw = _cell_quantile(flat, z, size, percentile)
        ground[lost] = raw[flat[lost]]
    return ground


def _trapezoid(x: float, a: float, b: float, c: float, d: float) -> float:
    """0 below a and above d, 1 on [b, c], linear between."""
    if x <= a or x >= d:
        return 0.0
    if x < b:
        return (x - a) / (b - a)
    if x > c:
        return (d - x) / (d - c)
    return 1.0


def _extent(xy: np.ndarray) -> float:
    """Longest side of the oriented (PCA) footprint of (n, 2) points, metres (0 for n < 2)."""
    if xy.shape[0] < 2:
        return 0.0
    centred = xy - xy.mean(axis=0)
    _, vectors = np.linalg.eigh(centred.T @ centred + 1e-12 * np.eye(2))
    along = centred @ vectors[:, 1]
    return float(along.max() - along.min())


#: person_score's components, their names in its returned dict
SCORE_PARTS = ("height", "torso_width", "taper", "upright", "fill", "aspect")


def person_score(cluster_lidar: np.ndarray, base_z: float) -> tuple[float, dict[str, float]]:
    """How person-like one cluster is, from its shape alone (no scanner-specific densities).

    cluster_lidar: (n, 3) float metres, LiDAR frame; base_z: the ground under it, metres.
    Returns (score in [0, 1], {part: value in [0, 1]}): the product of (each part can veto)

    - height: top above ground, 1 on [1.45, 1.95] m, 0 at 1.0 and 2.15 m;
    - torso_width: oriented extent of the band 45-80 % of the height, 1 on [0.3, 0.8] m, 0 at
      0.12 and 1.1 m (a pole or a thin post is narrower, a bush wider);
    - taper: extent of the top 13 % (the head) over the torso's (the head is narrower than the shoulders and
      the swinging arms: 0.23 median, 0.13-0.79 for 90 % of the simulator's people), 1 on
      [0.1, 0.7], 0 at 0.03 and 0.95 (a post or a pole is as wide at the top as below);
    - upright: horizontal distance between the centroids of the top 13 % and the lowest 40 %
      (head over feet), 1 up to 0.25 m, 0 at 0.6 m;
    - fill: fraction of ten height bins from 0.1 m to the top holding points, 1 from 0.8, 0 at 0.4
      (a crown on a trunk, a sign on a pole leave gaps);
    - aspect: height over the footprint's longest side, 1 from 1.6, 0 at 1.0 (a bush is squat).
    """
    pts = np.asarray(cluster_lidar, np.float64).reshape(-1, 3)
    rel = pts[:, 2] - base_z
    top = float(rel.max()) if rel.size else 0.0
    parts = dict.fromkeys(SCORE_PARTS, 0.0)
    if pts.shape[0] < 3 or top <= 0.3:
        return 0.0, parts
    torso = pts[(rel >= 0.45 * top) & (rel <= 0.8 * top), :2]
    head = pts[rel >= 0.87 * top, :2]  # a head is about 1/7.5 of the height
    feet = pts[rel <= 0.4 * top, :2]
    torso_w = _extent(torso)
    parts["height"] = _trapezoid(top, 1.0, 1.45, 1.95, 2.15)
    parts["torso_width"] = _trapezoid(torso_w, 0.12, 0.3, 0.8, 1.1)
    if torso_w > 0 and head.shape[0] >= 2:
        parts["taper"] = _trapezoid(_extent(head) / torso_w, 0.03, 0.1, 0.7, 0.95)
    if head.shape[0] and feet.shape[0]:
        offset = float(np.linalg.norm(head.mean(axis=0) - feet.mean(axis=0)))
        parts["upright"] = _trapezoid(offset, -1.0, 0.0, 0.25, 0.6)
    bins = np.floor((rel - 0.1) / max(top - 0.1, 1e-6) * 10).astype(np.int64)
    filled = np.unique(bins[(bins >= 0) & (bins < 10)]).size / 10.0
    parts["fill"] = _trapezoid(filled, 0.4, 0.8, 2.0, 3.0)
    parts["aspect"] = _trapezoid(top / max(_extent(pts[:, :2]), 1e-6), 1.0, 1.6, 1e9, 2e9)
    values = np.array([parts[k] for k in SCORE_PARTS])
    return float(np.prod(values)), parts


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
    score: :func:`person_score` (>= ``min_score``).
    """
    p = params
    points = np.asarray(points_lidar, np.float64).reshape(-1, 3)
    points = points[np.linalg.norm(points[:, :2], axis=1) <= p.max_range_m]
    ground = robust_ground_height(points, p.ground_cell_m, p.ground_percentile, p.ground_max_drop_m)
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
        score, _ = person_score(cluster, base)
        if score < p.min_score:
            continue
        centre_xy = mean + ((lo + hi) / 2) @ rot
        centers.append([centre_xy[0], centre_xy[1], (base + top) / 2])
        sizes.append([max(length, 0.05), max(width, 0.05), top - base])
        yaws.append(yaw)
        scores.append(score)
    if not centers:
        return LidarDetections.empty()
    return LidarDetections(
        centers=np.asarray(centers, np.float32),
        sizes=np.asarray(sizes, np.float32),
        yaws=np.asarray(yaws, np.float32),
        scores=np.asarray(scores, np.float32),
    )
