"""Stage inputs: everything a stage reads from the config, and so everything its cache key covers.

One frozen object per stage, made from the resolved config by one function per stage (the
``INPUTS`` table). A stage function receives its inputs object, its upstream products and where
the sequence lives, never the config, so it cannot depend on a setting its key does not cover:

    key(sequence, stage) = H(stage, code version, canonical JSON of the inputs object,
                             fingerprint of the input files (detect) / upstream keys (the others))

Settings in no stage's inputs change no output byte: where the data and the output store live,
which sequences are selected, how many workers run (``RUNTIME_KEYS``). Where a provider is chosen
by name, the inputs hold only the chosen provider's settings (changing the oracle's noise does not
rerun a detect stage that reads precomputed files).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from pydantic import BaseModel, TypeAdapter
from pydantic.dataclasses import is_pydantic_dataclass

from configs.schema import Config, ModelsConfig
from configs.sources import LogSettings
from flows.pipeline.dag import CODE_VERSIONS, STAGES
from storage.sources import SequenceSource
from storage.sources.coda import READER_VERSION as CODA_READER_VERSION
from storage.sources.coda import (
    CodaSequence,
    check_dataset_root,
    frame_number,
    sequence_ids,
    sequence_layout,
)
from storage.sources.log.bag import LogFormatError, find_logs, holds_logs
from storage.sources.log.reader import READER_VERSION as LOG_READER_VERSION
from storage.sources.log.reader import LogSequence
from tasks.conventions import CLASS_NAMES
from tasks.fit.settings import (
    FitSettings,
    FlipSettings,
    GapSettings,
    InitLidarSettings,
    RefineSettings,
)
from tasks.fit.weights import FitWeights
from tasks.occupancy.geometric_classes import GeometricClassSettings
from tasks.occupancy.grid import GridSpec
from tasks.occupancy.settings import FreeSpaceParams, FuseSettings, MapParams
from tasks.perception.lidar_clusters import LidarClusterParams
from tasks.perception.oracle import OracleNoise
from tasks.perception.person_points import PersonPointParams
from tasks.track.ocsort import TrackerParams
from tasks.track.offline import Confirmation, OfflineParams, WorldCheck
from tasks.track.rate import GateRate, gates_at_rate

#: config keys that only say where things are or how many workers run (no stage reads them)
RUNTIME_KEYS = ("dataset.root", "dataset.sequences", "output.root", "dask")
#: config keys about one sequence each: in its fingerprint (SequenceRef), not in stage inputs
PER_SEQUENCE_KEYS = ("dataset.lighting",)


def to_jsonable(value: Any) -> Any:
    """Plain JSON of an inputs object: dataclasses (tagged with their type, so two providers with
    the same fields differ: its ``KEY_TYPE`` where it has one, else its class name), config
    sections held whole (``detect.models``: their config JSON), tuples, paths."""
    if is_pydantic_dataclass(type(value)) or isinstance(value, BaseModel):
        return TypeAdapter(type(value)).dump_python(value, mode="json")
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {
            "type": getattr(value, "KEY_TYPE", type(value).__name__),
            **{f.name: to_jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)},
        }
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    return value


def inputs_hash(inputs: Any) -> str:
    """sha256 (first 16 hex) of the canonical JSON of an inputs object."""
    blob = json.dumps(to_jsonable(inputs), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


# ---- what every stage reads: the sequence ----------------------------------------------------------


@dataclass(frozen=True)
class SequenceRef:
    """One sequence: where it lives and what the config says about it alone (its entry in
    ``dataset.lighting``). In no stage's inputs: the plan folds the lighting into the sequence's
    fingerprint, so changing one sequence's lighting reruns that sequence only. ``cache_dir``:
    where a source keeps what it derives from its input (a log's index, its LiDAR-odometry
    trajectory: OUT/.cache), keyed by the input's fingerprint; never part of a key."""

    root: Path
    sequence: str
    lighting: str | None = None
    cache_dir: Path | None = None

    def fingerprint(self, files_fingerprint: str) -> str:
        if self.lighting is None:
            return files_fingerprint
        return hashlib.sha256(f"{files_fingerprint}/lighting={self.lighting}".encode()).hexdigest()[
            :32
        ]


def sequence_ref(config: Config, sequence: str) -> SequenceRef:
    return SequenceRef(
        Path(config.dataset.root),
        str(sequence),
        config.dataset.lighting.get(str(sequence)),
        Path(config.output.root) / ".cache",
    )


def open_sequence(config: Config, sequence: str, with_poses: bool = True) -> SequenceSource:
    """The reader of one sequence as the config says to read it (for commands; stages get their
    :class:`Source` and :class:`SequenceRef`). ``with_poses`` False: a log's LiDAR-odometry poses
    are not computed (check-data)."""
    return source(config).open(sequence_ref(config, sequence), with_poses=with_poses)


@dataclass(frozen=True)
class Source:
    """How a sequence of the CODa layout is read (the dataset root is not part of it: the input
    fingerprint covers the files' content wherever they are). Its kind's dataset-level questions
    (which sequences a root holds, where a sequence's files are) are its methods too."""

    kind: ClassVar[str] = "coda"
    #: version of what opening a sequence checks (a planner memo of another is not used)
    reader_version: ClassVar[str] = CODA_READER_VERSION

    lidar_source: str
    image_source: str
    camera: str
    frame_stride: int
    min_range_m: float
    max_range_m: float
    #: which raw frames a sequence has: those with a sweep file, or those the metadata lists
    frames: str
    #: LiDAR height above the ground where calib_os1_to_base.yaml is missing
    lidar_height_m: float

    def sequence_ids(self, root: Path) -> list[str]:
        return sequence_ids(root)

    def check_root(self, root: Path) -> list[str]:
        """The sequence ids of a dataset root; an InputError when it holds none."""
        return check_dataset_root(root)

    def frame_of(self, path: Path) -> int | None:
        """The raw frame a file of the layout belongs to (for error messages), or None."""
        return frame_number(path)

    def layout(self, ref: SequenceRef) -> list[tuple[str, bool]]:
        """(path, is a folder) of everything the sequence's files live in: its stat signature."""
        return sequence_layout(ref.root, ref.sequence, self.lidar_source, self.image_source)

    def open(self, ref: SequenceRef, with_poses: bool = True) -> CodaSequence:
        """The sequence ``ref``, read this way."""
        return CodaSequence(
            ref.root,
            ref.sequence,
            frame_stride=self.frame_stride,
            lidar_source=self.lidar_source,
            image_source=self.image_source,
            min_range_m=self.min_range_m,
            max_range_m=self.max_range_m,
            frames=self.frames,
            lighting=ref.lighting,
            lidar_height_m=self.lidar_height_m,
        )


@dataclass(frozen=True)
class LogSource:
    """How a robot log is read as a sequence (``dataset.log``; storage/sources/log): each log
    (a .bag or .mcap file, or a ROS 2 bag folder) directly in the dataset root, or the root
    itself, is a sequence named by its stem."""

    kind: ClassVar[str] = "log"
    reader_version: ClassVar[str] = LOG_READER_VERSION

    camera: str
    frame_stride: int
    min_range_m: float
    max_range_m: float
    #: LiDAR height above the ground where the TF tree has no base frame
    lidar_height_m: float
    log: LogSettings

    def sequence_ids(self, root: Path) -> list[str]:
        return list(find_logs(root))

    def check_root(self, root: Path) -> list[str]:
        root = Path(root)
        if not root.exists():
            raise LogFormatError(f"dataset root {root} does not exist", root)
        ids = self.sequence_ids(root)
        if not ids:
            raise LogFormatError(
                f"dataset root {root} holds no log (expected .bag / .mcap files or ROS 2 bag "
                "folders with a metadata.yaml, or one of them as the root)",
                root,
            )
        return ids

    def _path(self, ref: SequenceRef) -> Path:
        logs = find_logs(ref.root)
        if ref.sequence not in logs:
            raise LogFormatError(
                f"unknown sequence {ref.sequence!r} in {ref.root}: no log of that name "
                f"(logs: {', '.join(logs) or 'none'})",
                ref.root,
            )
        return logs[ref.sequence]

    def frame_of(self, path: Path) -> int | None:
        return None

    def layout(self, ref: SequenceRef) -> list[tuple[str, bool]]:
        """The log (a file, or a bag folder to list) and the ground truth beside it."""
        import os

        path = self._path(ref)
        return [
            (os.fspath(path), path.is_dir()),
            (os.fspath(path.parent / "gt" / ref.sequence), True),
        ]

    def open(self, ref: SequenceRef, with_poses: bool = True) -> LogSequence:
        return LogSequence(
            self._path(ref),
            ref.sequence,
            settings=self.log,
            frame_stride=self.frame_stride,
            min_range_m=self.min_range_m,
            max_range_m=self.max_range_m,
            cameras=("cam0", "cam1"),
            lighting=ref.lighting,
            lidar_height_m=self.lidar_height_m,
            cache_dir=ref.cache_dir,
            with_poses=with_poses,
        )


@dataclass(frozen=True)
class Runtime:
    """How a stage runs, not what it computes (in no key): GPU routing, thread counts."""

    #: route the fit's batches to workers started with ``--resources GPU=1``
    gpu_fit: bool = False
    #: route the detect stage's frame chunks there too (image_provider 'models' on CUDA)
    gpu_detect: bool = False
    #: threads one unit's kernels may use (the occupancy kernels' pools, BLAS / OpenMP); torch
    #: always runs one thread (its results depend on its thread count: parallelism comes from the
    #: workers, and the bytes stay the same for any number of them)
    threads: int = 1


def runtime(config: Config) -> Runtime:
    """A unit's share of its machine: ``dask.threads_per_worker`` on Dask workers; with the thread
    runner, the cores divided among the ``dask.workers`` units running at once."""
    d = config.dask
    if d.runner == "dask" or d.address:
        threads = d.threads_per_worker
    else:
        threads = max(1, (os.cpu_count() or 1) // max(1, d.workers))
    return Runtime(gpu_fit=d.gpu_fit, gpu_detect=d.gpu_detect, threads=threads)


def source(config: Config) -> Source | LogSource:
    """How the dataset's sequences are read: ``dataset.format``, or with "auto" robot logs when
    the root is a log or holds logs, else the CODa layout. Only the chosen format's settings are
    in the stage inputs (a CODa dataset's keys do not change with dataset.log)."""
    ds = config.dataset
    if ds.format == "log" or (ds.format == "auto" and holds_logs(Path(ds.root))):
        return LogSource(
            ds.camera,
            ds.frame_stride,
            ds.min_range_m,
            ds.max_range_m,
            ds.lidar_height_m,
            ds.log.settings(),
        )
    return Source(
        ds.lidar_source,
        ds.image_source,
        ds.camera,
        ds.frame_stride,
        ds.min_range_m,
        ds.max_range_m,
        ds.frames,
        ds.lidar_height_m,
    )


# ---- provider specifications, each with only its own settings -------------------------------------
#
# A spec says which provider a stage uses and with which settings (flows/stages/providers.py builds
# the provider from it). KEY_TYPE: the spec's type in the cache key's JSON, the name the class had
# when the keys were first written (renaming a class must not rerun every stage).


@dataclass(frozen=True)
class OracleSpec:
    """Detections from the synthetic ground truth with the oracle's noise model."""

    NAME: ClassVar[str] = "oracle"
    KEY_TYPE: ClassVar[str] = "OracleProvider"

    noise: OracleNoise
    seed: int


@dataclass(frozen=True)
class PrecomputedSpec:
    """Model outputs read from files (storage/PERCEPTION_FORMAT.md) under ``directory``."""

    NAME: ClassVar[str] = "precomputed"
    KEY_TYPE: ClassVar[str] = "PrecomputedProvider"

    directory: str


@dataclass(frozen=True)
class LidarClustersSpec:
    """The weight-free LiDAR pedestrian detector."""

    NAME: ClassVar[str] = "lidar-clusters"
    KEY_TYPE: ClassVar[str] = "LidarClustersProvider"

    params: LidarClusterParams


@dataclass(frozen=True)
class ModelsSpec:
    """Real networks from local files (the ``detect.models`` section; model files are named by
    path: replacing a file at the same path is not seen by the key), with the oracle's semantics
    and ground-truth identities where ``models.semantic.kind`` is 'oracle' (synthetic data)."""

    NAME: ClassVar[str] = "models"
    KEY_TYPE: ClassVar[str] = "ModelsProvider"

    models: ModelsConfig
    oracle: OracleSpec | None
    #: the camera whose images the networks see (dataset.camera)
    camera: str


@dataclass(frozen=True)
class CliffSpec:
    """Initial bodies from a CLIFF ONNX export run on each tracked box."""

    NAME: ClassVar[str] = "cliff"
    KEY_TYPE: ClassVar[str] = "CliffProvider"

    path: str
    device: str


@dataclass(frozen=True)
class OracleInitSpec:
    """Initial body estimates from the synthetic ground truth, perturbed like a monocular
    regressor (tasks.fit.init_oracle)."""

    NAME: ClassVar[str] = "oracle"
    KEY_TYPE: ClassVar[str] = "OracleInitProvider"

    seed: int


@dataclass(frozen=True)
class LidarKeypointsInitSpec:
    """Initial body estimates from each person's LiDAR points and 2D keypoints, no network and
    no ground truth (tasks.fit.init_lidar; its settings are FitInputs.init_lidar)."""

    NAME: ClassVar[str] = "lidar-keypoints"


@dataclass(frozen=True)
class NoDetectionsSpec:
    """No detections of this kind."""

    NAME: ClassVar[str] = "none"
    KEY_TYPE: ClassVar[str] = "NoProvider"


@dataclass(frozen=True)
class BodyModelFiles:
    """The body model and pose prior: the user's official files, or (None) our procedural
    stand-ins in the same formats (made once per output store)."""

    body_model_path: str | None
    pose_prior_path: str | None


#: what each kind of provider can be
ImageSpec = OracleSpec | PrecomputedSpec | ModelsSpec
LidarDetectionsSpec = LidarClustersSpec | OracleSpec | PrecomputedSpec | NoDetectionsSpec
InitSpec = OracleInitSpec | PrecomputedSpec | CliffSpec | LidarKeypointsInitSpec


# ---- the stages ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DetectInputs:
    source: Source | LogSource
    image: ImageSpec
    lidar: LidarDetectionsSpec
    #: frames with bad input are left out; the stage fails when more than this share of them are
    max_failed_frame_share: float


@dataclass(frozen=True)
class TrackInputs:
    source: Source | LogSource
    #: the frame-counted gates at dataset.rate_hz (tasks.track.rate: the same values at 5 Hz)
    tracker: TrackerParams
    offline: OfflineParams
    world_check: WorldCheck
    person_points: PersonPointParams
    #: tracklets confirmed by one detection's evidence (image, LiDAR and keypoints agreeing)
    confirm: Confirmation


@dataclass(frozen=True)
class FitInputs:
    source: Source | LogSource
    #: initial estimates: the oracle (perturbed ground truth) or precomputed CLIFF files
    init: InitSpec
    body: BodyModelFiles
    #: the loss weights of the chosen preset (its name, and the weights resolved)
    preset: str
    weights: FitWeights
    settings: FitSettings
    #: the weight-free start (also scores the headings the swap decision weighs), the left /
    #: right swap decision, the temporal refinement and the gap filling
    init_lidar: InitLidarSettings
    flips: FlipSettings
    refine: RefineSettings
    gaps: GapSettings


@dataclass(frozen=True)
class MapInputs:
    source: Source | LogSource
    #: Cityscapes train id -> our class id, sorted pairs
    class_lut: tuple[tuple[int, int], ...]
    #: ground classes as class ids
    ground_class_ids: tuple[int, ...]
    settings: MapParams
    freespace: FreeSpaceParams
    #: LiDAR boxes confirmed by an image detection at this IoU remove points in the camera view
    assoc_min_iou: float
    #: where the points' labels come from (map.point_classes, "auto" resolved: camera, geometry,
    #: camera+geometry) and the geometry's settings
    point_classes: str = "camera"
    geometry: GeometricClassSettings = GeometricClassSettings()


@dataclass(frozen=True)
class FuseInputs:
    source: Source | LogSource
    grid: GridSpec
    body_source: str
    #: ground-truth bodies: people with fewer LiDAR returns are not fused
    gt_min_points: int
    fusion: FuseSettings
    frames_per_chunk: int
    #: the occupancy map's sensor model (its state queries need the threshold)
    freespace: FreeSpaceParams
    body: BodyModelFiles


@dataclass(frozen=True)
class ExportInputs:
    source: Source | LogSource
    body: BodyModelFiles
    #: what the published bytes were made from: a hash of every stage's inputs and code version
    #: (written as the sequences table's ``config_hash``)
    content_hash: str
    code_version: str


@dataclass(frozen=True)
class DatasetExportInputs:
    """The dataset-level exports (Occ3D / nuScenes) made after every sequence is published."""

    formats: tuple[str, ...]
    nuscenes_version: str
    scene_prefix: str
    val_sequences: tuple[str, ...]
    min_range_m: float
    infos_data_root: str | None


def _spec(name: str, config: Config, seed: int) -> Any:
    """The spec of the detect provider called ``name`` (detect.image_provider / lidar_provider)."""
    det = config.detect
    if name == "oracle":
        return OracleSpec(det.oracle.to(OracleNoise), seed)
    if name == "precomputed":
        return PrecomputedSpec(str(det.precomputed_dir))
    if name == "lidar-clusters":
        return LidarClustersSpec(det.lidar_clusters.to(LidarClusterParams))
    if name == "none":
        return NoDetectionsSpec()
    if name == "models":
        oracle = det.models.semantic.kind == "oracle"
        return ModelsSpec(
            det.models, _spec("oracle", config, seed) if oracle else None, config.dataset.camera
        )
    raise ValueError(f"unknown provider {name!r}")  # the schema's Literal types prevent this


def _body(config: Config) -> BodyModelFiles:
    f = config.fit
    return BodyModelFiles(
        None if f.body_model_path is None else str(f.body_model_path),
        None if f.pose_prior_path is None else str(f.pose_prior_path),
    )


def detect_inputs(config: Config) -> DetectInputs:
    det = config.detect
    return DetectInputs(
        source(config),
        _spec(det.image_provider, config, det.seed),
        _spec(det.lidar_provider, config, det.seed),
        det.max_failed_frame_share,
    )


def track_inputs(config: Config) -> TrackInputs:
    t = config.track
    tracker, offline, check = gates_at_rate(
        t.to(TrackerParams),
        t.to(OfflineParams),
        t.world_check.to(WorldCheck),
        config.dataset.rate_hz,
        t.to(GateRate),
    )
    return TrackInputs(
        source(config),
        tracker,
        offline,
        check,
        t.person_points.to(PersonPointParams),
        t.confirm.to(Confirmation),
    )


def fit_inputs(config: Config) -> FitInputs:
    f = config.fit
    init = {
        "oracle": lambda: OracleInitSpec(f.seed),
        "precomputed": lambda: PrecomputedSpec(str(f.init_dir)),
        "cliff": lambda: CliffSpec(str(f.cliff_path), f.device),
        "lidar-keypoints": LidarKeypointsInitSpec,
    }[f.init_provider]()
    return FitInputs(
        source(config),
        init,
        _body(config),
        f.preset,
        f.weights,
        f.to(FitSettings),
        f.init_lidar.to(InitLidarSettings),
        f.flips.to(FlipSettings),
        f.refine.to(RefineSettings),
        f.gaps.to(GapSettings),
    )


def point_classes(config: Config) -> str:
    """map.point_classes with "auto" resolved: camera+geometry where the detect stage gives no
    image semantics (image_provider 'models' with semantic.kind 'none'), else camera."""
    m, det = config.map, config.detect
    if m.point_classes != "auto":
        return m.point_classes
    no_semantics = det.image_provider == "models" and det.models.semantic.kind == "none"
    return "camera+geometry" if no_semantics else "camera"


def map_inputs(config: Config) -> MapInputs:
    m = config.map
    lut = tuple(sorted((int(k), CLASS_NAMES.index(v)) for k, v in m.cityscapes_to_class.items()))
    return MapInputs(
        source(config),
        lut,
        tuple(CLASS_NAMES.index(c) for c in m.ground_classes),
        m.to(MapParams),
        m.freespace.to(FreeSpaceParams),
        config.track.person_points.assoc_min_iou,
        point_classes(config),
        m.geometry.to(GeometricClassSettings),
    )


def fuse_inputs(config: Config) -> FuseInputs:
    fu = config.fuse
    return FuseInputs(
        source(config),
        fu.grid.spec(),
        fu.body_source,
        fu.gt_min_points,
        fu.to(FuseSettings),
        config.output.frames_per_chunk,
        config.map.freespace.to(FreeSpaceParams),
        _body(config),
    )


def export_inputs(config: Config) -> ExportInputs:
    upstream = {stage: INPUTS[stage](config) for stage in STAGES if stage != "export"}
    return ExportInputs(
        source(config),
        _body(config),
        inputs_hash([upstream, CODE_VERSIONS]),
        CODE_VERSIONS["export"],
    )


def dataset_export_inputs(config: Config) -> DatasetExportInputs:
    ex = config.export
    return DatasetExportInputs(
        tuple(ex.formats),
        ex.nuscenes_version,
        ex.scene_prefix,
        tuple(ex.val_sequences),
        config.dataset.min_range_m,
        ex.infos_data_root,
    )


#: a stage's inputs object (the type of ``StageContext.inputs``)
StageInputs = DetectInputs | TrackInputs | FitInputs | MapInputs | FuseInputs | ExportInputs

#: stage -> the function making its inputs object
INPUTS: dict[str, Callable[[Config], StageInputs]] = {
    "detect": detect_inputs,
    "track": track_inputs,
    "fit": fit_inputs,
    "map": map_inputs,
    "fuse": fuse_inputs,
    "export": export_inputs,
}


def stage_inputs(config: Config) -> dict[str, StageInputs]:
    """Every stage's inputs object."""
    return {stage: make(config) for stage, make in INPUTS.items()}
