"""The bundled BlazePose models (Bazarevsky et al. 2020; MediaPipe, Apache-2.0).

The ``mediapipe`` wheel ships ``pose_detection.tflite`` and ``pose_landmark_full.tflite``; their
pre- and post-processing are MediaPipe's graphs (``mediapipe/modules/pose_detection/
pose_detection_cpu.pbtxt``, ``pose_landmark/pose_detection_to_roi.pbtxt``,
``pose_landmark_by_roi_cpu.pbtxt``, ``tensors_to_pose_landmarks_and_segmentation.pbtxt``):

- region of interest: the person box of the pipeline's detector gives a square on its centre,
  side max(w, h) x ``box_scale``, upright (MediaPipe's own detector, ``pose_detection.tflite``,
  is not used: the boxes come from the configured detector).
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

from tasks.perception.models.image import (
    apply_affine,
    crop_affine,
    invert_affine,
    paste_back,
    warp_crops,
)
from tasks.perception.models.runner import ModelRunner, expect
from tasks.perception.models.settings import BlazePoseSettings

#: BlazePose landmark index of each COCO-17 keypoint (nose, eyes, ears, shoulders, elbows,
#: wrists, hips, knees, ankles; left before right)
BLAZEPOSE_TO_COCO = (0, 2, 5, 7, 8, 11, 12, 13, 14, 15, 16, 23, 24, 25, 26, 27, 28)
LANDMARK_SIZE = 256
#: MediaPipe's region of interest: the square around the person, 1.25 x its size
ROI_SCALE = 1.25
#: MediaPipe's pose detector merges detections overlapping by more than this (weighted NMS)
DETECTOR_MERGE_IOU = 0.3
REFINE_KERNEL = 7
REFINE_MIN_CONFIDENCE = 0.5


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
