"""The configuration tree: every YAML in configs/ validates into :class:`Config`.

Every section forbids unknown keys (a misspelled key is an error, never ignored) and is frozen.
Only flows/ read a Config; they hand kernels their settings dataclasses (flows/pipeline/inputs.py).
A config file may start with ``extends: other.yaml`` (relative to itself): the other file is
loaded first and this one is deep-merged over it.

One home per default: a section that configures a kernel IS the kernel's settings dataclass (a
subclass of it, validated by pydantic: :class:`Section`), so its keys, types, defaults and bounds
(``tasks.bounds``: ``Positive``, ``Probability``, ...) are the dataclass's, declared once in
tasks/; a section adds only what no kernel reads (which provider, which files) and the rules
across fields. Every section is a class written out here, so ``config.fit.iterations`` is an
``int`` to an editor and to mypy (tests/test_config_types.py). YAML files set only what differs
from the defaults; ``mobileocc config show`` prints everything resolved.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import typing
from pathlib import Path
from typing import Any, Literal, TypeVar

import numpy as np
import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic.dataclasses import dataclass as pydantic_dataclass
from pydantic.fields import FieldInfo

from configs.sources import CameraTopics, LogSettings, PoseMode
from tasks.bounds import AtLeastOne, Count, NonNegative, Positive, Probability, VoxelSize
from tasks.conventions import CITYSCAPES_TO_CLASS, CLASS_NAMES, FREE, UNLABELED
from tasks.fit.settings import (
    MAX_ITERATIONS,
    SECONDS_PER_PERSON_STEP,
    FitSettings,
    FlipSettings,
    GapSettings,
    InitLidarSettings,
    RefineSettings,
)
from tasks.fit.weights import FIT_PRESETS, FitWeights, LossWeights, ObjectiveSettings
from tasks.occupancy.geometric_classes import GeometricClassSettings
from tasks.occupancy.grid import GridSpec
from tasks.occupancy.settings import FreeSpaceParams, FuseSettings, MapParams
from tasks.occupancy.tiles import check_tiling
from tasks.perception.lidar_clusters import LidarClusterParams
from tasks.perception.models.settings import (
    DEFAULT_BUNDLED_CACHE,
    BlazePoseSettings,
    DetectorSettings,
    KeypointSettings,
    MaskSettings,
    SemanticSettings,
)
from tasks.perception.oracle import OracleNoise
from tasks.perception.person_points import PersonPointParams
from tasks.poses.odometry import OdometrySettings
from tasks.track.ocsort import TrackerParams
from tasks.track.offline import Confirmation, OfflineParams, WorldCheck
from tasks.track.rate import GateRate

CONFIG_DIR = Path(__file__).resolve().parent
DEFAULT_CONFIG = CONFIG_DIR / "default.yaml"
#: the simulator's oracle (perception and initial bodies from gt/): benchmarks, ablations, tests
ORACLE_CONFIG = CONFIG_DIR / "oracle.yaml"

#: every model and section: unknown keys are errors, values frozen, numbers finite (no .inf / .nan)
STRICT = ConfigDict(extra="forbid", allow_inf_nan=False)

Kernel = TypeVar("Kernel")


def _number_kind(annotation: Any) -> bool:
    """Whether a field holds numbers (int / float, or a tuple / list / optional of them)."""
    if annotation in (int, float):
        return True
    args = typing.get_args(annotation)
    if typing.get_origin(annotation) is typing.Annotated:
        return _number_kind(args[0])
    args = tuple(a for a in args if a is not type(None) and a is not Ellipsis)
    return (
        bool(args)
        and typing.get_origin(annotation) is not dict
        and all(_number_kind(a) for a in args)
    )


def _not_a_number(value: Any) -> bool:
    if isinstance(value, (list, tuple)):
        return any(_not_a_number(v) for v in value)
    return isinstance(value, (bool, str))


def _numbers_are_numbers(fields: dict[str, FieldInfo], name: str | None, value: Any) -> Any:
    """A number is never a boolean or a string: YAML ``true`` or ``"2"`` for a number is an
    error, not 1 or 2."""
    field = fields.get(name or "")
    if field is not None and _number_kind(field.annotation) and _not_a_number(value):
        raise ValueError(
            f"expected a number, got {value!r} ({type(value).__name__}){_yaml_hint(value)}"
        )
    return value


def _yaml_hint(value: Any) -> str:
    """Why a number written in YAML arrived as text: YAML 1.1 (PyYAML) reads ``1e12`` (no
    decimal point, no exponent sign) as a string."""
    text = (
        next((v for v in value if isinstance(v, str)), None)
        if isinstance(value, (list, tuple))
        else value
    )
    if not isinstance(text, str):
        return ""
    try:
        number = float(text)
    except ValueError:
        return ""
    return (
        f": YAML reads {text} as text (an exponent needs a decimal point and a sign in YAML "
        f"1.1); write {number:.1e}".replace("e+0", "e+").replace("e-0", "e-")
        + " or the plain number"
    )


class Strict(BaseModel):
    """A section of settings no kernel reads (where the data are, which providers, workers)."""

    model_config = ConfigDict(**STRICT, frozen=True)

    @field_validator("*", mode="before")
    @classmethod
    def _numbers_are_numbers(cls, value: Any, info: Any) -> Any:
        return _numbers_are_numbers(cls.model_fields, info.field_name, value)


@pydantic_dataclass(config=STRICT, frozen=True)
class Section:
    """The base of a section made of kernel settings dataclasses: ``class FitConfig(FitSettings,
    ..., Section)``, decorated with :func:`pydantic.dataclasses.dataclass`, has the kernels'
    fields, defaults and bounds, and the checks of :class:`Strict`."""

    @field_validator("*", mode="before")
    @classmethod
    def _numbers_are_numbers(cls, value: Any, info: Any) -> Any:
        fields: dict[str, FieldInfo] = getattr(cls, "__pydantic_fields__", {})
        return _numbers_are_numbers(fields, info.field_name, value)

    def to(self, kernel: type[Kernel]) -> Kernel:
        """The settings dataclass ``kernel`` (one this section is made of) with this section's
        values: what a stage's inputs hold (its type names the cache key's JSON)."""
        names = [f.name for f in dataclasses.fields(kernel)]  # type: ignore[arg-type]
        return kernel(**{name: getattr(self, name) for name in names})


Vec3 = tuple[float, float, float]


def _duration(seconds: float) -> str:
    for unit, length in (("years", 3.156e7), ("days", 86400.0), ("hours", 3600.0)):
        if seconds >= length:
            return f"~{seconds / length:.3g} {unit}"
    return f"~{seconds:.3g} s"


#: grid bounds: every range within +-MAX_GRID_RANGE_M of the robot, at most MAX_GRID_CELLS_PER_AXIS
#: voxels along an axis and MAX_GRID_VOXELS in all: 2.4 x the benchmark grid at 0.02 m
#: (480 x 480 x 240); a frame's published arrays alone are BYTES_PER_VOXEL per voxel (1.2 GB at
#: the bound) and the fuse stage holds several frames' worth while it works
MAX_GRID_RANGE_M = 1000.0
MAX_GRID_CELLS_PER_AXIS = 4096
MAX_GRID_VOXELS = 2**27
#: semantics (1) + instances (2) + mask_lidar (1) + mask_camera (1) + velocity (2 x 2), bytes
BYTES_PER_VOXEL = 9


class GridConfig(Strict):
    """A robot-local voxel grid in the base frame, [x, y, z] order (default: the benchmark grid)."""

    range_min: Vec3 = (0.4, -4.8, -1.0)
    range_max: Vec3 = (10.0, 4.8, 3.8)
    voxel_size_m: VoxelSize = 0.2

    @model_validator(mode="after")
    def _extent_divides(self) -> GridConfig:
        for axis, (lo, hi) in enumerate(zip(self.range_min, self.range_max)):
            if max(abs(lo), abs(hi)) > MAX_GRID_RANGE_M:
                raise ValueError(
                    f"range [{lo}, {hi}] along axis {axis} reaches beyond {MAX_GRID_RANGE_M:g} m "
                    "of the robot"
                )
            if hi <= lo:
                raise ValueError(f"range_max[{axis}]={hi} must exceed range_min[{axis}]={lo}")
            if (hi - lo) / self.voxel_size_m > MAX_GRID_CELLS_PER_AXIS + 0.5:
                raise ValueError(
                    f"extent {hi - lo:g} m along axis {axis} is {(hi - lo) / self.voxel_size_m:.0f} "
                    f"voxels of {self.voxel_size_m:g} m; at most {MAX_GRID_CELLS_PER_AXIS}"
                )
            cells = (hi - lo) / self.voxel_size_m
            if abs(cells - round(cells)) > 1e-6:
                raise ValueError(
                    f"extent {hi - lo:g} m along axis {axis} is not a multiple of "
                    f"voxel_size_m={self.voxel_size_m:g}"
                )
        voxels = int(np.prod(self.shape, dtype=np.int64))
        if voxels > MAX_GRID_VOXELS:
            raise ValueError(
                f"grid of {' x '.join(map(str, self.shape))} = {voxels:.3g} voxels is more than "
                f"{MAX_GRID_VOXELS} (2^27): one frame's published arrays alone would take "
                f"{voxels * BYTES_PER_VOXEL / 1e9:.1f} GB of memory ({BYTES_PER_VOXEL} bytes per "
                "voxel), and the fuse stage holds several; the benchmark grid at 0.02 m is "
                "480 x 480 x 240 (55.3e6)"
            )
        return self

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(  # type: ignore[return-value]
            int(round((hi - lo) / self.voxel_size_m))
            for lo, hi in zip(self.range_min, self.range_max)
        )

    def spec(self) -> GridSpec:
        return GridSpec(self.range_min, self.range_max, self.voxel_size_m)


@pydantic_dataclass(config=STRICT, frozen=True)
class OdometryConfig(OdometrySettings, Section):
    """LiDAR odometry (KISS-ICP) of logs without world poses: tasks.poses.odometry."""


@pydantic_dataclass(config=STRICT, frozen=True)
class CameraTopicsConfig(CameraTopics, Section):
    """One camera's topics in a log (null: found in the log): storage/sources/log/reader.py."""


class LogConfig(Strict):
    """How robot logs are read (dataset.format log): topics and frames (null: found in the log,
    storage/sources/log/reader.py), where the poses come from, the image / pose time limits. The
    defaults are configs.sources.LogSettings'."""

    lidar_topic: str | None = LogSettings.lidar_topic
    cameras: dict[Literal["cam0", "cam1"], CameraTopicsConfig] = Field(default_factory=dict)
    base_frame: str | None = LogSettings.base_frame
    world_frame: str | None = LogSettings.world_frame
    poses: PoseMode = LogSettings.poses
    pose_topic: str | None = LogSettings.pose_topic
    max_image_offset_ms: Positive = LogSettings.max_image_offset_ms
    max_pose_gap_ms: Positive = LogSettings.max_pose_gap_ms
    odometry: OdometryConfig = OdometryConfig()

    def settings(self) -> LogSettings:
        """The reader's settings (what the stage inputs hold)."""
        cams = tuple((name, self.cameras[name].to(CameraTopics)) for name in sorted(self.cameras))
        plain = {f.name: getattr(self, f.name) for f in dataclasses.fields(LogSettings)}
        return LogSettings(
            **{**plain, "cameras": cams, "odometry": self.odometry.to(OdometrySettings)}
        )


class DatasetConfig(Strict):
    """Where the raw sequences are and how they are read (CODa raw layout or robot logs)."""

    root: Path = Path("demo-data")
    #: auto: robot logs when the root is a log or holds logs (.bag, .mcap, ROS 2 bag folders),
    #: else the CODa layout
    format: Literal["auto", "coda", "log"] = "auto"
    log: LogConfig = LogConfig()
    sequences: list[str] | Literal["all"] = "all"
    lidar_source: Literal["3d_comp", "3d_raw"] = "3d_comp"
    image_source: Literal["2d_rect", "2d_raw"] = "2d_rect"
    camera: Literal["cam0", "cam1"] = "cam0"
    #: which raw frames a sequence has: those with a sweep file, or those the metadata lists name
    frames: Literal["files", "metadata"] = "files"
    #: day / night per sequence id; a sequence not listed takes its metadata's "lighting"
    lighting: dict[str, Literal["day", "night"]] = Field(default_factory=dict)
    #: LiDAR height above the ground, used only where calib_os1_to_base.yaml is missing
    lidar_height_m: Positive = 0.9
    #: raw sensors run at 10 Hz; MobileOcc keeps every 2nd frame (5 Hz); 10: every frame (the
    #: tracking gates counted in frames are scaled to it: track.gates_rate_hz)
    rate_hz: Positive = 5.0
    sensor_rate_hz: Positive = 10.0
    #: drops no-return points (zeros) and returns off the robot body
    min_range_m: NonNegative = 0.5
    max_range_m: Positive = 120.0

    @field_validator("lighting", mode="before")
    @classmethod
    def _sequence_ids_as_text(cls, value):
        return {str(k): v for k, v in value.items()} if isinstance(value, dict) else value

    @model_validator(mode="after")
    def _stride_integral(self) -> DatasetConfig:
        stride = self.sensor_rate_hz / self.rate_hz
        if abs(stride - round(stride)) > 1e-9 or stride < 1:
            raise ValueError(f"sensor_rate_hz / rate_hz = {stride:g} must be a whole number >= 1")
        return self

    @property
    def frame_stride(self) -> int:
        return int(round(self.sensor_rate_hz / self.rate_hz))


@pydantic_dataclass(config=STRICT, frozen=True)
class OracleNoiseConfig(OracleNoise, Section):
    """Noise of the `oracle` provider (synthetic data only): tasks.perception.oracle."""


@pydantic_dataclass(config=STRICT, frozen=True)
class LidarClustersConfig(LidarClusterParams, Section):
    """The weight-free LiDAR pedestrian detector: tasks.perception.lidar_clusters."""


@pydantic_dataclass(config=STRICT, frozen=True)
class DetectorModelConfig(DetectorSettings, Section):
    """Person boxes of image_provider 'models': tasks/perception/models/settings.py."""


@pydantic_dataclass(config=STRICT, frozen=True)
class KeypointModelConfig(KeypointSettings, Section):
    """Top-down COCO-17 keypoints: tasks/perception/models/settings.py."""


@pydantic_dataclass(config=STRICT, frozen=True)
class MaskModelConfig(MaskSettings, Section):
    """Person instance masks: tasks/perception/models/settings.py."""


@pydantic_dataclass(config=STRICT, frozen=True)
class SemanticModelConfig(SemanticSettings, Section):
    """Image semantics of image_provider 'models'."""


@pydantic_dataclass(config=STRICT, frozen=True)
class ModelsConfig(BlazePoseSettings, Section):
    """image_provider 'models': real networks from local files; the defaults are the bundled
    BlazePose setup that needs no download (README, "Real perception models")."""

    device: Literal["cpu", "cuda", "auto"] = "auto"
    #: the bundled BlazePose .tflite files, extracted by `make setup` from the mediapipe wheel
    bundled_dir: Path = DEFAULT_BUNDLED_CACHE
    detector: DetectorModelConfig = DetectorModelConfig()
    keypoints: KeypointModelConfig = KeypointModelConfig()
    masks: MaskModelConfig = MaskModelConfig()
    semantic: SemanticModelConfig = SemanticModelConfig()

    @model_validator(mode="after")
    def _kinds_and_paths(self) -> ModelsConfig:
        if self.masks.kind == "blazepose" and self.keypoints.kind != "blazepose":
            raise ValueError(
                "masks.kind 'blazepose' comes with keypoints.kind 'blazepose' (one model run)"
            )
        if self.masks.kind == "semantic" and self.semantic.kind == "none":
            raise ValueError(
                "masks.kind 'semantic' needs a semantic model (semantic.kind onnx or oracle)"
            )
        for name, part, needs in (
            ("detector", self.detector, self.detector.kind != "lidar"),
            ("keypoints", self.keypoints, self.keypoints.kind in ("vitpose", "rtmpose")),
            ("masks", self.masks, self.masks.kind == "mask2former"),
            ("semantic", self.semantic, self.semantic.kind == "onnx"),
        ):
            if needs and part.path is None:
                raise ValueError(
                    f"{name}.path is required for {name}.kind {part.kind!r} (an ONNX file)"
                )
        return self


class DetectConfig(Strict):
    #: models: the bundled BlazePose keypoints and masks on the LiDAR detector's boxes (no ground
    #: truth, nothing to download); oracle: the simulator's truth + noise (configs/oracle.yaml)
    image_provider: Literal["oracle", "precomputed", "models"] = "models"
    lidar_provider: Literal["lidar-clusters", "oracle", "precomputed", "none"] = "lidar-clusters"
    precomputed_dir: Path | None = None
    oracle: OracleNoiseConfig = OracleNoiseConfig()
    lidar_clusters: LidarClustersConfig = LidarClustersConfig()
    models: ModelsConfig = ModelsConfig()
    seed: int = 0
    #: a frame whose input is bad (a cut sweep, an image that does not decode) is left out of
    #: every stage; the sequence fails when more than this share of its frames is bad (0: any)
    max_failed_frame_share: Probability = 0.5

    @model_validator(mode="after")
    def _precomputed_needs_dir(self) -> DetectConfig:
        uses = "precomputed" in (self.image_provider, self.lidar_provider)
        if uses and self.precomputed_dir is None:
            raise ValueError("precomputed_dir is required when a provider is 'precomputed'")
        if (
            self.image_provider == "models"
            and self.models.detector.kind == "lidar"
            and self.lidar_provider == "none"
        ):
            raise ValueError("models.detector.kind 'lidar' needs a lidar_provider (not 'none')")
        return self


@pydantic_dataclass(config=STRICT, frozen=True)
class PersonPointsConfig(PersonPointParams, Section):
    """Separating a person's LiDAR points: tasks.perception.person_points."""


@pydantic_dataclass(config=STRICT, frozen=True)
class WorldCheckConfig(WorldCheck, Section):
    """Offline identity check on world positions: tasks.track.offline.WorldCheck."""


@pydantic_dataclass(config=STRICT, frozen=True)
class ConfirmConfig(Confirmation, Section):
    """A tracklet confirmed by one detection's evidence: tasks.track.offline.Confirmation."""


@pydantic_dataclass(config=STRICT, frozen=True)
class TrackConfig(GateRate, OfflineParams, TrackerParams, Section):
    """OC-SORT (tasks.track.ocsort.TrackerParams), the offline refinement
    (tasks.track.offline.OfflineParams, WorldCheck), person points, and the rate the
    frame-counted gates are given at (tasks.track.rate.GateRate: scaled to dataset.rate_hz)."""

    world_check: WorldCheckConfig = WorldCheckConfig()
    confirm: ConfirmConfig = ConfirmConfig()
    person_points: PersonPointsConfig = PersonPointsConfig()


@pydantic_dataclass(config=STRICT, frozen=True)
class LossWeightsConfig(LossWeights, Section):
    """A preset of ``fit.presets``: tasks.fit.weights.LossWeights (the paper's appendix table)."""


@pydantic_dataclass(config=STRICT, frozen=True)
class InitLidarConfig(InitLidarSettings, Section):
    """The weight-free start from LiDAR points and keypoints: tasks.fit.settings.InitLidarSettings."""


@pydantic_dataclass(config=STRICT, frozen=True)
class FlipsConfig(FlipSettings, Section):
    """Left / right keypoint swaps decided along a track: tasks.fit.settings.FlipSettings."""


@pydantic_dataclass(config=STRICT, frozen=True)
class RefineConfig(RefineSettings, Section):
    """The temporal refinement of a track's fits: tasks.fit.settings.RefineSettings."""


@pydantic_dataclass(config=STRICT, frozen=True)
class GapsConfig(GapSettings, Section):
    """Bodies for frames a track coasted over: tasks.fit.settings.GapSettings."""


@pydantic_dataclass(config=STRICT, frozen=True)
class FitConfig(ObjectiveSettings, FitSettings, Section):
    """The body fit: tasks.fit.settings.FitSettings, the objective's preset and its
    tasks.fit.weights.ObjectiveSettings, where the initial estimates and the body model come
    from."""

    #: the paper's 3DPW weights: on our persons they fit better than its UT-Campus ones (CODa's)
    #: from every start and with every keypoint source measured (docs/fit-benchmark.md, "The
    #: default preset")
    preset: str = "3dpw"
    #: named loss-weight presets beside the paper's four (tasks.fit.weights.FIT_PRESETS)
    presets: dict[str, LossWeightsConfig] = Field(default_factory=dict)
    #: initial estimates: the oracle (synthetic data), CLIFF (precomputed files or an export),
    #: or lidar-keypoints (the default: no network, no ground truth: tasks/fit/init_lidar.py)
    init_provider: Literal["oracle", "precomputed", "cliff", "lidar-keypoints"] = "lidar-keypoints"
    init_lidar: InitLidarConfig = InitLidarConfig()
    flips: FlipsConfig = FlipsConfig()
    refine: RefineConfig = RefineConfig()
    gaps: GapsConfig = GapsConfig()
    #: cliff: a CLIFF ONNX export run on each tracked box (tasks/perception/models/cliff.py), on
    #: fit.device
    cliff_path: Path | None = None
    #: precomputed CLIFF estimates: <init_dir>/<sequence>/cliff.parquet (storage/PERCEPTION_FORMAT.md)
    init_dir: Path | None = None
    #: user-supplied official model files; None = our procedural stand-ins
    body_model_path: Path | None = None
    pose_prior_path: Path | None = None

    @model_validator(mode="after")
    def _precomputed_needs_dir(self) -> FitConfig:
        if self.init_provider == "precomputed" and self.init_dir is None:
            raise ValueError("fit.init_dir is required when fit.init_provider is 'precomputed'")
        if self.init_provider == "cliff" and self.cliff_path is None:
            raise ValueError("fit.cliff_path is required when fit.init_provider is 'cliff'")
        return self

    @model_validator(mode="after")
    def _iterations_can_finish(self) -> FitConfig:
        if self.iterations > MAX_ITERATIONS:
            seconds = self.iterations * SECONDS_PER_PERSON_STEP
            raise ValueError(
                f"fit.iterations {self.iterations} is more than {MAX_ITERATIONS}: at "
                f"~{SECONDS_PER_PERSON_STEP * 1e3:g} ms per person-frame and step on a CPU core "
                f"(docs/fit-benchmark.md) one person-frame alone would take {_duration(seconds)}; "
                "the default is 100"
            )
        return self

    @model_validator(mode="after")
    def _preset_known(self) -> FitConfig:
        known = sorted(set(FIT_PRESETS) | set(self.presets))
        if self.preset not in known:
            raise ValueError(f"preset {self.preset!r} is not one of {known}")
        return self

    @property
    def weights(self) -> FitWeights:
        """The chosen preset's weights with the objective's settings."""
        preset: LossWeights = self.presets.get(self.preset) or FIT_PRESETS[self.preset]
        return FitWeights.of(preset, self.to(ObjectiveSettings))


@pydantic_dataclass(config=STRICT, frozen=True)
class FreeSpaceConfig(FreeSpaceParams, Section):
    """OctoMap sensor model of the free / unknown map: tasks.occupancy.settings.FreeSpaceParams."""


#: Cityscapes train id -> class name, the default mapping (tasks.conventions.CITYSCAPES_TO_CLASS)
DEFAULT_CITYSCAPES_TO_CLASS = {
    cs: CLASS_NAMES[int(CITYSCAPES_TO_CLASS[cs])]
    for cs in range(19)
    if CITYSCAPES_TO_CLASS[cs] != UNLABELED
}


@pydantic_dataclass(config=STRICT, frozen=True)
class GeometricClassesConfig(GeometricClassSettings, Section):
    """Per-point classes from geometry (``map.point_classes`` geometry / camera+geometry):
    tasks/occupancy/geometric_classes.py."""


@pydantic_dataclass(config=STRICT, frozen=True)
class MapConfig(MapParams, Section):
    """The static semantic map: tasks.occupancy.settings.MapParams, the class mapping, and the
    free / unknown map."""

    cityscapes_to_class: dict[int, str] = Field(
        default_factory=lambda: dict(DEFAULT_CITYSCAPES_TO_CLASS)
    )
    ground_classes: list[str] = Field(default_factory=lambda: ["road", "terrain"])
    freespace: FreeSpaceConfig = FreeSpaceConfig()
    #: which labels the map's points take: the camera's (lifted image semantics, the outside-image
    #: fallback beyond), the geometry's (tasks/occupancy/geometric_classes.py: no segmenter
    #: needed), the camera's where it has one and the geometry's elsewhere, or auto:
    #: camera+geometry where detect gives no image semantics (models.semantic.kind none), else
    #: camera (tasks.occupancy.mapping.SweepLabeller)
    point_classes: Literal["auto", "camera", "geometry", "camera+geometry"] = "auto"
    geometry: GeometricClassesConfig = GeometricClassesConfig()


@pydantic_dataclass(config=STRICT, frozen=True)
class FuseConfig(FuseSettings, Section):
    """The per-frame fusion: the grid, the bodies, and tasks.occupancy.settings.FuseSettings."""

    grid: GridConfig = GridConfig()
    body_source: Literal["fit", "ground-truth"] = "fit"
    #: ground-truth bodies: fuse only people the sensors observe (>= this many LiDAR returns and
    #: some pixels in cam0), the people a real pipeline can annotate; 0 = every simulated person
    gt_min_points: Count = 10


class ExportConfig(Strict):
    formats: list[Literal["occ3d", "nuscenes"]] = ["occ3d"]
    nuscenes_version: Literal["v1.0-trainval", "v1.0-mini", "v1.0-test"] = "v1.0-trainval"
    scene_prefix: str = "coda"
    val_sequences: list[str] = Field(default_factory=list)
    #: prefix of the file paths in the nuScenes export's training infos: where the trainer finds
    #: the export folder; null: FlashOcc's data_root (storage.export.nuscenes.INFOS_DATA_ROOT)
    infos_data_root: str | None = None


class OutputConfig(Strict):
    root: Path = Path("demo-out")
    frames_per_chunk: AtLeastOne = 50


class DaskConfig(Strict):
    runner: Literal["thread", "dask"] = "thread"
    workers: AtLeastOne = 2
    threads_per_worker: AtLeastOne = 1
    address: str | None = None
    memory_limit: str = "4GiB"
    #: route the fit stage to workers started with `--resources GPU=1`
    gpu_fit: bool = False
    #: route the detect stage's frame chunks to those workers (image_provider 'models' on CUDA)
    gpu_detect: bool = False
    #: run the units as Prefect tasks: auto = only where a Prefect API is configured
    #: (PREFECT_API_URL); otherwise they run on the same thread pool / Dask cluster without Prefect,
    #: whose temporary server would cost seconds and keep nothing (flows/pipeline/local.py)
    prefect: Literal["auto", "always", "never"] = "auto"


class Config(Strict):
    dataset: DatasetConfig = DatasetConfig()
    detect: DetectConfig = DetectConfig()
    track: TrackConfig = TrackConfig()
    fit: FitConfig = FitConfig()
    map: MapConfig = MapConfig()
    fuse: FuseConfig = FuseConfig()
    export: ExportConfig = ExportConfig()
    output: OutputConfig = OutputConfig()
    dask: DaskConfig = DaskConfig()

    @model_validator(mode="after")
    def _mapping_targets_known(self) -> Config:
        occupied = CLASS_NAMES[:FREE]
        for name in self.map.ground_classes:
            if name not in occupied:
                raise ValueError(
                    f"map.ground_classes: {name!r} is not an occupied class {occupied}"
                )
        for cs_id, name in self.map.cityscapes_to_class.items():
            if not 0 <= cs_id <= 18:
                raise ValueError(
                    f"map.cityscapes_to_class: Cityscapes train id {cs_id} not in 0..18"
                )
            if name not in occupied:
                raise ValueError(
                    f"map.cityscapes_to_class[{cs_id}] = {name!r} is not an occupied class {occupied}"
                )
        check_tiling(self.map.tile_m, self.map.voxel_size_m, self.map.freespace.voxel_size_m)
        return self


def config_hash(config: Config) -> str:
    """sha256 (first 16 hex) of the canonical JSON of the resolved config (what a run was asked
    to do; the published data carry the hash of the stage inputs instead, flows/pipeline/inputs.py)."""
    dump = config.model_dump(mode="json")
    blob = json.dumps(dump, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


class ConfigError(ValueError):
    """A config file failed to validate; ``errors`` holds (key path, message) pairs."""

    def __init__(self, source: str, errors: list[tuple[str, str]]):
        self.source = source
        self.errors = errors
        if len(errors) == 1 and not errors[0][0]:  # the file as a whole: one line
            super().__init__(f"{source}: {errors[0][1]}")
            return
        lines = "\n".join(f"  {path}: {msg}" for path, msg in errors)
        super().__init__(f"{source}: {len(errors)} error(s)\n{lines}")


def _deep_merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _deep_merge(out[key], value)
        else:
            out[key] = value
    return out


def read_config_dict(path: Path, _seen: tuple[Path, ...] = ()) -> dict:
    """Read a YAML config with its ``extends`` chain resolved (no validation)."""
    path = Path(path).resolve()
    if path in _seen:
        raise ConfigError(str(path), [("extends", "circular extends chain")])
    try:
        raw = yaml.safe_load(path.read_bytes().decode("utf-8"))
    except FileNotFoundError:
        raise ConfigError(str(path), [("", "file not found")]) from None
    except IsADirectoryError:
        raise ConfigError(str(path), [("", "is a folder, expected a YAML file")]) from None
    except OSError as exc:
        raise ConfigError(str(path), [("", f"cannot be read ({exc.strerror or exc})")]) from None
    except UnicodeDecodeError as exc:
        raise ConfigError(
            str(path), [("", f"is not UTF-8 text (byte {exc.start}); expected a YAML file")]
        ) from None
    except yaml.YAMLError as exc:
        raise ConfigError(str(path), [("", f"invalid YAML: {exc}")]) from None
    raw = raw or {}
    if not isinstance(raw, dict):
        raise ConfigError(
            str(path), [("", f"expected a mapping at top level, got {type(raw).__name__}")]
        )
    parent = raw.pop("extends", None)
    if parent is not None:
        raw = _deep_merge(read_config_dict(path.parent / parent, _seen + (path,)), raw)
    return raw


def _set_dotted(tree: dict, dotted: str, value: Any) -> None:
    keys = dotted.split(".")
    node = tree
    for key in keys[:-1]:
        node = node.setdefault(key, {})
        if not isinstance(node, dict):
            raise ConfigError("--set", [(dotted, f"{key!r} is not a mapping")])
    node[keys[-1]] = value


def load_config(path: Path | str | None = None, overrides: dict[str, Any] | None = None) -> Config:
    """Load, merge overrides (dotted keys -> YAML-parsed values) and validate a config.

    Raises ConfigError listing every validation error with its key path.
    """
    path = Path(path) if path is not None else DEFAULT_CONFIG
    return config_from_tree(read_config_dict(path), str(path), overrides)


def config_from_tree(tree: dict, source: str, overrides: dict[str, Any] | None = None) -> Config:
    """Validate a config tree (a YAML file's, or a resolved config recorded beside a dataset)
    with dotted ``overrides``; ConfigError names ``source`` and every error's key path."""
    tree = copy.deepcopy(tree)
    for dotted, value in (overrides or {}).items():
        _set_dotted(tree, dotted, value)
    try:
        return Config.model_validate(tree)
    except ValidationError as exc:
        errors = []
        for err in exc.errors():
            loc = ".".join(str(p) for p in err["loc"])
            msg = err["msg"]
            if err["type"] in ("extra_forbidden", "unexpected_keyword_argument"):
                msg = "unknown key (misspelled?)"
            elif err["type"] == "missing_argument":  # a section's words for "missing"
                msg = "Field required"
            errors.append((loc or "<root>", msg))
        raise ConfigError(source, errors) from None
