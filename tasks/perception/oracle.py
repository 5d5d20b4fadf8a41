"""The ``oracle`` perception provider: detections derived from ground truth with realistic noise.

For synthetic sequences only (the simulator writes the ground-truth arrays). Every random draw
comes from the ``np.random.Generator`` the caller passes, so a (seed, frame) pair gives the same
detections on every worker.

Noise model (all parameters in :class:`OracleNoise`):

- misses: p_detect = recall * (1 - occlusion_miss * (1 - f_vis)^occlusion_power)
  * (1 - distance_miss * ramp(d)), ramp going 0 -> 1 between ``near_m`` and ``far_m``; persons with
  f_vis < ``min_visible_fraction`` are never detected. ``recall`` is ``day_recall`` (0.99) or
  ``night_recall`` (0.77), the paper's detection-robustness table (day recall ~99 %, night 76.9 %,
  precision 97.6-100 %; its recall is T / (T + M_vis), visible persons only).
  Calibration (defaults): the paper's crowded row misses 6 visible persons in 486 (1.2 %) and as
  many occluded ones, so a partly hidden person is still found most of the time and misses pile up
  only when little of the body shows: occlusion_miss 0.9, occlusion_power 6 give p ~ 0.97 at
  f_vis 0.5, 0.89 at 0.3, 0.52 at 0.1, 0.34 at 0.05 (times ``recall``); distance_miss 0.1 (10 %
  fewer hits at 40 m). Over our synthetic crowded day sequences this gives T / (T + M_vis) ~ 98 %
  (paper 98.8), uncrowded ~ 99 % (99.5), crowded night ~ 78 % (76.9). The earlier setting
  (0.6, power 2, distance 0.3) gave 94.4 % crowded: a 50 %-visible person was missed 15 % of the
  time. Our ground truth counts every person with any visible pixel, so M_occ stays well above
  the paper's (people under 5 % visible are never detected, and manual QA would not count them).
- false positives: Poisson(``fp_per_frame``) boxes of person-like aspect, scores U(fp_score_range),
  an ellipse mask, random low-confidence keypoints.
- box jitter: Gaussian on each edge, std ``box_jitter`` x box size.
- keypoints: Gaussian pixel noise, std ``keypoint_sigma`` x box height; confidences U(0.7, 1) for
  visible joints (v = 2), U(0.1, 0.5) for occluded (v = 1), U(0, 0.15) for unlabeled (v = 0).
- masks: the person's pixels in the instance image, each boundary pixel (dilation minus erosion)
  flipped with probability ``mask_flip_prob``.
- semantics: Poisson(``semantic_patches``) rectangles set to a random Cityscapes train id.
- night also scales false positives and semantic patches by ``night_noise_scale``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from tasks.bounds import NonNegative, Positive, Probability
from tasks.perception.types import NUM_KEYPOINTS, ImagePerception, LidarDetections

_VALID_TRAIN_IDS = np.arange(19, dtype=np.uint8)


@dataclass(frozen=True)
class OracleNoise:
    """Plain parameters of the oracle noise model (see the module docstring)."""

    day_recall: Probability = 0.99
    night_recall: Probability = 0.77
    occlusion_miss: Probability = 0.9
    occlusion_power: Positive = 6.0
    min_visible_fraction: Probability = 0.05
    distance_miss: Probability = 0.1
    near_m: Positive = 10.0
    far_m: Positive = 40.0
    fp_per_frame: NonNegative = 0.02
    fp_score_range: tuple[float, float] = (0.3, 0.75)
    box_jitter: NonNegative = 0.03
    keypoint_sigma: NonNegative = 0.01
    mask_flip_prob: Probability = 0.3
    semantic_patches: NonNegative = 3.0
    semantic_patch_px: tuple[int, int] = (8, 48)
    night_noise_scale: NonNegative = 2.0
    lidar_recall: Probability = 0.97
    lidar_far_m: Positive = 40.0
    lidar_center_sigma_m: NonNegative = 0.05
    lidar_size_sigma_m: NonNegative = 0.05
    lidar_yaw_sigma_rad: NonNegative = 0.1


def detection_probability(
    visible_fraction: np.ndarray, distance_m: np.ndarray, night: bool, noise: OracleNoise
) -> np.ndarray:
    """Probability that the 2D detector finds each person.

    visible_fraction: (P,) float in [0, 1], visible pixels / all pixels of the person.
    distance_m: (P,) float metres from the camera. Returns (P,) float64 in [0, 1].
    """
    visible = np.clip(np.asarray(visible_fraction, np.float64), 0.0, 1.0)
    distance = np.asarray(distance_m, np.float64)
    recall = noise.night_recall if night else noise.day_recall
    ramp = np.clip((distance - noise.near_m) / max(noise.far_m - noise.near_m, 1e-9), 0.0, 1.0)
    p = (
        recall
        * (1.0 - noise.occlusion_miss * (1.0 - visible) ** noise.occlusion_power)
        * (1.0 - noise.distance_miss * ramp)
    )
    return np.where(visible < noise.min_visible_fraction, 0.0, np.clip(p, 0.0, 1.0))


def _noisy_mask(
    instance_image: np.ndarray,
    track_id: int,
    box: np.ndarray,
    flip_prob: float,
    rng: np.random.Generator,
) -> np.ndarray:
    height, width = instance_image.shape
    mask = np.zeros((height, width), bool)
    u0, v0 = max(int(np.floor(box[0])) - 2, 0), max(int(np.floor(box[1])) - 2, 0)
    u1, v1 = min(int(np.ceil(box[2])) + 3, width), min(int(np.ceil(box[3])) + 3, height)
    if u1 <= u0 or v1 <= v0:
        return mask
    crop = instance_image[v0:v1, u0:u1] == track_id
    if flip_prob > 0 and crop.any():
        band = ndimage.binary_dilation(crop) & ~ndimage.binary_erosion(crop)
        flips = band & (rng.random(crop.shape) < flip_prob)
        crop = crop ^ flips
    mask[v0:v1, u0:u1] = crop
    return mask


def _noisy_semantic(
    semantic: np.ndarray, patches: float, patch_px: tuple[int, int], rng: np.random.Generator
) -> np.ndarray:
    out = semantic.copy()
    height, width = out.shape
    for _ in range(rng.poisson(patches)):
        ph, pw = rng.integers(patch_px[0], patch_px[1] + 1, size=2)
        v0, u0 = rng.integers(0, max(height - ph, 1)), rng.integers(0, max(width - pw, 1))
        out[v0 : v0 + ph, u0 : u0 + pw] = rng.choice(_VALID_TRAIN_IDS)
    return out


def oracle_image_perception(
    gt_boxes_xyxy: np.ndarray,
    gt_keypoints: np.ndarray,
    visible_fraction: np.ndarray,
    distance_m: np.ndarray,
    gt_track_ids: np.ndarray,
    instance_image: np.ndarray,
    semantic_image: np.ndarray,
    rng: np.random.Generator,
    night: bool = False,
    noise: OracleNoise = OracleNoise(),
) -> tuple[ImagePerception, np.ndarray]:
    """Noisy 2D perception of one frame from its ground truth.

    gt_boxes_xyxy: (P, 4) float pixels. gt_keypoints: (P, 17, 3) float (u, v) pixels and COCO
    visibility 0 / 1 / 2 (NaN (u, v) allowed: placed at the box centre with a low confidence). visible_fraction: (P,) float in [0, 1]. distance_m: (P,) float metres.
    gt_track_ids: (P,) int, the id of each person in ``instance_image``. instance_image: (H, W)
    uint16 track ids (0 = no person). semantic_image: (H, W) uint8 Cityscapes train ids.
    Returns (perception, gt_index): detections sorted by descending score; gt_index (D,) int64 the
    ground-truth row of each detection, -1 for a false positive.
    """
    boxes_gt = np.asarray(gt_boxes_xyxy, np.float64).reshape(-1, 4)
    count = boxes_gt.shape[0]
    keypoints_gt = np.asarray(gt_keypoints, np.float64).reshape(count, NUM_KEYPOINTS, 3)
    visible = np.asarray(visible_fraction, np.float64).reshape(count)
    track_ids = np.asarray(gt_track_ids).reshape(count)
    semantic = np.asarray(semantic_image)
    if semantic.dtype != np.uint8 or semantic.ndim != 2:
        raise ValueError(
            f"semantic_image: expected (H, W) uint8, got {semantic.shape} {semantic.dtype}"
        )
    if instance_image.shape != semantic.shape:
        raise ValueError(
            f"instance_image {instance_image.shape} != semantic_image {semantic.shape}"
        )
    height, width = semantic.shape
    scale = noise.night_noise_scale if night else 1.0

    detected = rng.random(count) < detection_probability(visible, distance_m, night, noise)
    # a person with no box in this image (NaN: outside the view) cannot be detected, whatever the
    # noise settings (regression: min_visible_fraction 0 crashed on NaN boxes)
    detected &= np.isfinite(boxes_gt).all(axis=1)
    boxes, scores, keypoints, masks, gt_index = [], [], [], [], []
    for p in np.flatnonzero(detected):
        box = boxes_gt[p]
        size = np.array([box[2] - box[0], box[3] - box[1]] * 2)
        noisy = box + rng.normal(0.0, noise.box_jitter, 4) * size
        noisy = np.clip(noisy, [0, 0, 0, 0], [width, height, width, height])
        if noisy[2] - noisy[0] < 1 or noisy[3] - noisy[1] < 1:
            continue
        score = np.clip(0.97 - 0.3 * (1 - visible[p]) + rng.normal(0, 0.02), 0.05, 1.0)
        vis = np.nan_to_num(keypoints_gt[p, :, 2])
        kp = np.empty((NUM_KEYPOINTS, 3))
        kp[:, :2] = keypoints_gt[p, :, :2] + rng.normal(
            0, noise.keypoint_sigma * size[1], (NUM_KEYPOINTS, 2)
        )
        unknown = ~np.isfinite(kp[:, :2]).all(axis=1)  # GT without a projection: box centre, v = 0
        kp[unknown, :2] = (noisy[:2] + noisy[2:]) / 2
        vis = np.where(unknown, 0.0, vis)
        kp[:, 2] = np.where(
            vis >= 2,
            rng.uniform(0.7, 1.0, NUM_KEYPOINTS),
            np.where(
                vis >= 1,
                rng.uniform(0.1, 0.5, NUM_KEYPOINTS),
                rng.uniform(0.0, 0.15, NUM_KEYPOINTS),
            ),
        )
        boxes.append(noisy)
        scores.append(score)
        keypoints.append(kp)
        masks.append(_noisy_mask(instance_image, int(track_ids[p]), box, noise.mask_flip_prob, rng))
        gt_index.append(p)

    for _ in range(rng.poisson(noise.fp_per_frame * scale)):
        box_h = rng.uniform(40.0, max(min(300.0, height * 0.9), 41.0))
        box_w = box_h * rng.uniform(0.3, 0.5)
        u0 = rng.uniform(0, max(width - box_w, 1.0))
        v0 = rng.uniform(0, max(height - box_h, 1.0))
        box = np.array([u0, v0, min(u0 + box_w, width), min(v0 + box_h, height)])
        vv, uu = np.mgrid[0:height, 0:width]
        centre, half = (box[:2] + box[2:]) / 2, np.maximum((box[2:] - box[:2]) / 2, 0.5)
        mask = ((uu + 0.5 - centre[0]) / half[0]) ** 2 + (
            (vv + 0.5 - centre[1]) / half[1]
        ) ** 2 <= 1
        kp = np.empty((NUM_KEYPOINTS, 3))
        kp[:, 0] = rng.uniform(box[0], box[2], NUM_KEYPOINTS)
        kp[:, 1] = rng.uniform(box[1], box[3], NUM_KEYPOINTS)
        kp[:, 2] = rng.uniform(0.0, 0.4, NUM_KEYPOINTS)
        boxes.append(box)
        scores.append(rng.uniform(*noise.fp_score_range))
        keypoints.append(kp)
        masks.append(mask)
        gt_index.append(-1)

    order = np.argsort(-np.asarray(scores, np.float64), kind="stable")
    detections = ImagePerception(
        boxes_xyxy=np.asarray(boxes, np.float32).reshape(-1, 4)[order],
        scores=np.asarray(scores, np.float32).reshape(-1)[order],
        keypoints=np.asarray(keypoints, np.float32).reshape(-1, NUM_KEYPOINTS, 3)[order],
        masks=np.asarray(masks, bool).reshape(-1, height, width)[order],
        semantic=_noisy_semantic(
            semantic, noise.semantic_patches * scale, noise.semantic_patch_px, rng
        ),
    )
    return detections, np.asarray(gt_index, np.int64)[order]


def oracle_lidar_detections(
    gt_centers: np.ndarray,
    gt_sizes: np.ndarray,
    gt_yaws: np.ndarray,
    num_points: np.ndarray,
    rng: np.random.Generator,
    noise: OracleNoise = OracleNoise(),
    min_returns: int = 5,
) -> tuple[LidarDetections, np.ndarray]:
    """Noisy LiDAR pedestrian boxes from ground-truth boxes (LiDAR frame; lighting does not matter).

    gt_centers, gt_sizes: (M, 3) float metres (l, w, h); gt_yaws: (M,) radians; num_points: (M,)
    int LiDAR points inside each box (boxes with fewer than ``min_returns`` are never detected: the oracle's own visibility,
    not a setting).
    Returns (detections, gt_index (K,) int64 row of each detection).
    """
    centers = np.asarray(gt_centers, np.float64).reshape(-1, 3)
    count = centers.shape[0]
    sizes = np.asarray(gt_sizes, np.float64).reshape(count, 3)
    yaws = np.asarray(gt_yaws, np.float64).reshape(count)
    distance = np.linalg.norm(centers[:, :2], axis=1)
    p = noise.lidar_recall * np.clip(1.0 - distance / noise.lidar_far_m, 0.0, 1.0) ** 0.25
    p = np.where(np.asarray(num_points).reshape(count) < min_returns, 0.0, p)
    keep = np.flatnonzero(rng.random(count) < p)
    k = keep.size
    out = LidarDetections(
        centers=(centers[keep] + rng.normal(0, noise.lidar_center_sigma_m, (k, 3))).astype(
            np.float32
        ),
        sizes=np.maximum(
            sizes[keep] + rng.normal(0, noise.lidar_size_sigma_m, (k, 3)), 0.05
        ).astype(np.float32),
        yaws=(yaws[keep] + rng.normal(0, noise.lidar_yaw_sigma_rad, k)).astype(np.float32),
        scores=np.clip(rng.uniform(0.6, 1.0, k), 0, 1).astype(np.float32),
    )
    return out, keep.astype(np.int64)
