"""Providers: objects built from a stage's inputs, one class per kind of model output.

Perception (detect): a provider answers for one sequence, frame by frame: ``image(frame)`` gives the
frame's 2D perception (and, for the oracle, which ground-truth person each detection is),
``lidar(frame)`` its LiDAR pedestrian boxes; ``frame`` is the reader's
:class:`storage.sequence_data.Frame`.
Initial body estimates (fit): ``available(tracks)`` says which rows of the track product have an
estimate, ``estimates(tracks, rows)`` gives them (cam frame).

A new model adapter is a new spec class in flows/pipeline/inputs.py (its settings, hence its cache
key) and a new provider class here, registered in the table of its kind.
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

import numpy as np

from flows.pipeline.inputs import (
    CliffSpec,
    ImageSpec,
    InitSpec,
    LidarClustersSpec,
    LidarDetectionsSpec,
    LidarKeypointsInitSpec,
    ModelsSpec,
    NoDetectionsSpec,
    OracleInitSpec,
    OracleSpec,
    PrecomputedSpec,
)
from flows.stages.common import frame_rng, is_night
from flows.stages.models import (
    cliff_estimator,
    gt_index_by_boxes,
    lidar_proposals,
    model_perception,
)
from storage.cliff_files import CliffFileError, cliff_path, read_cliff_estimates
from storage.gt import read_frame_gt
from storage.perception_files import PrecomputedPerception
from storage.products import Tracks
from storage.sequence_data import Frame
from storage.sources import SequenceSource
from tasks.body.params import BodyParams
from tasks.fit.init_oracle import cliff_to_params, oracle_initial_estimate
from tasks.fit.reframe import reframe_params
from tasks.perception.lidar_clusters import detect_pedestrians_lidar
from tasks.perception.oracle import oracle_image_perception, oracle_lidar_detections
from tasks.perception.types import ImagePerception, LidarDetections


class ImageProvider(Protocol):
    def image(
        self, frame: Frame, lidar: LidarDetections
    ) -> tuple[ImagePerception, np.ndarray | None]:
        """The frame's 2D perception (given its LiDAR boxes), and (D,) int64 ground-truth rows
        (synthetic data) or None."""


class LidarProvider(Protocol):
    def lidar(self, frame: Frame) -> LidarDetections: ...


class OracleImage:
    """Ground truth + the oracle's noise model (synthetic data only)."""

    def __init__(self, spec: OracleSpec, seq: SequenceSource):
        self.spec, self.seq, self.night = spec, seq, is_night(seq)

    def image(
        self, frame: Frame, lidar: LidarDetections | None = None
    ) -> tuple[ImagePerception, np.ndarray]:
        gt = read_frame_gt(self.seq.root, self.seq.sequence, frame.index)
        rng = frame_rng(self.spec.seed, self.seq.sequence, frame.index, 1)
        return oracle_image_perception(
            gt.box2d,
            gt.keypoints,
            gt.visible_fraction,
            np.linalg.norm(gt.box_center, axis=1),
            gt.track_id,
            gt.cam0_instance,
            gt.cam0_semantic,
            rng,
            night=self.night,
            noise=self.spec.noise,
        )


class OracleLidar(OracleImage):
    def lidar(self, frame: Frame) -> LidarDetections:
        gt = read_frame_gt(self.seq.root, self.seq.sequence, frame.index)
        counts = np.array([(gt.point_instance == t).sum() for t in gt.track_id], np.int64)
        rng = frame_rng(self.spec.seed, self.seq.sequence, frame.index, 2)
        return oracle_lidar_detections(
            gt.box_center, gt.box_size, gt.box_yaw, counts, rng, noise=self.spec.noise
        )[0]


class PrecomputedFiles:
    """A model's outputs read from files (storage/PERCEPTION_FORMAT.md), keyed by raw frame."""

    def __init__(self, spec: PrecomputedSpec, seq: SequenceSource):
        self.files = PrecomputedPerception(Path(spec.directory) / seq.sequence)

    def image(self, frame: Frame, lidar: LidarDetections) -> tuple[ImagePerception, None]:
        return ImagePerception(**self.files.image(frame.index)), None

    def lidar(self, frame: Frame) -> LidarDetections:
        return LidarDetections(**self.files.lidar(frame.index))


class LidarClusters:
    """The weight-free LiDAR detector on the frame's sweep."""

    def __init__(self, spec: LidarClustersSpec, seq: SequenceSource):
        self.params = spec.params

    def lidar(self, frame: Frame) -> LidarDetections:
        return detect_pedestrians_lidar(frame.points_lidar, self.params)


class NoLidar:
    def __init__(self, spec: NoDetectionsSpec, seq: SequenceSource):
        pass

    def lidar(self, frame: Frame) -> LidarDetections:
        return LidarDetections.empty()


class ModelsImage:
    """Real networks on the frame's camera image (flows/stages/models.py); LiDAR boxes as the
    proposals when the detector is 'lidar'; with the oracle's semantics (synthetic data) the
    detections take ground-truth identities by box."""

    def __init__(self, spec: ModelsSpec, seq: SequenceSource):
        self.spec, self.seq = spec, seq
        self.cam = seq.info.calibration.cameras[spec.camera]
        self.oracle = OracleImage(spec.oracle, seq) if spec.oracle is not None else None

    def image(
        self, frame: Frame, lidar: LidarDetections
    ) -> tuple[ImagePerception, np.ndarray | None]:
        m, cam = self.spec.models, self.cam
        semantic = self.oracle.image(frame)[0].semantic if self.oracle is not None else None
        rgb = self.seq.image(self.spec.camera, frame.index)
        proposals = lidar_proposals(lidar, cam) if m.detector.kind == "lidar" else None
        image = model_perception(m)(rgb, proposals, semantic)
        if self.oracle is None:
            return image, None
        gt = read_frame_gt(self.seq.root, self.seq.sequence, frame.index)
        return image, gt_index_by_boxes(image.boxes_xyxy, gt.box2d)


IMAGE_PROVIDERS = {
    OracleSpec: OracleImage,
    PrecomputedSpec: PrecomputedFiles,
    ModelsSpec: ModelsImage,
}
LIDAR_PROVIDERS = {
    OracleSpec: OracleLidar,
    PrecomputedSpec: PrecomputedFiles,
    LidarClustersSpec: LidarClusters,
    NoDetectionsSpec: NoLidar,
}


def image_provider(spec: ImageSpec, seq: SequenceSource) -> ImageProvider:
    return IMAGE_PROVIDERS[type(spec)](spec, seq)


def lidar_provider(spec: LidarDetectionsSpec, seq: SequenceSource) -> LidarProvider:
    return LIDAR_PROVIDERS[type(spec)](spec, seq)


class OracleInit:
    """The oracle's initial estimates (synthetic data): the ground-truth bodies perturbed like a
    monocular regressor; a false positive has none. One generator per batch of rows."""

    def __init__(self, spec: OracleInitSpec, seq: SequenceSource, model, camera):
        self.spec, self.seq, self.model, self.camera = spec, seq, model, camera

    def available(self, tracks: Tracks) -> np.ndarray:
        return np.flatnonzero(tracks.gt_index >= 0)

    def estimates(self, tracks: Tracks, rows: np.ndarray) -> BodyParams:
        truths, bodies = [], {}  # one read per frame (a frame's file holds every person)
        for r in rows:
            f = int(tracks.frame[r])
            if f not in bodies:
                bodies[f] = BodyParams.of(read_frame_gt(self.seq.root, self.seq.sequence, f))
            truths.append(bodies[f].take([int(tracks.gt_index[r])]))
        truth = BodyParams.concat(truths)
        rng = frame_rng(self.spec.seed, self.seq.sequence, int(rows[0]), 3)
        return oracle_initial_estimate(
            self.model, reframe_params(self.model, truth, self.camera.T_cam_from_lidar), rng
        )


class PrecomputedCliff:
    """CLIFF outputs precomputed by the user (``<directory>/<sequence>/cliff.parquet``), keyed by
    (frame, det_index), converted with the sequence's calibrated intrinsics."""

    def __init__(self, spec: PrecomputedSpec, seq: SequenceSource, model, camera):
        self.path = cliff_path(spec.directory, seq.sequence)
        self.est = read_cliff_estimates(self.path)
        self.K = camera.K
        self.where = {
            key: i
            for i, key in enumerate(zip(self.est["frame"].tolist(), self.est["det_index"].tolist()))
        }

    def _index(self, tracks: Tracks, rows) -> list[int | None]:
        return [self.where.get((int(tracks.frame[r]), int(tracks.det_index[r]))) for r in rows]

    def available(self, tracks: Tracks) -> np.ndarray:
        """Rows with an estimate. A file with no estimate at all for a sequence with tracked
        persons is refused (it would publish the sequence without a single body, silently)."""
        rows = np.arange(len(tracks.track_id))
        if len(rows) and not len(self.est["frame"]):
            raise CliffFileError(
                f"{self.path}: holds no CLIFF estimate, but {len(rows)} tracked detection(s) are "
                "to be fitted: write the estimates (storage/PERCEPTION_FORMAT.md) or set "
                "fit.init_provider to oracle"
            )
        return rows[[i is not None for i in self._index(tracks, rows)]].astype(np.int64)

    def estimates(self, tracks: Tracks, rows: np.ndarray) -> BodyParams:
        i = np.array(self._index(tracks, rows), np.int64)
        e = self.est
        return cliff_to_params(
            e["rotmats"][i].reshape(-1, 24, 3, 3),
            e["betas"][i].reshape(-1, 10),
            e["cam_crop"][i].reshape(-1, 3),
            e["bbox_center"][i].reshape(-1, 2),
            e["bbox_size"][i],
            self.K,
            e["transl"][i].reshape(-1, 3),
            e["has_transl"][i],
        )


class CliffModel:
    """A CLIFF export on each tracked box (one image read per frame of the batch)."""

    def __init__(self, spec: CliffSpec, seq: SequenceSource, model, camera):
        self.spec, self.seq, self.camera = spec, seq, camera
        self.at = {raw: k for k, raw in enumerate(seq.info.frame_indices)}

    def available(self, tracks: Tracks) -> np.ndarray:
        return np.arange(len(tracks.track_id), dtype=np.int64)

    def estimates(self, tracks: Tracks, rows: np.ndarray) -> BodyParams:
        rows, cam = np.asarray(rows, np.int64), self.camera
        cliff, parts = cliff_estimator(self.spec.path, self.spec.device), []
        for raw in dict.fromkeys(tracks.frame[rows].tolist()):  # frames in order of first row
            here = rows[tracks.frame[rows] == raw]
            frame = self.seq.frame(self.at[int(raw)])
            rgb = self.seq.image(cam.name, frame.index)
            parts.append((here, cliff(rgb, tracks.boxes_xyxy[here], cam.K)))
        order = np.argsort(np.concatenate([h for h, _ in parts]), kind="stable")
        return BodyParams.concat(p for _, p in parts).take(order)


class WeightFree:
    """No estimates from elsewhere: the fit computes its starts from each person's LiDAR points
    and keypoints (tasks/fit/init_lidar.py), so every row can be fitted."""

    def __init__(self, spec: LidarKeypointsInitSpec, seq: SequenceSource, model, camera):
        pass

    def available(self, tracks: Tracks) -> np.ndarray:
        return np.arange(len(tracks.track_id), dtype=np.int64)


INIT_PROVIDERS = {
    OracleInitSpec: OracleInit,
    PrecomputedSpec: PrecomputedCliff,
    CliffSpec: CliffModel,
    LidarKeypointsInitSpec: WeightFree,
}


def init_provider(spec: InitSpec, seq: SequenceSource, model, camera):
    return INIT_PROVIDERS[type(spec)](spec, seq, model, camera)
