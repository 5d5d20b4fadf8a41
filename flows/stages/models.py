"""Real networks from local files, built once per process from the stage inputs: the composite of
``detect.models`` (image_provider 'models') and the CLIFF estimator (init_provider 'cliff').

Runners (storage/network_files.py) are opened once per file and device and reused across frames
and batches; the adapters and the composite live in tasks/perception/models/.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from configs.schema import ModelsConfig
from storage.network_files import bundled_model, open_onnx, open_tflite
from tasks.geometry import match_boxes
from tasks.perception.models.blazepose import BlazePoseLandmarks
from tasks.perception.models.cliff import CliffEstimator
from tasks.perception.models.composite import ModelPerception
from tasks.perception.models.detector import DecodedBoxesDetector, Detections, YoloxDetector
from tasks.perception.models.keypoints import TopDownKeypoints
from tasks.perception.models.proposals import project_lidar_boxes
from tasks.perception.models.segmentation import QueryInstanceMasks, SemanticSegmenter
from tasks.perception.models.settings import (
    BlazePoseSettings,
    DetectorSettings,
    KeypointSettings,
    MaskSettings,
    SemanticSettings,
)
from tasks.perception.types import LidarDetections

#: 2D IoU for a model detection to take a ground-truth person's identity (synthetic data)
GT_MATCH_IOU = 0.5


@functools.lru_cache(maxsize=16)
def _onnx(path: str, device: str):
    return open_onnx(path, device)


@functools.lru_cache(maxsize=4)
def _tflite(path: str):
    return open_tflite(path)


@functools.lru_cache(maxsize=4)
def model_perception(m: ModelsConfig) -> ModelPerception:
    """The composite of a ``detect.models`` section (frozen, hashable: cached per process)."""
    onnx = lambda p: _onnx(str(p), m.device)  # noqa: E731 - a local shorthand
    d, k, s, mk = m.detector, m.keypoints, m.semantic, m.masks
    detector = None
    if d.kind == "yolox":
        detector = YoloxDetector(onnx(d.path), d.to(DetectorSettings))
    elif d.kind == "decoded-boxes":
        detector = DecodedBoxesDetector(onnx(d.path), d.to(DetectorSettings))
    keypoints = (
        TopDownKeypoints(onnx(k.path), k.to(KeypointSettings))
        if k.kind in ("vitpose", "rtmpose")
        else None
    )
    blaze = (
        BlazePoseLandmarks(
            _tflite(str(bundled_model(m.bundled_dir, "pose_landmark_full.tflite"))),
            m.to(BlazePoseSettings),
        )
        if k.kind == "blazepose"
        else None
    )
    masks = (
        QueryInstanceMasks(onnx(mk.path), mk.to(MaskSettings)) if mk.kind == "mask2former" else None
    )
    semantic = SemanticSegmenter(onnx(s.path), s.to(SemanticSettings)) if s.kind == "onnx" else None
    source = {
        "mask2former": "masks",
        "blazepose": "blazepose",
        "semantic": "semantic",
        "none": "none",
    }[mk.kind]
    return ModelPerception(
        detector=detector,
        keypoints=keypoints,
        masks=masks,
        semantic=semantic,
        blazepose=blaze,
        mask_source=source,
    )


def lidar_proposals(lidar: LidarDetections, cam) -> Detections:
    """The LiDAR pedestrian boxes of a frame projected into the camera, score 1 (the image
    model's pose flag then scores them)."""
    boxes, _ = project_lidar_boxes(
        lidar.centers, lidar.sizes, lidar.yaws, cam.T_cam_from_lidar, cam.K, cam.width, cam.height
    )
    return Detections(boxes, np.ones(len(boxes), np.float32))


def gt_index_by_boxes(boxes_xyxy: np.ndarray, gt_box2d: np.ndarray) -> np.ndarray:
    """Synthetic data: the ground-truth person of each detection (Hungarian on 2D IoU >= 0.5,
    -1 unmatched), so the oracle's initial bodies can start the fit of model detections."""
    out = np.full(len(boxes_xyxy), -1, np.int64)
    finite = np.flatnonzero(np.all(np.isfinite(gt_box2d), axis=1))
    gi, di = match_boxes(gt_box2d[finite], boxes_xyxy, GT_MATCH_IOU)
    out[di] = finite[gi]
    return out


@functools.lru_cache(maxsize=2)
def cliff_estimator(path: str, device: str) -> CliffEstimator:
    return CliffEstimator(_onnx(str(Path(path)), device))
