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
from flows.pipeline.dag import CODE_VERSIONS, STAGES
from storage.coda import CodaSequence
from tasks.conventions import CLASS_NAMES
from tasks.fit.settings import FitSettings
from tasks.fit.weights import FitWeights
from tasks.occupancy.grid import GridSpec
from tasks.occupancy.settings import FreeSpaceParams, FuseSettings, MapParams
from tasks.perception.lidar_clusters import LidarClusterParams
from tasks.perception.oracle import OracleNoise
from tasks.perception.person_points import PersonPointParams
from tasks.track.ocsort import TrackerParams
from tasks.track.offline import OfflineParams, WorldCheck
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
    fingerprint, so changing one sequence's lighting reruns that sequence only."""

    root: Path
    sequence: str
    lighting: str | None = None

    def fingerprint(self, files_fingerprint: str) -> str:
        if self.lighting is None:
            return files_fingerprint
        return hashlib.sha256(f"{files_fingerprint}/lighting={self.lighting}".encode()).hexdigest()[
            :32
        ]


def sequence_ref(config: Config, sequence: str) -> SequenceRef:
    return SequenceRef(
        Path(config.dataset.root), str(sequence), config.dataset.lighting.get(str(sequence))
    )


def open_sequence(config: Config, sequence: str) -> CodaSequence:
    """The reader of one sequence as the config says to read it (for commands; stages get their
    :class:`Source` and :class:`SequenceRef`)."""
    return source(config).open(sequence_ref(config, sequence))


@dataclass(frozen=True)
class Source:
    """How a sequence's raw files are read (the dataset root is not part of it: the input
    fingerprint covers the files' content wherever they are)."""

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

    def open(self, ref: SequenceRef) -> CodaSequence:
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


def source(config: Config) -> Source:
    ds = config.dataset
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
InitSpec = OracleInitSpec | PrecomputedSpec | CliffSpec


# ---- the stages ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DetectInputs:
    source: Source
    image: ImageSpec
    lidar: LidarDetectionsSpec
    #: frames with bad input are left out; the stage fails when more than this share of them are
    max_failed_frame_share: float


@dataclass(frozen=True)
class TrackInputs:
    source: Source
    #: the frame-counted gates at dataset.rate_hz (tasks.track.rate: the same values at 5 Hz)
    tracker: TrackerParams
    offline: OfflineParams
    world_check: WorldCheck
    person_points: PersonPointParams


@dataclass(frozen=True)
class FitInputs:
    source: Source
    #: initial estimates: the oracle (perturbed ground truth) or precomputed CLIFF files
    init: InitSpec
    body: BodyModelFiles
    #: the loss weights of the chosen preset (its name, and the weights resolved)
    preset: str
    weights: FitWeights
    settings: FitSettings


@dataclass(frozen=True)
class MapInputs:
    source: Source
    #: Cityscapes train id -> our class id, sorted pairs
    class_lut: tuple[tuple[int, int], ...]
    #: ground classes as class ids
    ground_class_ids: tuple[int, ...]
    settings: MapParams
    freespace: FreeSpaceParams
    #: LiDAR boxes confirmed by an image detection at this IoU remove points in the camera view
    assoc_min_iou: float


@dataclass(frozen=True)
class FuseInputs:
    source: Source
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
    source: Source
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
        source(config), tracker, offline, check, t.person_points.to(PersonPointParams)
    )


def fit_inputs(config: Config) -> FitInputs:
    f = config.fit
    init = {
        "oracle": lambda: OracleInitSpec(f.seed),
        "precomputed": lambda: PrecomputedSpec(str(f.init_dir)),
        "cliff": lambda: CliffSpec(str(f.cliff_path), f.device),
    }[f.init_provider]()
    return FitInputs(source(config), init, _body(config), f.preset, f.weights, f.to(FitSettings))


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
