"""Per detection (hence per track and frame) the LiDAR points that belong to the person.

1. Project the sweep into the image with K and T_cam_from_lidar (z > ``min_depth_m``, inside),
   and drop ground points (less than ``ground_tol_m`` above the local ground of
   :func:`tasks.perception.lidar_clusters.robust_ground_height`, cells of ``ground_cell_m``, its
   ``ground_percentile`` and ``ground_max_drop_m``: returns below the road do not sink it): ground runs continuously from the
   feet to the background and would bridge the range gaps of step 3. After step 3 the ground-band
   points of the selection lying within ``feet_radius_m`` (horizontally) of the chosen points are
   added back: they are the feet.
2. Keep the points whose pixel is in the detection's instance mask (its box if the mask is empty).
3. The kept points still hold background seen past the silhouette edge (calibration, sweep/shutter
   timing, mask noise) and occluders in front: sort them by range from the camera, split at gaps
   larger than ``gap_m`` (1D range clustering) and keep the segment with the best score
   ``points x exp(-0.5 ((median range - expected) / sigma)^2) x centrality``, where ``expected`` is
   the range of an associated LiDAR box if any, else the range a ``person_height_m`` tall person
   would have at the box's pixel height (the term is dropped when the box is cut by the image
   border), sigma = ``range_sigma_frac`` x expected, and centrality is the fraction of the
   segment's points whose pixel lies in the inner part of the box (the middle ``core_frac`` of
   its width).
4. When the detection box reaches within ``edge_margin_px`` of the left or right image border (the
   person is leaving or entering the camera's view; detector boxes stop a few pixels short or
   past it), the image says nothing about the points past that border: the selection
   grows into the non-ground points outside the image connected to it (through occupied voxels of
   ``edge_grow_m / 2``, 26-neighbourhood: gaps up to about ``edge_grow_m`` are bridged), no
   farther than ``edge_extent_m`` (horizontally) from the selection's median;
   ground-band points outside the image within ``feet_radius_m`` of the result are its feet.
   ``edge_grow_m = 0`` turns this off.

LiDAR boxes are associated with image detections by the Hungarian method on the IoU between the
detection box and the image rectangle of the projected 3D box (``min_iou``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from tasks.bounds import AtLeastOne, NonNegative, Positive, PositiveFraction, Probability
from tasks.geometry import box_iou
from tasks.perception.lidar_clusters import robust_ground_height
from tasks.perception.types import box_corners

#: a LiDAR box whose corner is nearer the camera plane than this has no image box (is not matched)
BOX_CORNER_MIN_DEPTH_M = 0.1


@dataclass(frozen=True)
class PersonPointParams:
    """Settings of :func:`person_point_indices` (the steps of the module docstring). Lengths in
    metres, LiDAR z up."""

    #: step 3: split the range-sorted points at gaps larger than this
    gap_m: Positive = 0.3
    #: step 3: a segment needs this many points
    min_points: AtLeastOne = 3
    #: step 3: expected range from the box's pixel height for a person this tall
    person_height_m: Positive = 1.7
    range_sigma_frac: Positive = 0.25
    core_frac: PositiveFraction = 0.5
    #: step 1: points at camera depth z <= this are not projected
    min_depth_m: NonNegative = 0.5
    #: step 1: points less than this above the local ground are ground (None keeps all)
    ground_tol_m: float | None = 0.15
    ground_cell_m: Positive = 2.0
    #: step 1: the ground model's quantile per cell and outlier drop (robust_ground_height)
    ground_percentile: Probability = 0.1
    ground_max_drop_m: Positive = 0.5
    feet_radius_m: NonNegative = 0.1
    #: step 4 (0 = off)
    edge_grow_m: NonNegative = 0.25
    edge_extent_m: Positive = 0.7
    edge_margin_px: NonNegative = 20.0
    #: LiDAR boxes match image detections at this IoU or more (:func:`associate_lidar_boxes`)
    assoc_min_iou: Probability = 0.3


def _rigid(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    # column by column: (N, 3) @ (3, 3) through BLAS is several times slower for tall N here
    R, t = T[:3, :3], T[:3, 3]
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    return np.stack([R[i, 0] * x + R[i, 1] * y + R[i, 2] * z + t[i] for i in range(3)], axis=1)


def _pixels(cam: np.ndarray, K: np.ndarray, min_depth_m: float) -> np.ndarray:
    uv = np.full((cam.shape[0], 2), np.nan)
    front = cam[:, 2] > min_depth_m
    x, y, z = cam[front, 0], cam[front, 1], cam[front, 2]
    uv[front, 0] = (K[0, 0] * x + K[0, 1] * y) / z + K[0, 2]
    uv[front, 1] = K[1, 1] * y / z + K[1, 2]
    return uv


def _in_image(uv: np.ndarray, width: int, height: int) -> np.ndarray:
    """(N,) bool: pixel inside the image (NaN, i.e. behind the camera, is not)."""
    return (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)


def project_points(
    points_lidar: np.ndarray, K: np.ndarray, T_cam_from_lidar: np.ndarray, min_depth_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection (no distortion: undistort the image or the detections first).

    points_lidar: (N, 3) float metres, LiDAR frame. K: (3, 3) float64 pixels (zero K[1, 0], K[2, :2]).
    T_cam_from_lidar: (4, 4) float64. Returns uv (N, 2) float64 pixels and depth (N,) float64
    camera z in metres; uv is NaN where depth <= min_depth_m.
    """
    points = np.asarray(points_lidar, np.float64).reshape(-1, 3)
    cam = _rigid(points, np.asarray(T_cam_from_lidar, np.float64))
    return _pixels(cam, np.asarray(K, np.float64), min_depth_m), cam[:, 2]


def associate_lidar_boxes(
    boxes_xyxy: np.ndarray,
    centers: np.ndarray,
    sizes: np.ndarray,
    yaws: np.ndarray,
    K: np.ndarray,
    T_cam_from_lidar: np.ndarray,
    min_iou: float,
) -> np.ndarray:
    """Match image detections to LiDAR pedestrian boxes.

    boxes_xyxy: (D, 4) float pixels. centers, sizes: (M, 3) metres LiDAR frame (l, w, h); yaws:
    (M,) radians. Returns (D,) int64 row of the matched LiDAR box, -1 if none. Boxes with a corner
    behind the camera are not matched.
    """
    boxes = np.asarray(boxes_xyxy, np.float64).reshape(-1, 4)
    count, m = boxes.shape[0], np.asarray(centers).reshape(-1, 3).shape[0]
    matched = np.full(count, -1, np.int64)
    if count == 0 or m == 0:
        return matched
    corners = box_corners(
        np.asarray(centers).reshape(-1, 3),
        np.asarray(sizes).reshape(-1, 3),
        np.asarray(yaws).reshape(-1),
    )
    uv, _ = project_points(corners.reshape(-1, 3), K, T_cam_from_lidar, BOX_CORNER_MIN_DEPTH_M)
    uv = uv.reshape(m, 8, 2)
    valid = ~np.isnan(uv).any(axis=(1, 2))
    rect = np.zeros((m, 4))
    rect[valid] = np.concatenate([uv[valid].min(axis=1), uv[valid].max(axis=1)], axis=1)
    iou = box_iou(boxes, rect)
    iou[:, ~valid] = 0.0
    rows, cols = linear_sum_assignment(-iou)
    good = iou[rows, cols] >= min_iou
    matched[rows[good]] = cols[good]
    return matched


def _ground(points: np.ndarray, p: PersonPointParams) -> np.ndarray:
    return robust_ground_height(points, p.ground_cell_m, p.ground_percentile, p.ground_max_drop_m)


def _split_by_range(ranges: np.ndarray, gap_m: float) -> list[np.ndarray]:
    order = np.argsort(ranges, kind="stable")
    cuts = np.flatnonzero(np.diff(ranges[order]) > gap_m) + 1
    return np.split(order, cuts)


def person_point_indices(
    points_lidar: np.ndarray,
    K: np.ndarray,
    T_cam_from_lidar: np.ndarray,
    image_size: tuple[int, int],
    boxes_xyxy: np.ndarray,
    masks: np.ndarray | None = None,
    expected_range_m: np.ndarray | None = None,
    params: PersonPointParams = PersonPointParams(),
) -> list[np.ndarray]:
    """LiDAR point indices of each detected person.

    points_lidar: (N, 3) float32 metres, LiDAR frame. K: (3, 3) float64; T_cam_from_lidar: (4, 4)
    float64; image_size: (width, height) pixels. boxes_xyxy: (D, 4) float pixels. masks: (D, H, W)
    bool instance masks or None (an all-False mask falls back to its box). expected_range_m: (D,)
    float metres from the camera centre (e.g. an associated LiDAR box), NaN = unknown, or None.
    params: the steps' settings (:class:`PersonPointParams`, the module docstring).
    Returns D int64 arrays of row indices into points_lidar (sorted; empty when nothing is found).
    """
    p = params
    width, height = int(image_size[0]), int(image_size[1])
    boxes = np.asarray(boxes_xyxy, np.float64).reshape(-1, 4)
    count = boxes.shape[0]
    if count == 0:
        return []
    if masks is not None and tuple(masks.shape) != (count, height, width):
        raise ValueError(f"masks: expected ({count}, {height}, {width}), got {masks.shape}")
    expected = np.full(count, np.nan)
    if expected_range_m is not None:
        expected = np.asarray(expected_range_m, np.float64).reshape(count)

    points = np.asarray(points_lidar, np.float64).reshape(-1, 3)
    cam_all = _rigid(points, np.asarray(T_cam_from_lidar, np.float64))
    front = np.flatnonzero(cam_all[:, 2] > p.min_depth_m)
    uv = _pixels(cam_all[front], np.asarray(K, np.float64), p.min_depth_m)
    inside = _in_image(uv, width, height)
    idx = front[inside]
    uv, cam = uv[inside], cam_all[idx]
    is_ground = np.zeros(idx.size, bool)
    lidar_xyz = points[idx]
    if p.ground_tol_m is not None and idx.size:
        is_ground = lidar_xyz[:, 2] - _ground(lidar_xyz, p) < p.ground_tol_m
    side_cut = (boxes[:, 0] <= p.edge_margin_px) | (boxes[:, 2] >= width - p.edge_margin_px)
    edge = None  # the points outside the image, gathered once if some box nears a side
    if p.edge_grow_m > 0 and side_cut.any():
        # only the points near the image's left / right side planes can join a cut person
        Kf = np.asarray(K, np.float64)
        x, z = cam_all[:, 0], cam_all[:, 2]
        a_left, a_right = Kf[0, 2] / Kf[0, 0], (width - Kf[0, 2]) / Kf[0, 0]
        band = p.edge_extent_m + p.edge_grow_m
        near_side = (z > -band) & (
            (np.abs(x + a_left * z) <= band * np.hypot(1.0, a_left))
            | (np.abs(x - a_right * z) <= band * np.hypot(1.0, a_right))
        )
        near_side[idx] = False
        out_idx = np.flatnonzero(near_side)
        out_ground = np.zeros(out_idx.size, bool)
        if p.ground_tol_m is not None and out_idx.size:
            out_ground = points[out_idx, 2] - _ground(points[out_idx], p) < p.ground_tol_m
        edge = _OutsidePoints(points, out_idx[~out_ground], out_idx[out_ground])
    u, v = uv[:, 0], uv[:, 1]
    col, row = u.astype(np.int64), v.astype(np.int64)
    ranges_all = np.linalg.norm(cam, axis=1)
    fy = float(np.asarray(K)[1, 1])

    result = []
    for d in range(count):
        u0, v0, u1, v1 = boxes[d]
        in_box = (u >= u0) & (u < u1) & (v >= v0) & (v < v1)
        if masks is not None and masks[d].any():
            sel = np.flatnonzero(in_box)
            sel = sel[masks[d][row[sel], col[sel]]]
        else:
            sel = np.flatnonzero(in_box)
        ground_sel, sel = sel[is_ground[sel]], sel[~is_ground[sel]]
        if sel.size == 0:
            result.append(np.zeros(0, np.int64))
            continue
        exp_range = expected[d]
        cut = v0 <= 1 or v1 >= height - 1
        if not np.isfinite(exp_range) and not cut and v1 - v0 > 1:
            exp_range = fy * p.person_height_m / (v1 - v0)
        centre, half = (u0 + u1) / 2, p.core_frac * (u1 - u0) / 2
        best, best_score = None, -np.inf
        for segment in _split_by_range(ranges_all[sel], p.gap_m):
            if segment.size < p.min_points:
                continue
            members = sel[segment]
            score = segment.size * max(np.mean(np.abs(u[members] - centre) <= half), 0.05)
            if np.isfinite(exp_range):
                z = (np.median(ranges_all[members]) - exp_range) / (p.range_sigma_frac * exp_range)
                score *= np.exp(-0.5 * z * z)
            if score > best_score:
                best, best_score = members, score
        if best is None:
            result.append(np.zeros(0, np.int64))
            continue
        if ground_sel.size:
            tree = cKDTree(lidar_xyz[best, :2])
            near, _ = tree.query(lidar_xyz[ground_sel, :2], distance_upper_bound=p.feet_radius_m)
            best = np.concatenate([best, ground_sel[np.isfinite(near)]])
        chosen = idx[best]
        if edge is not None and side_cut[d]:
            chosen = edge.grow(chosen, p.edge_grow_m, p.edge_extent_m, p.feet_radius_m)
        result.append(np.sort(chosen))
    return result


def in_image_first(
    points_lidar: np.ndarray,
    point_sets: list[np.ndarray],
    K: np.ndarray,
    T_cam_from_lidar: np.ndarray,
    image_size: tuple[int, int],
    min_depth_m: float,
) -> tuple[list[np.ndarray], np.ndarray]:
    """Each set reordered as its points inside the image (sorted) then those outside (sorted), and
    (D,) int64 how many are inside: the camera-side consumers (the body fit, whose visibility
    filter only knows what the image shows) take the leading part.
    """
    width, height = int(image_size[0]), int(image_size[1])
    ordered, counts = [], np.zeros(len(point_sets), np.int64)
    for d, idx in enumerate(point_sets):
        idx = np.asarray(idx, np.int64)
        uv, depth = project_points(np.asarray(points_lidar)[idx], K, T_cam_from_lidar, min_depth_m)
        inside = (depth > min_depth_m) & _in_image(uv, width, height)
        ordered.append(np.concatenate([np.sort(idx[inside]), np.sort(idx[~inside])]))
        counts[d] = int(inside.sum())
    return ordered, counts


class _OutsidePoints:
    """The sweep's points outside the image (split into body and ground band) for step 4."""

    def __init__(self, points: np.ndarray, body: np.ndarray, ground: np.ndarray):
        self.points, self.body, self.ground = points, body, ground
        self.body_xy, self.ground_xy = points[body, :2], points[ground, :2]

    def grow(
        self, chosen: np.ndarray, step_m: float, extent_m: float, feet_radius_m: float
    ) -> np.ndarray:
        """``chosen`` (global point indices) plus the outside points connected to it."""
        if chosen.size == 0:
            return chosen
        centre = np.median(self.points[chosen, :2], axis=0)
        near = self.body[np.sum((self.body_xy - centre) ** 2, axis=1) <= extent_m**2]
        if near.size == 0:
            return chosen
        # connectivity on a voxel grid (cells of step_m / 2, 26-neighbourhood): linear in the points,
        # where ball queries from every point of a near person (thousands) cost much more
        cloud = np.concatenate([self.points[chosen], self.points[near]])
        cells = np.floor((cloud - cloud.min(axis=0)) / (step_m / 2)).astype(np.int64)
        grid = np.zeros(tuple(cells.max(axis=0) + 1), bool)
        grid[cells[:, 0], cells[:, 1], cells[:, 2]] = True
        labels, _ = ndimage.label(grid, structure=np.ones((3, 3, 3), bool))
        label = labels[cells[:, 0], cells[:, 1], cells[:, 2]]
        taken = np.isin(label[chosen.size :], label[: chosen.size])
        if not taken.any():
            return chosen
        grown = near[taken]
        if feet_radius_m > 0 and self.ground.size:
            cand = self.ground[
                np.sum((self.ground_xy - centre) ** 2, axis=1) <= (extent_m + feet_radius_m) ** 2
            ]
            if cand.size:
                dist, _ = cKDTree(self.points[grown]).query(
                    self.points[cand], distance_upper_bound=feet_radius_m
                )
                grown = np.concatenate([grown, cand[np.isfinite(dist)]])
        return np.concatenate([chosen, grown])
