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
class RawCameraCalibration:
    """A camera's calibration files as written (CODa ``calib_{cam}_intrinsics.yaml`` and
    ``calib_os1_to_{cam}.yaml``), kept for reference, for ``2d_raw`` and for check-data.

    K: (3, 3) float64 ``camera_matrix`` of the raw (distorted) image, pixels. distortion: (5,)
    plumb-bob k1 k2 p1 p2 k3. R_rect: (3, 3) ``rectification_matrix`` (raw camera frame -> rectified
    frame). P_rect: (3, 4) ``projection_matrix``. T_cam_from_lidar: (4, 4) the extrinsic of the raw
    camera frame. P_lidar_to_rect: (3, 4) the extrinsic file's optional ``projection_matrix``
    (devkit-regenerated files: P_rect @ [R_rect | 0] @ T_cam_from_lidar), else None.
    """

    K: np.ndarray
    distortion: np.ndarray
    R_rect: np.ndarray
    P_rect: np.ndarray
    T_cam_from_lidar: np.ndarray
    P_lidar_to_rect: np.ndarray | None = None


@dataclass(frozen=True)
class CameraCalibration:
    """One camera as every consumer sees it: a distortion-free pinhole of the image source.

    K: (3, 3) float64 intrinsics in pixels. distortion: (5,) float64 (k1, k2, p1, p2, k3) of the
    image source (zeros for rectified images). width, height: image size in pixels.
    T_cam_from_lidar: (4, 4) float64. A LiDAR point x lands on pixel ``K @ (T_cam_from_lidar @ x)``.

    For a rectified image source (CODa ``2d_rect``, made with ``initUndistortRectifyMap(K_raw, D,
    R_rect, P_rect)``), "cam" is the **rectified** camera frame: ``K = P_rect[:, :3]`` and
    ``T_cam_from_lidar = [[R_rect, 0], [0, 1]] @ raw.T_cam_from_lidar`` (the 4th column of P_rect,
    the stereo baseline term, is not used by the rectification map). For ``2d_raw`` "cam" is the
    raw camera: ``K = raw.K``, ``T_cam_from_lidar = raw.T_cam_from_lidar`` and ``distortion =
    raw.distortion``, which the pinhole consumers do not apply. raw: the files' values, None for a
    camera built in code.
    """

    name: str
    K: np.ndarray
    distortion: np.ndarray
    width: int
    height: int
    T_cam_from_lidar: np.ndarray
    raw: RawCameraCalibration | None = None
    rectified: bool = True


@dataclass(frozen=True)
class Calibration:
    """Sensor calibration of one sequence.

    cameras: by name ("cam0", "cam1"). T_base_from_lidar: (4, 4) float64, the LiDAR mounted on the
    robot base (base frame on the ground, see tasks.conventions). base_is_default: True when the
    sequence has no ``calib_os1_to_base.yaml`` and T_base_from_lidar is the configured default.
    T_cam1_from_cam0: (4, 4) float64 from ``calib_cam0_to_cam1.yaml`` (raw camera frames) or None.
    """

    cameras: dict[str, CameraCalibration]
    T_base_from_lidar: np.ndarray
    base_is_default: bool = False
    T_cam1_from_cam0: np.ndarray | None = None

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

    points_lidar: (N, 3) float32, no-return points removed. intensity: (N,) float32;
    intensity_present: False when every return of the sweep has intensity 0 (the devkit's
    ego-compensated ``3d_comp`` sweeps copy only x y z), so the values are not measurements.
    point_time_s: (N,) float32 seconds since the sweep's first column (the 5th .bin channel holds
    nanoseconds), or None (4-channel files). semantic_labels: (N,) uint8 CODa 3d_semantic ids
    aligned with points_lidar, or None. T_world_from_lidar: (4, 4) float64. stamp_ns: Unix time,
    integer nanoseconds. boxes: the valid 3d_bbox boxes; box_problems: one message per box of the
    file that was skipped (non-finite or non-positive size, no integer instance id, malformed).
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
    box_problems: tuple[str, ...] = ()
    intensity_present: bool = True


@dataclass(frozen=True)
class SequenceInfo:
    """What a sequence holds, known without reading any sweep.

    frame_indices: the raw frame numbers selected (after the 5 Hz stride), ascending; a raw frame
    number is its line in the timestamps and poses files. selection: how they were chosen, in words.
    num_stamps: lines of the timestamps file (raw frames of the whole recording).
    stamps_ns: (F,) int64 for those frames. poses: (F, 4, 4) float64 T_world_from_lidar.
    files: every input file the sequence reads (for the content fingerprint).
    lighting: "day" or "night"; lighting_source: "config", "metadata" or "default".
    warnings: what a run should say about the sequence (defaults used, values ignored).
    lidar_channels: float32 channels of every sweep of the sequence (4 or 5), taken from the size
    of its first sweep of a valid size (``lidar_channels_from``); 0 when no sweep has one.
    """

    sequence: str
    root: Path
    frame_indices: tuple[int, ...]
    stamps_ns: np.ndarray
    poses: np.ndarray
    calibration: Calibration
    metadata: dict = field(default_factory=dict)
    files: tuple[Path, ...] = ()
    selection: str = ""
    num_stamps: int = 0
    lighting: str = "day"
    lighting_source: str = "default"
    warnings: tuple[str, ...] = ()
    lidar_channels: int = 0
    lidar_channels_from: Path | None = None

    @property
    def num_frames(self) -> int:
        return len(self.frame_indices)

    @property
    def is_night(self) -> bool:
        return self.lighting == "night"
