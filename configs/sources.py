"""Settings of the sequence sources that no kernel reads: how a robot log is read (the
``dataset.log`` config section is made from these dataclasses, their one home of defaults;
storage/sources/log/reader.py reads with them)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, get_args

from tasks.bounds import Positive
from tasks.poses.odometry import OdometrySettings

PoseMode = Literal["auto", "tf", "odometry", "lidar-odometry"]
POSE_MODES = get_args(PoseMode)


@dataclass(frozen=True)
class CameraTopics:
    """One camera's topics; None = found in the log. rectified: None = from the image topic's
    name (``rect`` in it)."""

    image_topic: str | None = None
    info_topic: str | None = None
    rectified: bool | None = None


@dataclass(frozen=True)
class LogSettings:
    """How a log is read (the ``dataset.log`` config section). Every topic and frame None = found
    in the log (storage/sources/log/reader.py). poses: auto | tf | odometry | lidar-odometry; pose_topic: the
    Odometry / PoseStamped topic. max_image_offset_ms: an image further from its sweep's stamp
    is no match (50, as CODa's own bag decoder). max_pose_gap_ms: two pose samples further
    apart are not interpolated between."""

    lidar_topic: str | None = None
    cameras: tuple[tuple[str, CameraTopics], ...] = ()
    base_frame: str | None = None
    world_frame: str | None = None
    poses: PoseMode = "auto"
    pose_topic: str | None = None
    max_image_offset_ms: Positive = 50.0
    max_pose_gap_ms: Positive = 1000.0
    odometry: OdometrySettings = field(default_factory=OdometrySettings)

    def camera(self, name: str) -> CameraTopics:
        return dict(self.cameras).get(name, CameraTopics())
