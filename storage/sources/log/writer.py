"""Write a sequence as a robot log, the way real drivers record it: ROS 2 MCAP (``.mcap``) or a
ROS 1 bag (``.bag``), through ``rosbags`` (the simulator's ``--format mcap | ros1``).

Topics and layouts (:class:`LogLayout`), as the drivers publish them:

- ``/ouster/points`` sensor_msgs/PointCloud2 from the Ouster ROS driver: organised 128 x 1024,
  ``ouster_ros::Point`` records of 48 bytes (storage.sources.log.pointcloud.OUSTER_FIELDS), frame
  ``os_sensor``, no-returns as (0, 0, 0), ``t`` uint32 nanoseconds since the header stamp.
- ``/stereo/left`` and ``/stereo/right``: ``image_rect_color/compressed``
  (sensor_msgs/CompressedImage, JPEG or PNG, image_transport's format string) and
  ``camera_info`` (sensor_msgs/CameraInfo: the raw camera's K and plumb-bob D, the stereo
  rectification R and projection P), optical frames ``stereo_left_optical_frame`` / ``..._right_...``.
- ``/tf_static``: base_link -> os_sensor, os_sensor -> each raw camera's optical frame.
- poses ``tf``: ``/tf`` map -> base_link at every sweep; ``odometry``: ``/odom`` nav_msgs/Odometry
  (frame odom, child base_link); ``none``: no world poses (LiDAR odometry has to make them).

Each file is written under a temporary name and renamed when closed, so a killed run never
leaves a truncated log under its final name. The bytes depend only on the inputs.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from storage.atomic import move_into_place
from storage.sources.log.pointcloud import OUSTER_FIELDS, OUSTER_POINT_STEP, encode_pointcloud2
from tasks.poses.rotations import invert, matrix_to_quat_wxyz

#: mcap: a ROS 2 MCAP file; ros1: a ROS 1 bag; ros2: a ROS 2 bag folder (sqlite3 storage)
FORMATS = ("mcap", "ros1", "ros2")
POSE_MODES = ("tf", "odometry", "none")
SUFFIX = {"mcap": ".mcap", "ros1": ".bag", "ros2": ""}
#: ROS 1 typestores lack tf2_msgs: its one-line definition, registered where missing
TF_MESSAGE_DEF = "geometry_msgs/TransformStamped[] transforms\n"


@dataclass(frozen=True)
class LogLayout:
    """Topic and frame names of the written logs (real drivers' defaults)."""

    lidar_topic: str = "/ouster/points"
    lidar_frame: str = "os_sensor"
    base_frame: str = "base_link"
    world_frame: str = "map"
    odom_topic: str = "/odom"
    odom_frame: str = "odom"
    image_suffix: str = "/image_rect_color/compressed"
    info_suffix: str = "/camera_info"

    def camera_namespace(self, camera: str) -> str:
        return {"cam0": "/stereo/left", "cam1": "/stereo/right"}.get(camera, f"/{camera}")

    def optical_frame(self, camera: str) -> str:
        return self.camera_namespace(camera).strip("/").replace("/", "_") + "_optical_frame"


@dataclass(frozen=True)
class LogCamera:
    """One camera as the log holds it: name, width, height, K (3, 3) raw intrinsics, D (5,)
    plumb-bob, R (3, 3) rectification, P (3, 4) projection, T_cam_from_lidar (4, 4) of the raw
    camera's optical frame."""

    name: str
    width: int
    height: int
    K: np.ndarray
    D: np.ndarray
    R: np.ndarray
    P: np.ndarray
    T_cam_from_lidar: np.ndarray


def _typestore(fmt: str):
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC if fmt == "ros1" else Stores.ROS2_HUMBLE)
    if "tf2_msgs/msg/TFMessage" not in ts.types:
        ts.register(get_types_from_msg(TF_MESSAGE_DEF, "tf2_msgs/msg/TFMessage"))
    return ts


class LogWriter:
    """One log file. ``cameras``: LogCamera list; ``T_base_from_lidar`` (4, 4); poses: one of
    POSE_MODES; compress: lz4 chunks (ROS 1), zstd chunks (MCAP). Use as a context manager, or
    call :meth:`close`."""

    def __init__(
        self,
        path: Path,
        fmt: str,
        cameras: list[LogCamera],
        T_base_from_lidar: np.ndarray,
        poses: str = "tf",
        layout: LogLayout = LogLayout(),
        image_format: str = "jpeg",
        compress: bool = False,
    ):
        if fmt not in FORMATS:
            raise ValueError(f"log format {fmt!r}: expected one of {FORMATS}")
        if poses not in POSE_MODES:
            raise ValueError(f"poses {poses!r}: expected one of {POSE_MODES}")
        self.path, self.fmt, self.poses, self.layout = Path(path), fmt, poses, layout
        self.cameras, self.T_base_from_lidar = list(cameras), np.asarray(T_base_from_lidar)
        self.image_format = image_format
        self.ts = _typestore(fmt)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # written inside a hidden folder under its own name (a ROS 2 bag folder names its storage
        # file after itself), then moved to its final name
        self._tmpdir = self.path.with_name(f".{self.path.name}.tmp{os.getpid()}")
        shutil.rmtree(self._tmpdir, ignore_errors=True)
        self._tmpdir.mkdir(parents=True)
        self._tmp = self._tmpdir / (self.path.stem if fmt == "mcap" else self.path.name)
        if fmt == "ros1":
            from rosbags.rosbag1 import Writer

            self._writer = Writer(self._tmp)
            if compress:
                self._writer.set_compression(Writer.CompressionFormat.LZ4)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer
            from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

            plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
            self._writer = Writer(self._tmp, version=9, storage_plugin=plugin)
            if compress:
                self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self._writer.open()
        self._conns: dict[str, object] = {}
        self._seq = 0
        self._static_done = False

    # -- messages ----------------------------------------------------------------------------
    def _T(self, name: str):
        return self.ts.types[name]

    def _header(self, stamp_ns: int, frame_id: str):
        Time = self._T("builtin_interfaces/msg/Time")
        stamp = Time(sec=int(stamp_ns) // 1_000_000_000, nanosec=int(stamp_ns) % 1_000_000_000)
        Header = self._T("std_msgs/msg/Header")
        if self.fmt == "ros1":
            self._seq += 1
            return Header(seq=self._seq, stamp=stamp, frame_id=frame_id)
        return Header(stamp=stamp, frame_id=frame_id)

    def _write(self, topic: str, msgtype: str, msg, stamp_ns: int) -> None:
        if topic not in self._conns:
            self._conns[topic] = self._writer.add_connection(topic, msgtype, typestore=self.ts)
        data = (
            self.ts.serialize_ros1(msg, msgtype)
            if self.fmt == "ros1"
            else self.ts.serialize_cdr(msg, msgtype)
        )
        self._writer.write(self._conns[topic], int(stamp_ns), data)

    def _transform(self, stamp_ns: int, parent: str, child: str, T: np.ndarray):
        q = matrix_to_quat_wxyz(T[:3, :3])
        return self._transform_q(stamp_ns, parent, child, T[:3, 3], q)

    def _transform_q(self, stamp_ns, parent, child, t, q_wxyz):
        V, Q = self._T("geometry_msgs/msg/Vector3"), self._T("geometry_msgs/msg/Quaternion")
        return self._T("geometry_msgs/msg/TransformStamped")(
            header=self._header(stamp_ns, parent),
            child_frame_id=child,
            transform=self._T("geometry_msgs/msg/Transform")(
                translation=V(x=float(t[0]), y=float(t[1]), z=float(t[2])),
                rotation=Q(x=float(q_wxyz[1]), y=float(q_wxyz[2]), z=float(q_wxyz[3]), w=float(q_wxyz[0])),
            ),
        )  # fmt: skip

    def write_static(self, stamp_ns: int) -> None:
        """/tf_static: base -> LiDAR -> each raw camera's optical frame (once, at the start)."""
        L = self.layout
        transforms = [
            self._transform(stamp_ns, L.base_frame, L.lidar_frame, self.T_base_from_lidar)
        ]
        for cam in self.cameras:
            T_lidar_from_cam = invert(cam.T_cam_from_lidar)
            transforms.append(
                self._transform(
                    stamp_ns, L.lidar_frame, L.optical_frame(cam.name), T_lidar_from_cam
                )
            )
        msg = self._T("tf2_msgs/msg/TFMessage")(transforms=transforms)
        self._write("/tf_static", "tf2_msgs/msg/TFMessage", msg, stamp_ns)
        self._static_done = True

    def write_sweep(
        self, stamp_ns: int, points: np.ndarray, intensity: np.ndarray, t_ns: np.ndarray
    ) -> None:
        """An organised 128 x 1024 sweep: points (131072, 3) float32 (zeros = no return),
        intensity (131072,) float32, t_ns (131072,) uint32 nanoseconds since ``stamp_ns``."""
        n = len(points)
        rows = 128 if n % 128 == 0 else 1
        data = encode_pointcloud2(
            {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2], "intensity": intensity,
             "t": t_ns, "ring": np.repeat(np.arange(rows, dtype=np.uint16), n // rows),
             "range": (np.linalg.norm(points.astype(np.float64), axis=1) * 1000).astype(np.uint32)},
        )  # fmt: skip
        PF = self._T("sensor_msgs/msg/PointField")
        fields = [PF(name=f, offset=o, datatype=d, count=c) for f, o, d, c in OUSTER_FIELDS]
        msg = self._T("sensor_msgs/msg/PointCloud2")(
            header=self._header(stamp_ns, self.layout.lidar_frame),
            height=rows,
            width=n // rows,
            fields=fields,
            is_bigendian=False,
            point_step=OUSTER_POINT_STEP,
            row_step=OUSTER_POINT_STEP * (n // rows),
            data=np.frombuffer(data, np.uint8),
            is_dense=True,
        )
        self._write(self.layout.lidar_topic, "sensor_msgs/msg/PointCloud2", msg, stamp_ns)

    def write_image(self, stamp_ns: int, camera: str, encoded: bytes) -> None:
        """A rectified camera image (JPEG / PNG bytes) and its CameraInfo at ``stamp_ns``."""
        L, cam = self.layout, next(c for c in self.cameras if c.name == camera)
        ns, frame = L.camera_namespace(camera), L.optical_frame(camera)
        kind = "png" if self.image_format == "png" else "jpeg"
        msg = self._T("sensor_msgs/msg/CompressedImage")(
            header=self._header(stamp_ns, frame),
            format=f"rgb8; {kind} compressed bgr8",
            data=np.frombuffer(encoded, np.uint8),
        )
        self._write(ns + L.image_suffix, "sensor_msgs/msg/CompressedImage", msg, stamp_ns)
        self._write(
            ns + L.info_suffix,
            "sensor_msgs/msg/CameraInfo",
            self._info(cam, stamp_ns, frame),
            stamp_ns,
        )

    def _info(self, cam: LogCamera, stamp_ns: int, frame: str):
        CI = self._T("sensor_msgs/msg/CameraInfo")
        roi = self._T("sensor_msgs/msg/RegionOfInterest")(
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        )
        arrays = {
            "d": np.asarray(cam.D, np.float64).reshape(-1),
            "k": np.asarray(cam.K, np.float64).reshape(-1),
            "r": np.asarray(cam.R, np.float64).reshape(-1),
            "p": np.asarray(cam.P, np.float64).reshape(-1),
        }
        if self.fmt == "ros1":
            arrays = {k.upper(): v for k, v in arrays.items()}
        return CI(
            header=self._header(stamp_ns, frame),
            height=int(cam.height),
            width=int(cam.width),
            distortion_model="plumb_bob",
            binning_x=0,
            binning_y=0,
            roi=roi,
            **arrays,
        )

    def write_pose(self, stamp_ns: int, t: np.ndarray, q_wxyz: np.ndarray) -> None:
        """The robot base's world pose (translation (3,), quaternion (w, x, y, z)), on /tf
        (world -> base) or /odom (nav_msgs/Odometry, odom -> base) by the writer's ``poses``."""
        L = self.layout
        if self.poses == "tf":
            tr = self._transform_q(stamp_ns, L.world_frame, L.base_frame, t, q_wxyz)
            msg = self._T("tf2_msgs/msg/TFMessage")(transforms=[tr])
            self._write("/tf", "tf2_msgs/msg/TFMessage", msg, stamp_ns)
        elif self.poses == "odometry":
            P, Q = self._T("geometry_msgs/msg/Point"), self._T("geometry_msgs/msg/Quaternion")
            pose = self._T("geometry_msgs/msg/Pose")(
                position=P(x=float(t[0]), y=float(t[1]), z=float(t[2])),
                orientation=Q(x=float(q_wxyz[1]), y=float(q_wxyz[2]), z=float(q_wxyz[3]), w=float(q_wxyz[0])),
            )  # fmt: skip
            V = self._T("geometry_msgs/msg/Vector3")
            zero = V(x=0.0, y=0.0, z=0.0)
            msg = self._T("nav_msgs/msg/Odometry")(
                header=self._header(stamp_ns, L.odom_frame),
                child_frame_id=L.base_frame,
                pose=self._T("geometry_msgs/msg/PoseWithCovariance")(
                    pose=pose, covariance=np.zeros(36)
                ),
                twist=self._T("geometry_msgs/msg/TwistWithCovariance")(
                    twist=self._T("geometry_msgs/msg/Twist")(linear=zero, angular=zero),
                    covariance=np.zeros(36),
                ),
            )
            self._write(L.odom_topic, "nav_msgs/msg/Odometry", msg, stamp_ns)

    # -- closing -----------------------------------------------------------------------------
    def close(self) -> Path:
        """Finish the file and move it to its final name; returns the path."""
        self._writer.close()
        if self.fmt == "mcap":  # rosbags writes a bag folder: keep its .mcap as a plain file
            move_into_place(self._tmp / f"{self._tmp.name}.mcap", self.path)
        else:  # a ROS 1 bag, or a ROS 2 bag folder (onto nothing)
            if self.path.is_dir():
                shutil.rmtree(self.path)
            move_into_place(self._tmp, self.path)
        shutil.rmtree(self._tmpdir)
        return self.path

    def abort(self) -> None:
        try:
            self._writer.close()
        except Exception:  # noqa: BLE001 - nothing of a failed write is kept
            pass
        shutil.rmtree(self._tmpdir, ignore_errors=True)

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(self, exc_type, *rest) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
