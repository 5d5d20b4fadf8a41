"""What a perception provider returns for one frame, and the provider interface.

Conventions are those of :mod:`tasks.conventions`. Pixels ``(u, v)``: u to the right, v down,
origin at the top-left corner of the top-left pixel (a pixel ``(c, r)`` covers
``[c, c + 1) x [r, r + 1)``). An empty frame has ``D = 0`` / ``M = 0`` and empty arrays, never None.

Instance masks are ``(D, H, W) bool``, one per detection, aligned with ``boxes_xyxy``; a detection
whose provider gives no mask has an all-False mask (consumers then fall back to the box).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

NUM_KEYPOINTS = 17


def _check(name: str, array: np.ndarray, shape: tuple[int | None, ...], dtype: type) -> None:
    if not isinstance(array, np.ndarray) or array.dtype != np.dtype(dtype):
        got = getattr(array, "dtype", type(array).__name__)
        raise ValueError(f"{name}: expected a numpy array of dtype {np.dtype(dtype)}, got {got}")
    if array.ndim != len(shape) or any(
        s is not None and s != a for s, a in zip(shape, array.shape)
    ):
        raise ValueError(f"{name}: expected shape {shape} (None = any), got {array.shape}")


@dataclass(frozen=True)
class ImagePerception:
    """2D perception of one camera image.

    boxes_xyxy: (D, 4) float32 pixels (u_min, v_min, u_max, v_max).
    scores: (D,) float32 in [0, 1].
    keypoints: (D, 17, 3) float32, COCO-17 order, (u, v) pixels and a confidence in [0, 1].
    masks: (D, H, W) bool instance masks aligned with the boxes (all False = no mask).
    semantic: (H, W) uint8 Cityscapes train ids (255 = ignore / not available).
    """

    boxes_xyxy: np.ndarray
    scores: np.ndarray
    keypoints: np.ndarray
    masks: np.ndarray
    semantic: np.ndarray

    def __post_init__(self) -> None:
        _check("semantic", self.semantic, (None, None), np.uint8)
        height, width = self.semantic.shape
        _check("boxes_xyxy", self.boxes_xyxy, (None, 4), np.float32)
        count = self.boxes_xyxy.shape[0]
        _check("scores", self.scores, (count,), np.float32)
        _check("keypoints", self.keypoints, (count, NUM_KEYPOINTS, 3), np.float32)
        _check("masks", self.masks, (count, height, width), np.bool_)

    def __len__(self) -> int:
        return int(self.boxes_xyxy.shape[0])

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return int(self.semantic.shape[1]), int(self.semantic.shape[0])

    @staticmethod
    def empty(width: int, height: int) -> ImagePerception:
        """No detections; semantic all ignore (255)."""
        return ImagePerception(
            boxes_xyxy=np.zeros((0, 4), np.float32),
            scores=np.zeros(0, np.float32),
            keypoints=np.zeros((0, NUM_KEYPOINTS, 3), np.float32),
            masks=np.zeros((0, height, width), bool),
            semantic=np.full((height, width), 255, np.uint8),
        )


@dataclass(frozen=True)
class LidarDetections:
    """3D pedestrian boxes of one LiDAR sweep, in the LiDAR frame.

    centers: (M, 3) float32 metres (box centre). sizes: (M, 3) float32 metres (l, w, h), l along
    the box x axis after rotating by yaw about +z. yaws: (M,) float32 radians. scores: (M,) float32.
    """

    centers: np.ndarray
    sizes: np.ndarray
    yaws: np.ndarray
    scores: np.ndarray

    def __post_init__(self) -> None:
        _check("centers", self.centers, (None, 3), np.float32)
        count = self.centers.shape[0]
        _check("sizes", self.sizes, (count, 3), np.float32)
        _check("yaws", self.yaws, (count,), np.float32)
        _check("scores", self.scores, (count,), np.float32)

    def __len__(self) -> int:
        return int(self.centers.shape[0])

    @staticmethod
    def empty() -> LidarDetections:
        return LidarDetections(
            centers=np.zeros((0, 3), np.float32),
            sizes=np.zeros((0, 3), np.float32),
            yaws=np.zeros(0, np.float32),
            scores=np.zeros(0, np.float32),
        )


def box_corners(centers: np.ndarray, sizes: np.ndarray, yaws: np.ndarray) -> np.ndarray:
    """Corners of yawed 3D boxes.

    centers, sizes: (M, 3); yaws: (M,) radians about +z. Returns (M, 8, 3) float64, same frame.
    """
    signs = np.array(
        [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64
    )
    local = signs[None] * 0.5 * np.asarray(sizes, np.float64)[:, None, :]
    cos, sin = np.cos(yaws).astype(np.float64), np.sin(yaws).astype(np.float64)
    x = cos[:, None] * local[..., 0] - sin[:, None] * local[..., 1]
    y = sin[:, None] * local[..., 0] + cos[:, None] * local[..., 1]
    rotated = np.stack([x, y, local[..., 2]], axis=-1)
    return rotated + np.asarray(centers, np.float64)[:, None, :]
