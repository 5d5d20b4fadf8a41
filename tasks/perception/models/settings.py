"""Settings of the model adapters as the pipeline configures them (``detect.models``): one home for
their defaults (configs/schema.py makes the config sections from these; the adapters' keyword
defaults point here)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from tasks.bounds import AtLeastOne, Count, Positive, PositiveFraction, Probability

#: the wheel set-up downloads (pip download mediapipe==0.10.21 --no-deps): the last release line
#: that still ships the pose models inside the package (1.x no longer does)
MEDIAPIPE_VERSION = "0.10.21"
#: where set-up puts them unless told otherwise: relative to the working directory, else to the
#: checkout that `make setup` ran in (:func:`bundled_model`)
DEFAULT_BUNDLED_CACHE = Path(".cache/models/mediapipe-" + MEDIAPIPE_VERSION)


@dataclass(frozen=True)
class DetectorSettings:
    """Person boxes: ``lidar`` (the LiDAR pedestrian boxes projected into the camera), ``yolox``
    or ``decoded-boxes`` (an export with dets + labels outputs) from the ONNX file ``path``.
    decoded: yolox exported with --decode_in_inference."""

    kind: Literal["lidar", "yolox", "decoded-boxes"] = "lidar"
    path: str | None = None
    decoded: bool = False
    person_class: Count = 0
    score_threshold: Probability = 0.3
    nms_iou: PositiveFraction = 0.45


@dataclass(frozen=True)
class KeypointSettings:
    """Top-down COCO-17 keypoints: ``blazepose`` (bundled), ``vitpose`` / ``rtmpose`` (ONNX), or
    none. udp: ViTPose's UDP codec (False: classic heatmaps)."""

    kind: Literal["blazepose", "vitpose", "rtmpose", "none"] = "blazepose"
    path: str | None = None
    udp: bool = True
    batch_size: AtLeastOne = 16


@dataclass(frozen=True)
class MaskSettings:
    """Person instance masks: ``blazepose`` (with its keypoints), ``mask2former`` (ONNX query
    logits), ``semantic`` (the semantic model's person pixels in each box), or none."""

    kind: Literal["blazepose", "mask2former", "semantic", "none"] = "blazepose"
    path: str | None = None
    person_class: Count = 0
    score_threshold: Probability = 0.5


@dataclass(frozen=True)
class SemanticSettings:
    """Image semantics: none (255, the default: no Cityscapes model is bundled), ``onnx`` (a
    Cityscapes export; input_size (height, width) for one with a dynamic input), or ``oracle``
    (the simulator's truth: synthetic data with gt/ only)."""

    kind: Literal["oracle", "onnx", "none"] = "none"
    path: str | None = None
    input_size: tuple[int, int] | None = None


@dataclass(frozen=True)
class BlazePoseSettings:
    """The bundled BlazePose run: min_pose_flag: a box whose pose flag (the landmark model's "a
    person is in the region") is below it drops, the others' scores are multiplied by it (measured
    on a tuning sequence, LiDAR boxes: 0 / 0.3 / 0.5 give recall 0.85 / 0.78 / 0.69, precision 0.68
    / 0.87 / 0.87); box_scale: the square region around a box is max(w, h) x box_scale (1.0 / 1.1
    / 1.25 / 1.5 give PCK@0.1 0.75 / 0.78 / 0.69 / 0.64, mask IoU 0.83 / 0.83 / 0.78 / 0.80)."""

    min_pose_flag: Probability = 0.3
    box_scale: Positive = 1.1
