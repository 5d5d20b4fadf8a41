"""The bundled BlazePose models (Bazarevsky et al. 2020; MediaPipe, Apache-2.0).

The ``mediapipe`` wheel ships ``pose_detection.tflite`` and ``pose_landmark_full.tflite``; their
pre- and post-processing are MediaPipe's graphs (``mediapipe/modules/pose_detection/
pose_detection_cpu.pbtxt``, ``pose_landmark/pose_detection_to_roi.pbtxt``,
``pose_landmark_by_roi_cpu.pbtxt``, ``tensors_to_pose_landmarks_and_segmentation.pbtxt``):

- detector: input (1, 224, 224, 3) in [-1, 1], the image letterboxed (centred, zero border);
  outputs raw boxes (1, 2254, 12) and scores (1, 2254, 1) over SSD anchors (5 layers, strides 8,
  16, 32, 32, 32, fixed size, two anchors per cell and layer); values decode as anchor centre +
  raw / 224: box (cx, cy, w, h) (the face) and 4 keypoints (mid-hip, a point whose distance from
  it gives the body's size and whose direction its rotation, then two upper-body points); score =
  sigmoid(clip(raw, +-100)); kept over ``min_score``; weighted NMS (IoU 0.3: overlapping
  detections average their coordinates, weighted by score).
- region of interest: a square centred on the mid-hip, side 2 |kp1 - kp0| x 1.25, rotated so
  that kp0 -> kp1 points up. A box from another detector gives a square on its centre, side
  max(w, h) x ``box_scale``, upright.
- landmarks: the region warped to (1, 256, 256, 3) in [0, 1]; outputs landmarks (1, 195) = 39 x
  (x, y, z, visibility, presence) in crop pixels, a pose flag (1, 1) in [0, 1], segmentation
  logits (1, 256, 256, 1), heatmaps (1, 64, 64, 39), world landmarks. Each landmark is refined
  by the sigmoid-weighted mean position over a 7 x 7 heatmap window where that window's maximum
  reaches 0.5; visibility = sigmoid. Pose flag < 0.5: no pose in the region.
- COCO-17 from the 33 landmarks (:data:`BLAZEPOSE_TO_COCO`); confidence = visibility (0 where
  no pose); mask = sigmoid(segmentation) > 0.5 brought back to the image, inside the box.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import expit

from tasks.geometry import box_iou
from tasks.perception.models.detector import Detections
from tasks.perception.models.image import (
    apply_affine,
    crop_affine,
    invert_affine,
    letterbox,
    paste_back,
    warp_crops,
)
from tasks.perception.models.runner import ModelRunner, expect
from tasks.perception.models.settings import BlazePoseSettings

#: BlazePose landmark index of each COCO-17 keypoint (nose, eyes, ears, shoulders, elbows,
#: wrists, hips, knees, ankles; left before right)
BLAZEPOSE_TO_COCO = (0, 2, 5, 7, 8, 11, 12, 13, 14, 15, 16, 23, 24, 25, 26, 27, 28)
DETECTOR_SIZE = 224
LANDMARK_SIZE = 256
NUM_ANCHORS = 2254
ROI_SCALE = 1.25
#: MediaPipe's pose detector merges detections overlapping by more than this (weighted NMS)
DETECTOR_MERGE_IOU = 0.3
REFINE_KERNEL = 7
REFINE_MIN_CONFIDENCE = 0.5


def ssd_anchors(size: int = DETECTOR_SIZE, strides=(8, 16, 32, 32, 32)) -> np.ndarray:
    """Anchor centres (A, 2) normalised (x, y) of MediaPipe's SsdAnchorsCalculator with fixed
    anchor size: consecutive layers of equal stride share a grid; each layer adds two anchors per
    cell (aspect ratio 1 and the interpolated scale), row-major over the grid."""
    out = []
    i = 0
    while i < len(strides):
        j = i
        while j < len(strides) and strides[j] == strides[i]:
            j += 1
        fm = int(np.ceil(size / strides[i]))
        y, x = np.mgrid[0:fm, 0:fm]
        centres = np.stack([(x.ravel() + 0.5) / fm, (y.ravel() + 0.5) / fm], 1)
        out.append(np.repeat(centres, 2 * (j - i), axis=0))
        i = j
    return np.concatenate(out)


def decode_detections(
    raw_boxes: np.ndarray, raw_scores: np.ndarray, anchors: np.ndarray, min_score: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw detector outputs (A, 12), (A, 1) -> boxes (N, 4) normalised xyxy, keypoints (N, 4, 2)
    normalised, scores (N,) for the anchors scoring >= min_score (normalised to the 224 input)."""
    raw = np.asarray(raw_boxes, np.float64) / DETECTOR_SIZE
    score = expit(np.clip(np.asarray(raw_scores, np.float64)[:, 0], -100, 100))
    keep = score >= min_score
    raw, score, a = raw[keep], score[keep], anchors[keep]
    c = a + raw[:, :2]
    wh = raw[:, 2:4]
    boxes = np.concatenate([c - wh / 2, c + wh / 2], 1)
    kps = a[:, None, :] + raw[:, 4:12].reshape(-1, 4, 2)
    return boxes, kps, score


def weighted_nms(
    boxes: np.ndarray,
    keypoints: np.ndarray,
    scores: np.ndarray,
    merge_iou: float = DETECTOR_MERGE_IOU,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """MediaPipe's WEIGHTED non-max suppression: the best remaining detection gathers every
    remaining one overlapping it by IoU > merge_iou (itself included); their boxes and
    keypoints are averaged with the scores as weights, the score is the best one's."""
    order = list(np.argsort(-scores, kind="stable"))
    out_b, out_k, out_s = [], [], []
    iou = box_iou(boxes, boxes)
    while order:
        top = order[0]
        group = [i for i in order if i == top or iou[top, i] > merge_iou]
        w = scores[group][:, None]
        out_b.append((boxes[group] * w).sum(0) / w.sum())
        out_k.append((keypoints[group] * w[:, :, None]).sum(0) / w.sum())
        out_s.append(scores[top])
        order = [i for i in order if i not in group]
    if not out_s:
        return np.zeros((0, 4)), np.zeros((0, 4, 2)), np.zeros(0)
    return np.array(out_b), np.array(out_k), np.array(out_s)


@dataclass(frozen=True)
class Regions:
    """Square regions of interest: centre (N, 2) px, side (N,) px, rotation (N,) rad."""

    center: np.ndarray
    side: np.ndarray
    rotation: np.ndarray

    def affine(self, size: int = LANDMARK_SIZE) -> np.ndarray:
        """Maps (N, 2, 3) image -> crop pixels, the region's edges on the crop's pixel corners
        (MediaPipe's ImageToTensor)."""
        A = crop_affine(
            self.center, np.stack([self.side, self.side], 1), (size, size), self.rotation, udp=False
        )
        A[:, :, 2] -= 0.5
        return A


def regions_from_keypoints(kp0: np.ndarray, kp1: np.ndarray, scale: float = ROI_SCALE) -> Regions:
    """MediaPipe's AlignmentPointsRects + RectTransformation: kp0 (N, 2) mid-hip, kp1 (N, 2) the
    size / rotation point, image px."""
    d = np.asarray(kp1, np.float64) - np.asarray(kp0, np.float64)
    side = 2 * np.hypot(d[:, 0], d[:, 1]) * scale
    rotation = np.pi / 2 - np.arctan2(-d[:, 1], d[:, 0])
    rotation = (rotation + np.pi) % (2 * np.pi) - np.pi
    return Regions(np.asarray(kp0, np.float64), side, rotation)


def regions_from_boxes(boxes_xyxy: np.ndarray, scale: float) -> Regions:
    """Upright squares on box centres, side max(w, h) x scale."""
    b = np.asarray(boxes_xyxy, np.float64).reshape(-1, 4)
    return Regions(
        (b[:, :2] + b[:, 2:]) / 2,
        np.maximum(b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]) * scale,
        np.zeros(len(b)),
    )


def refine_from_heatmap(
    xy_norm: np.ndarray,
    heatmap: np.ndarray,
    kernel: int = REFINE_KERNEL,
    min_confidence: float = REFINE_MIN_CONFIDENCE,
) -> np.ndarray:
    """MediaPipe's RefineLandmarksFromHeatmap: landmarks (L, 2) normalised to the crop, heatmap
    logits (h, w, L). Each landmark inside the heatmap moves to the sigmoid-weighted mean cell
    (cell index / size) of the ``kernel`` window around its cell, where the window's largest
    sigmoid reaches ``min_confidence``."""
    h, w, L = heatmap.shape
    out = np.array(xy_norm, np.float64)
    conf = expit(np.asarray(heatmap, np.float64))
    r = (kernel - 1) // 2
    for i in range(min(L, len(out))):
        col, row = int(out[i, 0] * w), int(out[i, 1] * h)
        if not (0 <= col < w and 0 <= row < h):
            continue
        win = conf[max(row - r, 0) : min(row + r + 1, h), max(col - r, 0) : min(col + r + 1, w), i]
        if win.max() < min_confidence or win.sum() <= 0:
            continue
        rows, cols = np.mgrid[
            max(row - r, 0) : min(row + r + 1, h), max(col - r, 0) : min(col + r + 1, w)
        ]
        out[i] = [(cols * win).sum() / win.sum() / w, (rows * win).sum() / win.sum() / h]
    return out


class BlazePoseDetector:
    """MediaPipe's pose detector on a whole image (module docstring). Boxes: the region of
    interest's axis-aligned bounds clipped to the image; :attr:`last_regions` keeps the regions."""

    def __init__(
        self, runner: ModelRunner, min_score: float = 0.5, merge_iou: float = DETECTOR_MERGE_IOU
    ):
        expect(
            runner,
            "BlazePose detector",
            {"*": (1, DETECTOR_SIZE, DETECTOR_SIZE, 3)},
            {"*": (1, NUM_ANCHORS, 12), "**": (1, NUM_ANCHORS, 1)},
        )
        self.runner, self.min_score, self.merge_iou = runner, min_score, merge_iou
        self.input = next(iter(runner.input_shapes))
        self.anchors = ssd_anchors()

    def regions(self, image: np.ndarray) -> tuple[Regions, np.ndarray]:
        """Regions of interest of the detected persons and their scores (N,)."""
        x, lb = letterbox(image, DETECTOR_SIZE, DETECTOR_SIZE, 0.0, center=True)
        out = list(self.runner({self.input: (x / 127.5 - 1.0)[None].astype(np.float32)}).values())
        raw_boxes, raw_scores = sorted(out, key=lambda a: -a.shape[-1])
        boxes, kps, scores = decode_detections(
            raw_boxes[0], raw_scores[0], self.anchors, self.min_score
        )
        _, kps, scores = weighted_nms(boxes, kps, scores, self.merge_iou)
        px = lb.to_image(kps * DETECTOR_SIZE) - 0.5  # input pixel corners -> image, OpenCV pixels
        return regions_from_keypoints(px[:, 0], px[:, 1]), scores

    def __call__(self, image: np.ndarray) -> Detections:
        reg, scores = self.regions(image)
        self.last_regions = reg
        if len(scores) == 0:
            return Detections.empty()
        H, W = image.shape[:2]
        corners = apply_affine(
            invert_affine(reg.affine()),
            np.array([[[-0.5, -0.5], [255.5, -0.5], [255.5, 255.5], [-0.5, 255.5]]] * len(scores)),
        )
        boxes = np.concatenate([corners.min(1), corners.max(1)], 1)
        boxes = np.clip(boxes, 0, [W - 1, H - 1, W - 1, H - 1])
        return Detections(boxes.astype(np.float32), scores.astype(np.float32))


class BlazePoseLandmarks:
    """COCO-17 keypoints and person masks from MediaPipe's landmark model (module docstring).
    settings: the region around a box (``box_scale``) and the pose flag a box needs
    (``min_pose_flag``, applied by :class:`tasks.perception.models.composite.ModelPerception`)."""

    def __init__(
        self,
        runner: ModelRunner,
        settings: BlazePoseSettings,
        mask_threshold: float = 0.5,
        refine: bool = True,
    ):
        expect(runner, "BlazePose landmark", {"*": (1, LANDMARK_SIZE, LANDMARK_SIZE, 3)}, 5)
        shapes = [tuple(s) for s in runner.output_shapes.values()]
        need = [(1, 195), (1, 1), (1, LANDMARK_SIZE, LANDMARK_SIZE, 1), (1, 64, 64, 39)]
        if any(n not in shapes for n in need):
            raise ValueError(
                f"{runner.source}: not a BlazePose landmark model: outputs {dict(runner.output_shapes)}, "
                f"expected among them {need}"
            )
        self.runner, self.settings, self.mask_threshold, self.refine = (
            runner,
            settings,
            mask_threshold,
            refine,
        )
        self.input = next(iter(runner.input_shapes))
        self.names = {
            s: next(n for n, t in runner.output_shapes.items() if tuple(t) == s) for s in need
        }

    def __call__(
        self, image: np.ndarray, boxes_xyxy: np.ndarray, regions: Regions | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Keypoints (D, 17, 3) float32, masks (D, H, W) bool and pose flags (D,) float32 in
        [0, 1] of boxes (D, 4); ``regions`` (from the BlazePose detector) replaces the regions
        made from the boxes."""
        H, W = image.shape[:2]
        boxes = np.asarray(boxes_xyxy, np.float64).reshape(-1, 4)
        D = len(boxes)
        reg = regions if regions is not None else regions_from_boxes(boxes, self.settings.box_scale)
        A = reg.affine()
        crops = warp_crops(image, A, (LANDMARK_SIZE, LANDMARK_SIZE)) / 255.0
        kp = np.zeros((D, 17, 3), np.float32)
        seg = np.zeros((D, LANDMARK_SIZE, LANDMARK_SIZE), np.float32)
        flag = np.zeros(D, np.float32)
        n = self.names
        for d in range(D):
            out = self.runner({self.input: crops[d : d + 1].astype(np.float32)})
            lm = out[n[(1, 195)]].reshape(39, 5).astype(np.float64)
            xy = lm[:, :2] / LANDMARK_SIZE
            if self.refine:
                xy = refine_from_heatmap(xy, out[n[(1, 64, 64, 39)]][0])
            flag[d] = float(out[n[(1, 1)]].ravel()[0])
            present = flag[d] >= 0.5
            uv = apply_affine(invert_affine(A[d : d + 1]), (xy * LANDMARK_SIZE - 0.5)[None])[0]
            vis = expit(lm[:, 3])
            idx = list(BLAZEPOSE_TO_COCO)
            kp[d, :, :2] = uv[idx]
            kp[d, :, 2] = vis[idx] * present
            seg[d] = expit(out[n[(1, LANDMARK_SIZE, LANDMARK_SIZE, 1)]][0, :, :, 0])
        if D == 0:
            return kp, np.zeros((0, H, W), bool), flag
        probs = paste_back(seg, A, H, W, region_xyxy=boxes)
        return kp, probs > self.mask_threshold, flag
