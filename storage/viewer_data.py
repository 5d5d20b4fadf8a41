"""Everything the 3D viewer shows of one frame, read from a published dataset (and, where they
are still there, the raw sensor files and the simulator's ground truth beside them).

``src = ViewerSource(out)``; ``src.frame(sequence, k)`` -> :class:`FrameData`. ``k`` is the
frame index of the dataset (frames table ``frame``, the store's frame axis). Labels come from the
store and the tables; the LiDAR sweep and the camera image from the raw data root recorded in
``OUT/manifest.json`` (frames table paths are relative to it); ground truth from ``ROOT/gt/<seq>/``
when the data is simulated. A sensor file or ground truth that is not there is not an error: the
frame is shown without it and ``FrameData.notes`` says what is missing.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from storage.coda import read_lidar_bin
from storage.dataset import Dataset, open_dataset
from storage.export.common import recorded_source_root, resolve, sequence_info
from storage.files import InputError
from storage.gt import GTFormatError, gt_dir, read_frame_gt, read_sequence_gt
from storage.images import read_rgb
from storage.layout import StoreError
from storage.occupancy_store import read_frames


class ViewerInputError(StoreError):
    """A dataset, sequence or frame the viewer cannot show (names the path and the value)."""


@dataclass(frozen=True)
class GroundTruth:
    """The simulator's exact labels of a frame on the dataset's grid: occupancy (X, Y, Z) uint8,
    track_id (K,), vertices (K, V, 3) float32 base frame, faces (F, 3) int64."""

    occupancy: np.ndarray
    track_id: np.ndarray
    vertices: np.ndarray
    faces: np.ndarray


@dataclass(frozen=True)
class FrameData:
    """One frame as the viewer draws it (arrays as in storage/SCHEMA.md; base frame, metres).

    persons: rows of the instances table for this frame (track_id, box2d_xyxy, box3d_center,
    box3d_size, box3d_yaw, betas, global_orient, body_pose, transl, vx, vy). points_lidar (N, 3)
    float32 LiDAR frame or None; image (H, W, 3) uint8 or None; K (3, 3); T_base_from_cam0,
    T_base_from_lidar (4, 4); gt: ground truth on the same grid, or None. notes: what is not
    shown and why.
    """

    sequence: str
    frame: int
    raw_frame: int
    num_frames: int
    stamp_ns: int
    is_night: bool
    range_min: np.ndarray
    voxel_size_m: float
    semantics: np.ndarray
    instances: np.ndarray
    mask_lidar: np.ndarray
    mask_camera: np.ndarray
    velocity: np.ndarray
    persons: list[dict[str, Any]]
    K: np.ndarray
    width: int
    height: int
    T_base_from_cam0: np.ndarray
    T_base_from_lidar: np.ndarray
    points_lidar: np.ndarray | None = None
    image: np.ndarray | None = None
    gt: GroundTruth | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def grid_shape(self) -> tuple[int, int, int]:
        return tuple(int(n) for n in self.semantics.shape)  # type: ignore[return-value]


class ViewerSource:
    """A published dataset opened for viewing (raises ViewerInputError when ``out`` is not one
    or holds no sequence)."""

    def __init__(self, out: str | os.PathLike, data_root: str | os.PathLike | None = None):
        out = Path(out)
        if not out.exists():
            raise ViewerInputError(f"{out}: no such dataset folder")
        try:
            self.ds: Dataset = open_dataset(out)
        except StoreError as exc:
            raise ViewerInputError(
                f"{exc} (expected the output folder of `mobileocc rebuild`)"
            ) from None
        if not self.ds.sequences:
            raise ViewerInputError(f"{out}: no published sequence (run the pipeline first)")
        self.out = out
        self.data_root = Path(data_root) if data_root is not None else recorded_source_root(out)
        self._info: dict[str, Any] = {}
        self._gt_seq: dict[str, Any] = {}
        self._persons: dict[str, dict[int, list[dict[str, Any]]]] = {}

    @property
    def sequences(self) -> tuple[str, ...]:
        return self.ds.sequences

    def check_sequence(self, sequence: str) -> str:
        if sequence not in self.ds.sequences:
            raise ViewerInputError(
                f"dataset {self.out}: no sequence {sequence!r}; it has {list(self.ds.sequences)}"
            )
        return sequence

    def info(self, sequence: str):
        """The sequence's calibration and frames rows (storage.export.common.sequence_info)."""
        self.check_sequence(sequence)
        if sequence not in self._info:
            try:
                self._info[sequence] = sequence_info(self.ds, sequence)
            except ValueError as exc:
                raise ViewerInputError(str(exc)) from None
        return self._info[sequence]

    def num_frames(self, sequence: str) -> int:
        return len(self.info(sequence).frames)

    def check_frame(self, sequence: str, frame: int) -> int:
        n = self.num_frames(sequence)
        if not 0 <= int(frame) < n:
            raise ViewerInputError(
                f"dataset {self.out}: sequence {sequence!r} has no frame {frame}; its frames are "
                f"0..{n - 1} (the frames table's `frame`, not the raw CODa number)"
            )
        return int(frame)

    def version(self, sequence: str) -> str | None:
        """The published occupancy version of the sequence (``current.json``)."""
        return self.ds.store_path(sequence).stem

    def metadata(self, sequence: str) -> dict:
        """The raw sequence's metadata JSON ({} when the raw data is not there)."""
        if self.data_root is None:
            return {}
        path = self.data_root / "metadata" / f"{sequence}.json"
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError):
            return {}
        return data if isinstance(data, dict) else {}

    def persons(self, sequence: str) -> dict[int, list[dict[str, Any]]]:
        """frame -> its rows of the instances table (read once per sequence)."""
        self.check_sequence(sequence)
        if sequence not in self._persons:
            out: dict[int, list[dict[str, Any]]] = {}
            for row in self.ds.table("instances", sequence).to_pylist():
                out.setdefault(int(row["frame"]), []).append(row)
            self._persons[sequence] = out
        return self._persons[sequence]

    def frame(
        self, sequence: str, frame: int, sensors: bool = True, ground_truth: bool = True
    ) -> FrameData:
        """Frame ``frame`` (index) of ``sequence``; sensors: read the LiDAR sweep and the image;
        ground_truth: read the simulator's labels when there are some."""
        frame = self.check_frame(self.check_sequence(sequence), frame)
        info = self.info(sequence)
        row = info.frames[frame]
        attrs = self.ds.attrs(sequence)
        arrays = read_frames(self.ds.store_path(sequence), frame)
        persons = list(self.persons(sequence).get(frame, []))
        notes: list[str] = []
        points = image = gt = None
        if sensors:
            points, image = self._sensors(sequence, frame, row, info, notes)
        if ground_truth:
            gt = self._ground_truth(sequence, int(row["raw_frame"]), info, arrays, attrs, notes)
        return FrameData(
            sequence=sequence,
            frame=frame,
            raw_frame=int(row["raw_frame"]),
            num_frames=len(info.frames),
            stamp_ns=int(row["stamp_ns"]),
            is_night=bool(row.get("is_night")),
            range_min=np.asarray(attrs["range_min"], np.float64),
            voxel_size_m=float(attrs["voxel_size_m"]),
            semantics=arrays["semantics"][0],
            instances=arrays["instances"][0],
            mask_lidar=arrays["mask_lidar"][0],
            mask_camera=arrays["mask_camera"][0],
            velocity=arrays["velocity"][0],
            persons=persons,
            K=info.K,
            width=info.width,
            height=info.height,
            T_base_from_cam0=info.T_base_from_cam0,
            T_base_from_lidar=info.T_base_from_lidar,
            points_lidar=points,
            image=image,
            gt=gt,
            notes=notes,
        )

    def _sensors(self, sequence: str, frame: int, row: dict, info, notes: list[str]):
        points = image = None
        try:
            path = resolve(row.get("lidar_path"), self.data_root, "LiDAR", sequence, frame)
            points = read_lidar_bin(path, frame=int(row["raw_frame"])).points
        except (ValueError, OSError, InputError) as exc:
            notes.append(f"LiDAR sweep not shown: {exc}")
        try:
            path = resolve(row.get("cam0_path"), self.data_root, "cam0 image", sequence, frame)
            image = read_rgb(path, (info.width, info.height))
        except (ValueError, OSError) as exc:
            notes.append(f"camera image not shown: {exc}")
        return points, image

    def _ground_truth(self, sequence, raw_frame, info, arrays, attrs, notes):
        if self.data_root is None or not sequence.isdigit():
            return None
        if not (gt_dir(self.data_root, int(sequence)) / "sequence.npz").exists():
            return None  # real data: no ground truth, nothing to say
        try:
            if sequence not in self._gt_seq:
                self._gt_seq[sequence] = read_sequence_gt(self.data_root, int(sequence))
            gseq = self._gt_seq[sequence]
            gtf = read_frame_gt(self.data_root, int(sequence), raw_frame)
        except (GTFormatError, OSError) as exc:
            notes.append(f"ground truth not shown: {exc}")
            return None
        shape = arrays["semantics"].shape[1:]
        same = (
            tuple(gseq.grid_shape) == tuple(shape)
            and abs(gseq.grid_voxel_size_m - float(attrs["voxel_size_m"])) < 1e-9
            and np.allclose(gseq.grid_range_min, attrs["range_min"])
        )
        if not same:
            notes.append(
                f"ground truth not shown: its grid {tuple(gseq.grid_shape)} at "
                f"{gseq.grid_voxel_size_m} m is not the dataset's {tuple(shape)} at "
                f"{attrs['voxel_size_m']} m"
            )
            return None
        T = np.asarray(gseq.T_base_from_lidar, np.float64)
        verts = np.asarray(gtf.vertices, np.float64)
        verts = verts @ T[:3, :3].T + T[:3, 3] if verts.size else verts.reshape(0, 0, 3)
        return GroundTruth(
            occupancy=gtf.occupancy,
            track_id=np.asarray(gtf.track_id),
            vertices=verts.astype(np.float32),
            faces=np.asarray(gseq.person_faces),
        )
