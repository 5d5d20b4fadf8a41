"""The configuration tree: every YAML in configs/ validates into :class:`Config`.

Every model forbids unknown keys (a misspelled key is an error, never ignored) and is frozen. Only
flows/ read a Config; they hand kernels plain values. A config file may start with
``extends: other.yaml`` (relative to itself): the other file is loaded first and this one is
deep-merged over it.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

CONFIG_DIR = Path(__file__).resolve().parent
DEFAULT_CONFIG = CONFIG_DIR / "default.yaml"


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


Vec3 = tuple[float, float, float]


class GridConfig(Strict):
    """A robot-local voxel grid in the base frame, [x, y, z] order."""

    range_min: Vec3 = (0.4, -4.8, -1.0)
    range_max: Vec3 = (10.0, 4.8, 3.8)
    voxel_size_m: float = Field(0.2, ge=0.02, le=1.0)

    @model_validator(mode="after")
    def _extent_divides(self) -> GridConfig:
        for axis, (lo, hi) in enumerate(zip(self.range_min, self.range_max)):
            if hi <= lo:
                raise ValueError(f"range_max[{axis}]={hi} must exceed range_min[{axis}]={lo}")
            cells = (hi - lo) / self.voxel_size_m
            if abs(cells - round(cells)) > 1e-6:
                raise ValueError(
                    f"extent {hi - lo:g} m along axis {axis} is not a multiple of "
                    f"voxel_size_m={self.voxel_size_m:g}"
                )
        return self

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(  # type: ignore[return-value]
            int(round((hi - lo) / self.voxel_size_m)) for lo, hi in zip(self.range_min, self.range_max)
        )


class ClassEntry(Strict):
    id: int = Field(ge=0, le=254)
    name: str
    color: tuple[int, int, int]


class DatasetConfig(Strict):
    """Where the raw sequences are and how they are read (CODa raw layout)."""

    root: Path = Path("demo-data")
    sequences: list[str] | Literal["all"] = "all"
    lidar_source: Literal["3d_comp", "3d_raw"] = "3d_raw"
    image_source: Literal["2d_rect", "2d_raw"] = "2d_rect"
    camera: Literal["cam0", "cam1"] = "cam0"
    #: raw sensors run at 10 Hz; MobileOcc keeps every 2nd frame (5 Hz)
    rate_hz: float = Field(5.0, gt=0)
    sensor_rate_hz: float = Field(10.0, gt=0)
    min_range_m: float = Field(0.5, ge=0)
    max_range_m: float = Field(120.0, gt=0)

    @model_validator(mode="after")
    def _stride_integral(self) -> DatasetConfig:
        stride = self.sensor_rate_hz / self.rate_hz
        if abs(stride - round(stride)) > 1e-9 or stride < 1:
            raise ValueError(
                f"sensor_rate_hz / rate_hz = {stride:g} must be a whole number >= 1"
            )
        return self

    @property
    def frame_stride(self) -> int:
        return int(round(self.sensor_rate_hz / self.rate_hz))


class OracleNoise(Strict):
    """Noise of the `oracle` perception provider (synthetic data only); see tasks.perception.oracle."""

    day_recall: float = Field(0.99, ge=0, le=1)
    night_recall: float = Field(0.77, ge=0, le=1)
    occlusion_miss: float = Field(0.9, ge=0, le=1)
    occlusion_power: float = Field(6.0, gt=0)
    min_visible_fraction: float = Field(0.05, ge=0, le=1)
    distance_miss: float = Field(0.1, ge=0, le=1)
    near_m: float = Field(10.0, gt=0)
    far_m: float = Field(40.0, gt=0)
    fp_per_frame: float = Field(0.02, ge=0)
    fp_score_range: tuple[float, float] = (0.3, 0.75)
    box_jitter: float = Field(0.03, ge=0)
    keypoint_sigma: float = Field(0.01, ge=0)
    mask_flip_prob: float = Field(0.3, ge=0, le=1)
    semantic_patches: float = Field(3.0, ge=0)
    semantic_patch_px: tuple[int, int] = (8, 48)
    night_noise_scale: float = Field(2.0, ge=0)
    lidar_recall: float = Field(0.97, ge=0, le=1)
    lidar_far_m: float = Field(40.0, gt=0)
    lidar_center_sigma_m: float = Field(0.05, ge=0)
    lidar_size_sigma_m: float = Field(0.05, ge=0)
    lidar_yaw_sigma_rad: float = Field(0.1, ge=0)


class LidarClustersConfig(Strict):
    """The weight-free LiDAR pedestrian detector (tasks.perception.lidar_clusters)."""

    ground_cell_m: float = Field(2.0, gt=0)
    ground_tol_m: float = Field(0.2, ge=0)
    ceiling_m: float = Field(2.4, gt=0)
    voxel_m: float = Field(0.1, gt=0)
    cluster_tol_m: float = Field(0.3, gt=0)
    min_points: int = Field(10, ge=1)
    min_height_m: float = Field(1.0, gt=0)
    max_height_m: float = Field(2.1, gt=0)
    max_footprint_m: float = Field(1.2, gt=0)
    max_range_m: float = Field(40.0, gt=0)


class DetectConfig(Strict):
    image_provider: Literal["oracle", "precomputed"] = "oracle"
    lidar_provider: Literal["lidar-clusters", "oracle", "precomputed", "none"] = "lidar-clusters"
    precomputed_dir: Path | None = None
    oracle: OracleNoise = OracleNoise()
    lidar_clusters: LidarClustersConfig = LidarClustersConfig()
    seed: int = 0

    @model_validator(mode="after")
    def _precomputed_needs_dir(self) -> DetectConfig:
        uses = "precomputed" in (self.image_provider, self.lidar_provider)
        if uses and self.precomputed_dir is None:
            raise ValueError("precomputed_dir is required when a provider is 'precomputed'")
        return self


class PersonPointsConfig(Strict):
    """Separating a person's LiDAR points (tasks.perception.person_points)."""

    gap_m: float = Field(0.3, gt=0)
    min_points: int = Field(3, ge=1)
    person_height_m: float = Field(1.7, gt=0)
    range_sigma_frac: float = Field(0.25, gt=0)
    core_frac: float = Field(0.5, gt=0, le=1)
    min_depth_m: float = Field(0.5, ge=0)
    ground_tol_m: float | None = 0.15
    ground_cell_m: float = Field(2.0, gt=0)
    feet_radius_m: float = Field(0.1, ge=0)
    #: a person cut by the image's left / right border grows past it on LiDAR geometry (0 = off)
    edge_grow_m: float = Field(0.25, ge=0)
    edge_extent_m: float = Field(0.7, gt=0)
    edge_margin_px: float = Field(20.0, ge=0)
    assoc_min_iou: float = Field(0.3, ge=0, le=1)


class WorldCheckConfig(Strict):
    """Offline identity check on world positions (tasks.track.offline.split_tracks / stitch_ids)."""

    #: cut tracks at missed frames and 3D jumps, re-stitch on world positions (False = 2D only)
    enabled: bool = True
    #: persons with fewer LiDAR points have no position (the check skips them)
    min_points: int = Field(5, ge=1)
    max_speed_mps: float = Field(2.5, gt=0)
    #: a position within tol_m + speed_sigma_mps * dt of the track's prediction is consistent
    tol_m: float = Field(0.6, gt=0)
    speed_sigma_mps: float = Field(0.5, ge=0)
    #: positions per track end for the velocity fit
    window: int = Field(5, ge=1)
    #: gate factor for a join OC-SORT made itself (two cues agree)
    continuation_gate_scale: float = Field(1.5, ge=1)
    #: never-confirmed tracklets may join a confirmed track (kept only then)
    tentative: bool = True


class TrackConfig(Strict):
    """OC-SORT (Cao et al.) settings, offline refinement (tasks.track.offline), person points."""

    det_thresh: float = Field(0.6, ge=0, le=1)
    #: frames at the stage's rate (lost tracks kept this long)
    max_age: int = Field(30, ge=1)
    min_hits: int = Field(3, ge=1)
    iou_threshold: float = Field(0.3, ge=0, le=1)
    delta_t: int = Field(3, ge=1)
    inertia: float = Field(0.2, ge=0, le=1)
    #: report a re-found confirmed track at once (False = reference OC-SORT output)
    keep_confirmed_ids: bool = True
    #: offline: a confirmed track also gets its tentative first detections
    backfill: bool = True
    #: offline: join a track to one starting at most this many frames after it ends (0 = never)
    stitch_max_gap: int = Field(10, ge=0)
    #: join gate: mean constant-velocity extrapolation error, in box heights
    stitch_max_distance: float = Field(0.5, gt=0)
    #: join gate: largest height ratio of the two end boxes
    stitch_max_scale: float = Field(1.5, ge=1)
    world_check: WorldCheckConfig = WorldCheckConfig()
    person_points: PersonPointsConfig = PersonPointsConfig()


class LossWeights(Strict):
    """Scalar weights and thresholds of the fitting objective (paper, appendix table)."""

    rho: float = Field(gt=0, description="Geman-McClure scale, pixels")
    lambda_theta: float = Field(ge=0)
    lambda_a: float = Field(ge=0)
    lambda_beta: float = Field(ge=0)
    lambda_3d: float = Field(ge=0)
    lambda_occ: float = Field(ge=0)
    w: float = Field(ge=-1, le=1, description="backface culling threshold")
    j_conf: float = Field(ge=0, le=1, description="keypoint confidence threshold")


PAPER_PRESETS: dict[str, LossWeights] = {
    "3dpw": LossWeights(rho=100, lambda_theta=2.2, lambda_a=11.0, lambda_beta=5.0, lambda_3d=800,
                        lambda_occ=35, w=0.2, j_conf=0.6),
    "sloper4d": LossWeights(rho=100, lambda_theta=0.75, lambda_a=8.5, lambda_beta=1.0,
                            lambda_3d=500, lambda_occ=55, w=0.2, j_conf=0.7),
    "humanm3": LossWeights(rho=100, lambda_theta=1.0, lambda_a=3.0, lambda_beta=17.5,
                           lambda_3d=600, lambda_occ=135, w=-1.0, j_conf=0.6),
    "ut_campus": LossWeights(rho=100, lambda_theta=1.4, lambda_a=10.0, lambda_beta=10.0,
                             lambda_3d=300, lambda_occ=50, w=0.2, j_conf=0.7),
}


class FitConfig(Strict):
    preset: str = "ut_campus"
    #: named loss-weight presets; the paper's four are always available, YAML may add more
    presets: dict[str, LossWeights] = Field(default_factory=dict)
    #: the paper does not say whether lambdas multiply squared; squared measured better here
    squared_weights: bool = True
    #: keypoint confidence power in L_J (SMPLify-X / SPIN use 2)
    confidence_power: float = Field(2.0, ge=0)
    iterations: int = Field(100, ge=0)
    learning_rate: float = Field(0.02, gt=0)
    #: recompute the Chamfer nearest pairs and the pose blend shapes every this many steps (no
    #: gradient flows through the blend shapes in between; 1 = the exact gradient every step)
    nn_every: int = Field(5, ge=1)
    #: a person stops when its objective fell by less than this fraction between two pair
    #: refreshes (null: always ``iterations`` steps)
    converge_rtol: float | None = Field(None, gt=0)
    #: cap (m) of the vertex -> point distances in L_3D: a visible vertex with no LiDAR return
    #: this close is treated as unobserved (null = the paper's uncapped Chamfer; the cap removed a
    #: ~30 mm pull towards the sensor on the synthetic benchmark)
    chamfer_vertex_max_m: float | None = Field(0.03, gt=0)
    #: detections with fewer LiDAR points are not fitted: keypoints alone leave depth free (on the
    #: benchmark such fits floated metres away); 0 fits every detection
    min_points: int = Field(10, ge=0)
    #: fits whose root moved farther (m) from the initial estimate are dropped: they latched onto
    #: someone else's points or floated off (null keeps every fit)
    max_shift_m: float | None = Field(1.5, gt=0)
    batch_persons: int = Field(64, ge=1)
    device: Literal["cpu", "cuda", "auto"] = "auto"
    #: start a track's fit from its previous frame's fit (beyond the paper; frames run in order)
    warm_start: bool = False
    init_provider: Literal["oracle", "precomputed"] = "oracle"
    #: precomputed CLIFF estimates: <init_dir>/<sequence>/cliff.parquet (storage/PERCEPTION_FORMAT.md)
    init_dir: Path | None = None
    #: user-supplied official model files; None = our procedural stand-ins
    body_model_path: Path | None = None
    pose_prior_path: Path | None = None
    seed: int = 0

    @model_validator(mode="after")
    def _precomputed_needs_dir(self) -> FitConfig:
        if self.init_provider == "precomputed" and self.init_dir is None:
            raise ValueError("fit.init_dir is required when fit.init_provider is 'precomputed'")
        return self

    @model_validator(mode="after")
    def _preset_known(self) -> FitConfig:
        if self.preset not in self.all_presets:
            raise ValueError(
                f"preset {self.preset!r} is not one of {sorted(self.all_presets)}"
            )
        return self

    @property
    def all_presets(self) -> dict[str, LossWeights]:
        return {**PAPER_PRESETS, **self.presets}

    @property
    def weights(self) -> LossWeights:
        return self.all_presets[self.preset]


class FreeSpaceConfig(Strict):
    """OctoMap sensor model (defaults are OctoMap's) of the free / unknown map."""

    #: its own resolution: memory grows with the volume the rays cross (keep 0.1-0.2 m; the fused
    #: grid may still be finer)
    voxel_size_m: float = Field(0.2, ge=0.02, le=1.0)
    prob_hit: float = Field(0.7, gt=0.5, lt=1)
    prob_miss: float = Field(0.4, gt=0, lt=0.5)
    clamp_min: float = Field(0.1192, gt=0, lt=0.5)
    clamp_max: float = Field(0.971, gt=0.5, lt=1)
    occupancy_threshold: float = Field(0.5, gt=0, lt=1)
    max_range_m: float = Field(20.0, gt=0)
    #: OctoMap's `discretize`: one ray per distinct endpoint voxel
    discretize: bool = False


class MapConfig(Strict):
    voxel_size_m: float = Field(0.2, ge=0.02, le=1.0)
    #: Cityscapes train id (0-18) -> class name; ids not listed are unlabelled (e.g. sky)
    cityscapes_to_class: dict[int, str] = Field(default_factory=dict)
    outside_image_fallback: Literal["nearest", "unknown"] = "nearest"
    #: > 1: out-of-view ground points match in-view ground with the lateral axis stretched (ground
    #: classes run in strips along the robot's path); 1 = plain nearest neighbour
    fallback_ground_lateral_scale: float = Field(4.0, ge=1.0)
    pedestrian_box_margin_m: float = Field(0.15, ge=0)
    #: ground consistency: road / terrain votes farther than this from the local ground are rejected
    ground_max_deviation_m: float = Field(0.3, gt=0)
    ground_cell_m: float = Field(1.0, gt=0)
    ground_neighbourhood_cells: int = Field(1, ge=0)
    ground_quantile: float = Field(0.5, ge=0, le=1)
    ground_classes: list[str] = ["road", "terrain"]
    min_votes: int = Field(1, ge=1)
    freespace: FreeSpaceConfig = FreeSpaceConfig()


class FuseConfig(Strict):
    grid: GridConfig = GridConfig()
    body_source: Literal["fit", "ground-truth"] = "fit"
    #: ground-truth bodies: fuse only people the sensors observe (>= this many LiDAR returns and
    #: some pixels in cam0), the people a real pipeline can annotate; 0 = every simulated person
    gt_min_points: int = Field(10, ge=0)
    camera_mask: bool = True
    #: exact per-pixel ray walks or a depth buffer (auto: rays for voxels >= 0.1 m)
    camera_method: Literal["auto", "rays", "zbuffer"] = "auto"
    camera_pixel_stride: int | None = Field(None, ge=1)


class ExportConfig(Strict):
    formats: list[Literal["occ3d", "nuscenes"]] = ["occ3d"]
    nuscenes_version: Literal["v1.0-trainval", "v1.0-mini", "v1.0-test"] = "v1.0-trainval"
    scene_prefix: str = "coda"
    val_sequences: list[str] = Field(default_factory=list)


class OutputConfig(Strict):
    root: Path = Path("demo-out")
    frames_per_chunk: int = Field(50, ge=1)


class DaskConfig(Strict):
    runner: Literal["thread", "dask"] = "thread"
    workers: int = Field(2, ge=1)
    threads_per_worker: int = Field(1, ge=1)
    address: str | None = None
    memory_limit: str = "4GiB"
    #: route the fit stage to workers started with `--resources GPU=1`
    gpu_fit: bool = False


class Config(Strict):
    dataset: DatasetConfig = DatasetConfig()
    classes: list[ClassEntry]
    detect: DetectConfig = DetectConfig()
    track: TrackConfig = TrackConfig()
    fit: FitConfig = FitConfig()
    map: MapConfig = MapConfig()
    fuse: FuseConfig = FuseConfig()
    export: ExportConfig = ExportConfig()
    output: OutputConfig = OutputConfig()
    dask: DaskConfig = DaskConfig()

    @field_validator("classes")
    @classmethod
    def _classes_contiguous_free_last(cls, classes: list[ClassEntry]) -> list[ClassEntry]:
        ids = [c.id for c in classes]
        if ids != list(range(len(classes))):
            raise ValueError(f"class ids must be 0..{len(classes) - 1} in order, got {ids}")
        names = [c.name for c in classes]
        if len(set(names)) != len(names):
            raise ValueError(f"class names must be unique, got {names}")
        if names[-1] != "free":
            raise ValueError(f"the last class must be 'free' (Occ3D convention), got {names[-1]!r}")
        if "pedestrian" not in names:
            raise ValueError("a 'pedestrian' class is required")
        return classes

    @model_validator(mode="after")
    def _mapping_targets_known(self) -> Config:
        names = {c.name for c in self.classes} - {"free"}
        for name in self.map.ground_classes:
            if name not in names:
                raise ValueError(f"map.ground_classes: {name!r} is not an occupied class")
        for cs_id, name in self.map.cityscapes_to_class.items():
            if not 0 <= cs_id <= 18:
                raise ValueError(f"map.cityscapes_to_class: Cityscapes train id {cs_id} not in 0..18")
            if name not in names:
                raise ValueError(
                    f"map.cityscapes_to_class[{cs_id}] = {name!r} is not an occupied class"
                )
        return self

    def class_id(self, name: str) -> int:
        for c in self.classes:
            if c.name == name:
                return c.id
        raise KeyError(name)

    def stage_slice(self, stage: str) -> dict[str, Any]:
        """The part of the config a stage reads: the input of its cache key."""
        dump = self.model_dump(mode="json")
        slices = {
            "detect": ("dataset", "detect"),
            "track": ("track",),
            "fit": ("fit",),
            "map": ("map", "classes"),
            "fuse": ("fuse", "classes", "output.frames_per_chunk"),
            "export": ("export",),
        }
        out: dict[str, Any] = {}
        for key in slices[stage]:
            head, _, tail = key.partition(".")
            out[key] = dump[head][tail] if tail else dump[head]
        if stage == "detect":  # where the data lives is not what it is: the fingerprint covers it
            out["dataset"] = {k: v for k, v in out["dataset"].items() if k not in ("root", "sequences")}
        if stage == "fit":
            out["weights"] = self.fit.weights.model_dump(mode="json")
        return out


def config_hash(config: Config, content_only: bool = False) -> str:
    """sha256 (first 16 hex) of the canonical JSON of the resolved config.

    content_only: leave out what does not change a single output byte (where the data and the
    output store live, which sequences are selected, how many workers run). This is the hash
    written beside the data, so the same inputs give byte-identical outputs whatever the runner.
    """
    dump = config.model_dump(mode="json")
    if content_only:
        dump.pop("dask")
        dump["output"].pop("root")
        for key in ("root", "sequences"):
            dump["dataset"].pop(key)
    blob = json.dumps(dump, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


class ConfigError(ValueError):
    """A config file failed to validate; ``errors`` holds (key path, message) pairs."""

    def __init__(self, source: str, errors: list[tuple[str, str]]):
        self.source = source
        self.errors = errors
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
        raw = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ConfigError(str(path), [("", "file not found")]) from None
    except yaml.YAMLError as exc:
        raise ConfigError(str(path), [("", f"invalid YAML: {exc}")]) from None
    raw = raw or {}
    if not isinstance(raw, dict):
        raise ConfigError(str(path), [("", f"expected a mapping at top level, got {type(raw).__name__}")])
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
    tree = read_config_dict(path)
    for dotted, value in (overrides or {}).items():
        _set_dotted(tree, dotted, value)
    try:
        return Config.model_validate(tree)
    except ValidationError as exc:
        errors = []
        for err in exc.errors():
            loc = ".".join(str(p) for p in err["loc"])
            msg = err["msg"]
            if err["type"] == "extra_forbidden":
                msg = "unknown key (misspelled?)"
            errors.append((loc or "<root>", msg))
        raise ConfigError(str(path), errors) from None
