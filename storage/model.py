"""The data model every reader returns: sequences, frames, calibration, boxes.

Frames, units and array conventions are those of :mod:`tasks.conventions`. These are plain frozen
dataclasses over numpy arrays: flows unpack them and hand the arrays to the kernels in ``tasks/``.
The CODa reader (:mod:`storage.coda`) builds them; the synthetic generator writes the CODa layout,
so synthetic and real data reach the pipeline through the same reader.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class CameraCalibration:
    """One pinhole camera (plumb-bob distortion) and its extrinsics.

    K: (3, 3) float64 intrinsics in pixels. distortion: (5,) float64 (k1, k2, p1, p2, k3).
    width, height: image size in pixels. T_cam_from_lidar: (4, 4) float64.
    """

    name: str
    K: np.ndarray
    distortion: np.ndarray
    width: int
    height: int
    T_cam_from_lidar: np.ndarray


@dataclass(frozen=True)
class Calibration:
    """Sensor calibration of one sequence.

    cameras: by name ("cam0", "cam1"). T_base_from_lidar: (4, 4) float64, the LiDAR mounted on the
    robot base (base frame on the ground, see tasks.conventions).
    """

    cameras: dict[str, CameraCalibration]
    T_base_from_lidar: np.ndarray

    @property
    def cam0(self) -> CameraCalibration:
        return self.cameras["cam0"]


@dataclass(frozen=True)
class Box3D:
    """A 3D box in the LiDAR frame of its frame (CODa 3d_bbox convention).

    center: (3,) metres; size: (3,) = (l, w, h) with l along the box x axis; rpy: (3,) roll, pitch,
    yaw in radians (the box rotation is Rz(yaw) Ry(pitch) Rx(roll)).
    """

    instance_id: str
    class_name: str
    center: np.ndarray
    size: np.ndarray
    rpy: np.ndarray
    occlusion: str = "Unknown"

    @property
    def track_id(self) -> int:
        """The integer part of ``instanceId`` ("Pedestrian:12" -> 12), -1 if none."""
        tail = self.instance_id.rsplit(":", 1)[-1]
        return int(tail) if tail.isdigit() else -1


@dataclass(frozen=True)
class Frame:
    """One synchronised frame: a LiDAR sweep, its images, its pose, its labels where they exist.

    points_lidar: (N, 3) float32, no-return points removed. intensity: (N,) float32.
    point_time_s: (N,) float32 per-point time offset within the sweep, or None (4-channel files).
    semantic_labels: (N,) uint8 CODa 3d_semantic ids aligned with points_lidar, or None.
    T_world_from_lidar: (4, 4) float64. stamp_ns: Unix time, integer nanoseconds.
    """

    sequence: str
    index: int
    stamp_ns: int
    points_lidar: np.ndarray
    intensity: np.ndarray
    T_world_from_lidar: np.ndarray
    image_paths: dict[str, Path]
    lidar_path: Path
    point_time_s: np.ndarray | None = None
    semantic_labels: np.ndarray | None = None
    boxes: tuple[Box3D, ...] = ()


@dataclass(frozen=True)
class SequenceInfo:
    """What a sequence holds, known without reading any sweep.

    frame_indices: the raw frame numbers selected (after the 5 Hz stride), ascending.
    stamps_ns: (F,) int64 for those frames. poses: (F, 4, 4) float64 T_world_from_lidar.
    files: every input file the sequence reads (for the content fingerprint).
    """

    sequence: str
    root: Path
    frame_indices: tuple[int, ...]
    stamps_ns: np.ndarray
    poses: np.ndarray
    calibration: Calibration
    metadata: dict = field(default_factory=dict)
    files: tuple[Path, ...] = ()

    @property
    def num_frames(self) -> int:
        return len(self.frame_indices)
