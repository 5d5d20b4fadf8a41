"""Build the real-model providers from the config: image_provider 'models' and init_provider
'cliff'. Runners are opened once per process (per file and device) and reused across frames."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from configs.schema import Config, ModelsConfig
from flows.parallel import fan_out
from flows.plan import open_sequence
from storage.images import read_rgb
from storage.model_files import bundled_model, open_onnx, open_tflite
from tasks.fit.init_oracle import BodyParams
from tasks.metrics.detection import match_boxes
from tasks.perception.models.blazepose import BlazePoseLandmarks
from tasks.perception.models.cliff import CliffEstimator
from tasks.perception.models.composite import ModelPerception
from tasks.perception.models.detector import DecodedBoxesDetector, Detections, YoloxDetector
from tasks.perception.models.keypoints import TopDownKeypoints
from tasks.perception.models.proposals import project_lidar_boxes
from tasks.perception.models.segmentation import QueryInstanceMasks, SemanticSegmenter


#: 2D IoU for a model detection to take a ground-truth person's identity (synthetic data)
GT_MATCH_IOU = 0.5


@functools.lru_cache(maxsize=16)
def _onnx(path: str, device: str):
    return open_onnx(path, device)


@functools.lru_cache(maxsize=4)
def _tflite(path: str):
    return open_tflite(path)


@functools.lru_cache(maxsize=4)
def _model_perception(m: ModelsConfig) -> ModelPerception:
    onnx = lambda p: _onnx(str(p), m.device)
    d, k, s, mk = m.detector, m.keypoints, m.semantic, m.masks
    detector = None
    if d.kind == "yolox":
        detector = YoloxDetector(onnx(d.path), d.person_class, d.score_threshold, d.nms_iou, decoded=d.decoded)
    elif d.kind == "decoded-boxes":
        detector = DecodedBoxesDetector(onnx(d.path), d.person_class, d.score_threshold, d.nms_iou)
    keypoints = (TopDownKeypoints(onnx(k.path), "heatmap" if k.kind == "vitpose" else "simcc", udp=k.udp,
                                  batch_size=k.batch_size) if k.kind in ("vitpose", "rtmpose") else None)
    blaze = (BlazePoseLandmarks(_tflite(str(bundled_model(m.bundled_dir, "pose_landmark_full.tflite"))),
                                box_scale=m.box_scale) if k.kind == "blazepose" else None)
    masks = (QueryInstanceMasks(onnx(mk.path), mk.person_class, mk.score_threshold)
             if mk.kind == "mask2former" else None)
    semantic = SemanticSegmenter(onnx(s.path), input_size=s.input_size) if s.kind == "onnx" else None
    source = {"mask2former": "masks", "blazepose": "blazepose", "semantic": "semantic", "none": "none"}[mk.kind]
    return ModelPerception(detector=detector, keypoints=keypoints, masks=masks, semantic=semantic,
                           blazepose=blaze, min_pose_flag=m.min_pose_flag, mask_source=source)


def model_perception(config: Config) -> ModelPerception:
    """The composite of ``detect.models`` (cached per process)."""
    return _model_perception(config.detect.models)


def uses_oracle_semantic(config: Config) -> bool:
    """image_provider 'models' with the oracle's semantics (synthetic data)."""
    return config.detect.image_provider == "models" and config.detect.models.semantic.kind == "oracle"


def models_image_perception(config: Config, frame, cam, lidar, semantic=None):
    """The frame's ImagePerception from the configured networks: its camera image read through
    storage, LiDAR proposals when ``detect.models.detector.kind`` is 'lidar', ``semantic`` (the
    oracle's, synthetic data) replacing the semantic model when given."""
    path = frame.image_paths[config.dataset.camera]
    image = read_rgb(path, (cam.width, cam.height))
    proposals = lidar_proposals(lidar, cam) if config.detect.models.detector.kind == "lidar" else None
    return model_perception(config)(image, proposals, semantic)


def gt_index_by_boxes(boxes_xyxy: np.ndarray, gt_box2d: np.ndarray) -> np.ndarray:
    """Synthetic data: the ground-truth person of each detection (Hungarian on 2D IoU >= 0.5,
    -1 unmatched), so the oracle's initial bodies can start the fit of model detections."""
    out = np.full(len(boxes_xyxy), -1, np.int64)
    finite = np.flatnonzero(np.all(np.isfinite(gt_box2d), axis=1))
    gi, di = match_boxes(gt_box2d[finite], boxes_xyxy, GT_MATCH_IOU)
    out[di] = finite[gi]
    return out


def lidar_proposals(lidar, cam) -> Detections:
    """The LiDAR pedestrian boxes of a frame projected into the camera, score 1 (the image
    model's pose flag then scores them)."""
    boxes, _ = project_lidar_boxes(lidar.centers, lidar.sizes, lidar.yaws, cam.T_cam_from_lidar, cam.K,
                                   cam.width, cam.height)
    return Detections(boxes, np.ones(len(boxes), np.float32))


@functools.lru_cache(maxsize=2)
def _cliff(path: str, device: str) -> CliffEstimator:
    return CliffEstimator(_onnx(path, device))


def cliff_estimator(config: Config) -> CliffEstimator:
    return _cliff(str(Path(config.fit.cliff_path)), config.fit.device)


def _cliff_frame(config: Config, sequence: str, raw: int, rows: list[int], boxes: np.ndarray) -> BodyParams:
    seq = open_sequence(config, sequence)
    cam = seq.info.calibration.cameras[config.dataset.camera]
    frame = seq.frame(seq.info.frame_indices.index(raw))
    image = read_rgb(frame.image_paths[config.dataset.camera], (cam.width, cam.height))
    return cliff_estimator(config)(image, boxes, cam.K)


def cliff_estimates(config: Config, sequence: str, tracks: dict) -> tuple[np.ndarray, BodyParams]:
    """Every row of the track product and its CLIFF estimate (cam frame), one image read per
    frame, frames fanned out like the detect stage."""
    frames = tracks["frame"].astype(np.int64)
    order = np.argsort(frames, kind="stable")
    args = [(config, sequence, int(f), order[frames[order] == f].tolist(), tracks["boxes_xyxy"][order[frames[order] == f]])
            for f in np.unique(frames)]
    parts = fan_out(_cliff_frame, args)
    rows = np.concatenate([np.asarray(a[3], np.int64) for a in args]) if args else np.zeros(0, np.int64)
    if not parts:
        z = lambda *s: np.zeros(s, np.float32)
        return rows, BodyParams(z(0, 10), z(0, 3), z(0, 69), z(0, 3))
    est = BodyParams(*(np.concatenate([getattr(p, k) for p in parts])
                       for k in ("betas", "global_orient", "body_pose", "transl")))
    back = np.argsort(rows, kind="stable")
    return rows[back], est.take(back)
