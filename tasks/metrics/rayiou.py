"""RayIoU and OccScore: the ray-based occupancy metric of SparseOcc and the OpenOcc (CVPR 2024
occupancy and flow) challenge, on our grids, on the CPU.

Definition (read from the public reference code: SparseOcc ``loaders/ray_metrics.py``,
``loaders/ego_pose_dataset.py``, ``lib/dvr/dvr.cu`` (MCG-NJU/SparseOcc); OpenOcc
``projects/mmdet3d_plugin/datasets/ray_metrics.py`` and ``tools/ray_iou/`` (OpenDriveLab/OccNet,
branch ``challenge``); our code is written from that reading, not copied):

1. Query rays. Per frame, up to ``max_origins`` (8) sensor origins: the LiDAR positions of every
   frame of the sequence (the frame itself included) expressed in this frame's grid (base) frame,
   kept when their x and y lie inside the grid's range shrunk by ``origin_margin_m`` (1 m; the
   reference's ``|x|, |y| < 39`` on its +-40 m grid), then thinned to ``round(linspace(0, n - 1,
   8))`` of them in time order. From each origin the same directions: LiDAR-like rings with
   pitches -(pi/2 - atan(k)), k = 1..10 (rings meeting flat ground at 1..10 sensor heights), then
   steps equal to the last gap up to the first pitch >= 0.21 rad (39 pitches), times azimuths
   0, 1, ..., 359 deg (14,040 rays), in base axes.
   Our grids are not centred on the robot (x 0.4-10 m): the frame's own sensor sits behind the
   grid, so it is kept whatever the margin says (the reference keeps it by construction), and a
   ray that never enters the grid hits nothing (the reference never casts one).
2. First hit. Each ray walks the grid voxel by voxel (3D DDA; at a tie the z step goes first,
   then y, then x, as the reference's traversal). The first voxel whose class is not free is the
   hit: its class, and as depth the distance from the origin at which the ray *leaves* that voxel
   (the reference's rendered distance). A ray that leaves the grid (or never enters it) hits
   nothing: class free. No step cap: the reference's 1,000 steps never bind on its 200 x 200 x 16
   grid and would on our 0.02 m grids.
3. Counting. Rays whose ground-truth hit is free are dropped. Per occupied class c (free
   excluded) and threshold t in (1, 2, 4) m: gt_c = rays whose GT hit is c, pred_c = rays whose
   predicted hit is c, tp_c,t = rays with both hits c and |depth_pred - depth_gt| < t (strict);
   IoU_c,t = tp / (gt + pred - tp), NaN when 0 / 0. Counts add over frames and sequences before
   dividing. RayIoU@t = nanmean over classes; RayIoU = nanmean over every (t, c).
4. Flow. AVE_c = mean ||flow_pred - flow_gt|| (m/s) of the hit voxels over the true-positive
   rays of class c at 2 m, for the moving classes (pedestrian, car, truck, two-wheeler, as the
   reference's vehicles and pedestrian); mAVE = nanmean over them. (The packaged
   ``tools/ray_iou/metric.py`` sums the error over every evaluated ray whenever a class has a
   true positive; the dataset's evaluation sums over that class's true positives: we follow the
   latter.)
5. OccScore = 0.9 RayIoU + 0.1 max(1 - mAVE, 0); NaN when mAVE is (no moving-class true positive).

The ground truth is the full ``semantics`` grid, without visibility masks, as in the reference
(Occ3D writes free where unobserved; so do we).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from tasks import conventions as C
from tasks.metrics._common import MetricInputError, check_label_grid


@dataclass(frozen=True)
class RayIoUSettings:
    """Every setting of the metric, with the reference's values as defaults."""

    #: depth-error thresholds of a true positive, m (strictly less than)
    thresholds_m: tuple[float, ...] = (1.0, 2.0, 4.0)
    #: the threshold whose true-positive rays carry the velocity error (AVE)
    flow_threshold_m: float = 2.0
    #: origins per frame (evenly thinned in time order)
    max_origins: int = 8
    #: an origin is kept when x and y lie this far inside the grid's range (the frame's own always)
    origin_margin_m: float = 1.0
    #: azimuth step of the query rays, degrees
    azimuth_step_deg: float = 1.0
    #: classes whose AVE enters mAVE
    flow_classes: tuple[int, ...] = (C.PEDESTRIAN, C.CAR, C.TRUCK, C.TWO_WHEELER)
    #: OccScore = weights[0] RayIoU + weights[1] max(1 - mAVE, 0)
    occ_score_weights: tuple[float, float] = (0.9, 0.1)

    def __post_init__(self) -> None:
        if self.flow_threshold_m not in self.thresholds_m:
            raise ValueError(
                f"flow_threshold_m {self.flow_threshold_m} must be one of thresholds_m "
                f"{self.thresholds_m}"
            )
        if self.max_origins < 1 or self.azimuth_step_deg <= 0:
            raise ValueError(
                f"max_origins ({self.max_origins}) >= 1 and azimuth_step_deg "
                f"({self.azimuth_step_deg}) > 0 expected"
            )


def lidar_ray_directions(azimuth_step_deg: float = 1.0) -> np.ndarray:
    """(R, 3) float64 unit query-ray directions, base axes (x forward, y left, z up).

    Pitches -(pi/2 - atan(k)) for k = 1..10, then the last gap repeated until a pitch reaches
    0.21 rad (39 pitches); azimuths 0, step, ... < 360 deg; pitch-major order."""
    pitches = [-(math.pi / 2 - math.atan(k)) for k in range(1, 11)]
    gap = pitches[-1] - pitches[-2]
    while pitches[-1] < 0.21:
        pitches.append(pitches[-1] + gap)
    pitch = np.asarray(pitches)[:, None]
    azimuth = np.deg2rad(np.arange(0.0, 360.0, azimuth_step_deg))[None, :]
    dirs = np.stack(
        np.broadcast_arrays(
            np.cos(pitch) * np.cos(azimuth), np.cos(pitch) * np.sin(azimuth), np.sin(pitch)
        ),
        axis=-1,
    )
    return dirs.reshape(-1, 3)


def ray_origins(
    T_world_from_base: np.ndarray,
    sensor_positions_world: np.ndarray,
    index: int,
    range_min,
    range_max,
    settings: RayIoUSettings = RayIoUSettings(),
) -> np.ndarray:
    """(T, 3) float64 ray origins of frame ``index`` in its base frame, m, time order.

    T_world_from_base: (4, 4) pose of frame ``index``; sensor_positions_world: (N, 3) the LiDAR
    centre of every frame of the sequence (time order) in the world frame; range_min /
    range_max: the grid's (3,) bounds, m. Kept: positions whose x and y lie strictly inside
    (range_min + margin, range_max - margin), and frame ``index``'s own; then at most
    ``max_origins``, at rounded evenly spaced positions of that list."""
    pos = np.asarray(sensor_positions_world, np.float64).reshape(-1, 3)
    if not 0 <= index < len(pos):
        raise MetricInputError(f"ray_origins: frame index {index} outside 0..{len(pos) - 1}")
    T_base_from_world = np.linalg.inv(np.asarray(T_world_from_base, np.float64))
    local = pos @ T_base_from_world[:3, :3].T + T_base_from_world[:3, 3]
    lo = np.asarray(range_min, np.float64)[:2] + settings.origin_margin_m
    hi = np.asarray(range_max, np.float64)[:2] - settings.origin_margin_m
    keep = np.all((local[:, :2] > lo) & (local[:, :2] < hi), axis=1)
    keep[index] = True
    kept = local[keep]
    if len(kept) > settings.max_origins:
        pick = np.round(np.linspace(0, len(kept) - 1, settings.max_origins)).astype(np.int64)
        kept = kept[pick]
    return kept


@njit(cache=True, inline="always")
def _axis_start(o, d, tm, n):
    """Along one axis: the voxel at ray parameter tm (clamped into 0..n-1), the step (-1, 0, 1),
    the parameter of the next voxel boundary and the parameter per voxel (grid units)."""
    big = 1e300
    c = min(max(int(math.floor(o + d * tm)), 0), n - 1)
    if d > 0.0:
        return c, 1, (c + 1 - o) / d, 1.0 / d
    if d < 0.0:
        return c, -1, (c - o) / d, -1.0 / d
    return c, 0, big, big


@njit(cache=True)
def _first_hits(occupied, shape, origins, dirs, index_out, depth_out):
    """For every (origin t, direction r) ray t * R + r: flat C-order index of its first occupied
    voxel (-1: none) and the distance at which it leaves that voxel (grid units; NaN: none).
    origins (T, 3), dirs (R, 3): grid units (voxel [i, i + 1) per axis), dirs unit length."""
    big = 1e300
    n_dirs = dirs.shape[0]
    s1 = shape[2]
    s0 = shape[1] * s1
    for t in range(origins.shape[0]):
        o = origins[t]
        for r in range(n_dirs):
            k = t * n_dirs + r
            index_out[k] = -1
            depth_out[k] = np.nan
            d = dirs[r]
            # the part of the ray inside the grid box: [t0, t1]
            t0 = 0.0
            t1 = big
            inside = True
            for a in range(3):
                if d[a] == 0.0:
                    if o[a] < 0.0 or o[a] >= shape[a]:
                        inside = False
                else:
                    ta = (0.0 - o[a]) / d[a]
                    tb = (shape[a] - o[a]) / d[a]
                    if ta > tb:
                        ta, tb = tb, ta
                    t0 = max(t0, ta)
                    t1 = min(t1, tb)
            if not inside or t0 >= t1:
                continue
            tm = t0 + 1e-9 * (t1 - t0)
            cx, sx, mx, dx = _axis_start(o[0], d[0], tm, shape[0])
            cy, sy, my, dy = _axis_start(o[1], d[1], tm, shape[1])
            cz, sz, mz, dz = _axis_start(o[2], d[2], tm, shape[2])
            while True:
                flat = cx * s0 + cy * s1 + cz
                # the axis crossed first; ties go to z, then y (the reference's order)
                if mx < my:
                    a = 0 if mx < mz else 2
                else:
                    a = 1 if my < mz else 2
                if occupied[flat]:
                    index_out[k] = flat
                    depth_out[k] = mx if a == 0 else (my if a == 1 else mz)
                    break
                if a == 0:
                    cx += sx
                    mx += dx
                    if cx < 0 or cx >= shape[0]:
                        break
                elif a == 1:
                    cy += sy
                    my += dy
                    if cy < 0 or cy >= shape[1]:
                        break
                else:
                    cz += sz
                    mz += dz
                    if cz < 0 or cz >= shape[2]:
                        break


@dataclass(frozen=True)
class RayHits:
    """First hits of T x R rays (origin-major): classes (T*R,) uint8 (free: no hit); depth_m
    (T*R,) float64 distance from the origin where the ray leaves the hit voxel (NaN: no hit);
    index (T*R,) int64 flat C-order voxel index (-1: no hit)."""

    classes: np.ndarray
    depth_m: np.ndarray
    index: np.ndarray


def cast_rays(
    labels: np.ndarray,
    origins_m: np.ndarray,
    directions: np.ndarray,
    range_min,
    voxel_size_m: float,
    free_class: int = C.FREE,
) -> RayHits:
    """First non-free voxel along every ray from every origin.

    labels: (X, Y, Z) class ids, [x, y, z]; origins_m: (T, 3) m, grid (base) frame; directions:
    (R, 3) base axes (normalised here); range_min: (3,) m, the grid's lower corner."""
    labels = check_label_grid("labels", labels)
    origins = np.asarray(origins_m, np.float64).reshape(-1, 3)
    dirs = np.asarray(directions, np.float64).reshape(-1, 3)
    norms = np.linalg.norm(dirs, axis=1)
    if np.any(norms == 0) or not np.isfinite(dirs).all() or not np.isfinite(origins).all():
        raise MetricInputError("cast_rays: directions must be finite and non-zero, origins finite")
    vs = float(voxel_size_m)
    if not vs > 0:
        raise MetricInputError(f"cast_rays: voxel_size_m {voxel_size_m} must be > 0")
    grid_origins = (origins - np.asarray(range_min, np.float64)) / vs
    n = len(origins) * len(dirs)
    index = np.empty(n, np.int64)
    depth = np.empty(n, np.float64)
    occupied = np.ascontiguousarray((labels != free_class).ravel()).view(np.uint8)
    _first_hits(
        occupied,
        np.asarray(labels.shape, np.int64),
        np.ascontiguousarray(grid_origins),
        np.ascontiguousarray(dirs / norms[:, None]),
        index,
        depth,
    )
    classes = np.full(n, free_class, np.uint8)
    hit = index >= 0
    classes[hit] = labels.ravel()[index[hit]]
    return RayHits(classes, depth * vs, index)


def _zeros(n: int, dtype=np.int64) -> np.ndarray:
    return np.zeros(n, dtype)


@dataclass(frozen=True)
class RayCounts:
    """Counts behind RayIoU and the ray AVE, over classes 0..free-1; add over frames.

    gt (C,) / pred (C,): evaluated rays (GT hit not free) whose GT / predicted hit is class c;
    tp (K, C): both hits c and depth error below thresholds_m[k]; flow_error_sum (C,) m/s and
    flow_count (C,): velocity errors over the true positives at the flow threshold."""

    thresholds_m: tuple[float, ...] = RayIoUSettings().thresholds_m
    gt: np.ndarray = field(default_factory=lambda: _zeros(C.FREE))
    pred: np.ndarray = field(default_factory=lambda: _zeros(C.FREE))
    tp: np.ndarray = field(
        default_factory=lambda: np.zeros((len(RayIoUSettings().thresholds_m), C.FREE), np.int64)
    )
    flow_error_sum: np.ndarray = field(default_factory=lambda: _zeros(C.FREE, np.float64))
    flow_count: np.ndarray = field(default_factory=lambda: _zeros(C.FREE))
    rays: int = 0

    def __add__(self, other: RayCounts) -> RayCounts:
        if tuple(self.thresholds_m) != tuple(other.thresholds_m):
            raise ValueError(
                f"RayCounts: thresholds {self.thresholds_m} and {other.thresholds_m} differ"
            )
        return RayCounts(
            self.thresholds_m,
            self.gt + other.gt,
            self.pred + other.pred,
            self.tp + other.tp,
            self.flow_error_sum + other.flow_error_sum,
            self.flow_count + other.flow_count,
            self.rays + other.rays,
        )

    def per_class_iou(self) -> np.ndarray:
        """(K, C) IoU per threshold and class, NaN where no ray is c on either side."""
        den = self.gt[None, :] + self.pred[None, :] - self.tp
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(den > 0, self.tp / np.maximum(den, 1), np.nan)

    def per_class_ave(self, flow_classes) -> np.ndarray:
        """(C,) mean velocity error (m/s) of the true-positive rays at the flow threshold, NaN
        for classes not in flow_classes or without a true positive."""
        out = np.full(len(self.gt), np.nan)
        for c in flow_classes:
            if self.flow_count[c]:
                out[c] = self.flow_error_sum[c] / self.flow_count[c]
        return out

    def scores(self, settings: RayIoUSettings = RayIoUSettings()) -> dict:
        """RayIoU (and per threshold), mAVE, OccScore, per-class IoU / AVE; NaN where undefined."""
        iou = self.per_class_iou()
        ave = self.per_class_ave(settings.flow_classes)
        iou = iou[:, : C.NUM_SEMANTIC_CLASSES]  # an unclassified hit counts against the GT's class
        ray_iou = _nanmean(iou)
        mave = _nanmean(ave)
        w_iou, w_ave = settings.occ_score_weights
        occ = w_iou * ray_iou + w_ave * max(1.0 - mave, 0.0) if np.isfinite(mave) else np.nan
        names = C.CLASS_NAMES[: len(self.gt)]  # flow classes may be any of them
        return {
            "ray_iou": ray_iou,
            **{f"ray_iou_{t:g}m": _nanmean(iou[k]) for k, t in enumerate(self.thresholds_m)},
            "mave": mave,
            "occ_score": float(occ),
            "rays": int(self.rays),
            "per_class_iou": {
                f"{t:g}m": {n: float(v) for n, v in zip(names, iou[k])}
                for k, t in enumerate(self.thresholds_m)
            },
            "per_class_ave": {names[c]: float(ave[c]) for c in settings.flow_classes},
        }


def _nanmean(a) -> float:
    a = np.asarray(a, np.float64)
    ok = np.isfinite(a)
    return float(a[ok].mean()) if ok.any() else float("nan")


def ray_counts(
    pred: RayHits,
    gt: RayHits,
    settings: RayIoUSettings = RayIoUSettings(),
    pred_flow: np.ndarray | None = None,
    gt_flow: np.ndarray | None = None,
    free_class: int = C.FREE,
) -> RayCounts:
    """Count one frame's rays (same rays on both sides). pred_flow / gt_flow: (X, Y, Z, 2) m/s
    velocity grids read at the hit voxels (None: no AVE counts)."""
    if pred.classes.shape != gt.classes.shape:
        raise MetricInputError(
            f"ray_counts: {pred.classes.shape} predicted and {gt.classes.shape} GT rays differ"
        )
    n_cls = free_class
    valid = gt.classes != free_class
    pc, gc = pred.classes[valid].astype(np.int64), gt.classes[valid].astype(np.int64)
    with np.errstate(invalid="ignore"):
        err = np.abs(pred.depth_m[valid] - gt.depth_m[valid])  # NaN (pred: no hit) fails every <
    same = pc == gc
    th = settings.thresholds_m
    tp = np.zeros((len(th), n_cls), np.int64)
    for k, t in enumerate(th):
        tp[k] = np.bincount(gc[same & (err < t)], minlength=n_cls)[:n_cls]
    flow_sum, flow_n = np.zeros(n_cls), np.zeros(n_cls, np.int64)
    if pred_flow is not None and gt_flow is not None:
        fp = np.asarray(pred_flow, np.float64).reshape(-1, np.shape(pred_flow)[-1])
        fg = np.asarray(gt_flow, np.float64).reshape(-1, np.shape(gt_flow)[-1])
        ok = same & (err < settings.flow_threshold_m)
        e = np.linalg.norm(fp[pred.index[valid][ok]] - fg[gt.index[valid][ok]], axis=1)
        flow_sum = np.bincount(gc[ok], weights=e, minlength=n_cls)[:n_cls]
        flow_n = np.bincount(gc[ok], minlength=n_cls)[:n_cls]
    return RayCounts(
        tuple(th),
        np.bincount(gc, minlength=n_cls)[:n_cls],
        np.bincount(pc[pc != free_class], minlength=n_cls)[:n_cls],
        tp,
        flow_sum,
        flow_n,
        int(valid.sum()),
    )


def frame_ray_counts(
    pred: np.ndarray,
    gt: np.ndarray,
    origins_m: np.ndarray,
    range_min,
    voxel_size_m: float,
    pred_flow: np.ndarray | None = None,
    gt_flow: np.ndarray | None = None,
    settings: RayIoUSettings = RayIoUSettings(),
    directions: np.ndarray | None = None,
) -> RayCounts:
    """One frame: cast the query rays (``directions``, default :func:`lidar_ray_directions`)
    from ``origins_m`` (:func:`ray_origins`) through ``pred`` and ``gt`` ((X, Y, Z) class ids,
    the full grids) and count (:func:`ray_counts`)."""
    dirs = lidar_ray_directions(settings.azimuth_step_deg) if directions is None else directions
    hits = [cast_rays(g, origins_m, dirs, range_min, voxel_size_m) for g in (pred, gt)]
    return ray_counts(hits[0], hits[1], settings, pred_flow, gt_flow)
