"""Tiny robot logs built in a test's tmp_path with the simulator's log writer: an organised
128 x 16 cloud per sweep (the Ouster driver's 48-byte records), two rectified 64 x 48 JPEG
cameras with CameraInfo, /tf_static, and poses on /tf, /odom or none."""

from __future__ import annotations

from io import BytesIO
from pathlib import Path

import numpy as np
from PIL import Image

from storage.sources.log.writer import LogCamera, LogWriter
from tasks.poses.rotations import matrix_to_quat_wxyz

ROWS, COLS = 128, 16
WIDTH, HEIGHT = 64, 48
START_NS = 1_700_000_000_000_000_000
PERIOD_NS = 100_000_000
K = np.array([[40.0, 0.0, 31.5], [0.0, 40.0, 23.5], [0.0, 0.0, 1.0]])
#: the optical frame: x right, y down, z forward (LiDAR x forward, y left, z up)
R_CAM_FROM_LIDAR = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


def camera(name: str, y: float) -> LogCamera:
    T = np.eye(4)
    T[:3, :3] = R_CAM_FROM_LIDAR
    T[:3, 3] = -R_CAM_FROM_LIDAR @ np.array([0.08, y, -0.15])
    P = np.c_[K, np.zeros(3)]
    return LogCamera(name, WIDTH, HEIGHT, K, np.zeros(5), np.eye(3), P, T)


def base_from_lidar() -> np.ndarray:
    T = np.eye(4)
    T[2, 3] = 0.9
    return T


def sweep(k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sweep k: points (ROWS * COLS, 3) on a cylinder of radius 5 + k / 10 (every 7th a
    no-return), intensity, t_ns."""
    n = ROWS * COLS
    az = np.tile(np.linspace(-np.pi, np.pi, COLS, endpoint=False), ROWS)
    el = np.repeat(np.linspace(-0.3, 0.3, ROWS), COLS)
    r = 5.0 + k / 10
    pts = np.c_[r * np.cos(az), r * np.sin(az), r * np.tan(el)].astype(np.float32)
    pts[::7] = 0.0
    intensity = np.arange(n, dtype=np.float32) % 255
    t_ns = np.tile(np.arange(COLS, dtype=np.uint32) * (PERIOD_NS // COLS), ROWS)
    return pts, intensity, t_ns


def jpeg(k: int, cam: int = 0) -> bytes:
    rgb = np.full((HEIGHT, WIDTH, 3), 40 * k % 255, np.uint8)
    rgb[:, :, 1] = 100 + cam
    buf = BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG", quality=95)
    return buf.getvalue()


def make_log(
    path: Path,
    fmt: str = "mcap",
    frames: int = 6,
    poses: str = "tf",
    cameras: tuple[str, ...] = ("cam0", "cam1"),
    image_offset_ns: int = 0,
    skip_images: tuple[int, ...] = (),
    compress: bool = False,
) -> Path:
    """A log of ``frames`` sweeps at 10 Hz; the robot drives 1 m/s along x, turning 0.1 rad/s."""
    cams = [camera(c, 0.06 if c == "cam0" else -0.06) for c in cameras]
    with LogWriter(path, fmt, cams, base_from_lidar(), poses=poses, compress=compress) as w:
        w.write_static(START_NS)
        for k in range(frames):
            stamp = START_NS + k * PERIOD_NS
            yaw = 0.01 * k
            R = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
            w.write_pose(stamp, np.array([0.1 * k, 0.0, 0.0]), matrix_to_quat_wxyz(R))
            w.write_sweep(stamp, *sweep(k))
            if k not in skip_images:
                for j, c in enumerate(cameras):
                    w.write_image(stamp + image_offset_ns, c, jpeg(k, j))
    return path


def expected_pose(k: int) -> np.ndarray:
    """T_world_from_lidar of sweep k of :func:`make_log`."""
    yaw = 0.01 * k
    T = np.eye(4)
    T[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
    T[:3, 3] = [0.1 * k, 0.0, 0.0]
    return T @ base_from_lidar()


def rewrite_log(src: Path, dst: Path, edit=None, empty_topics: tuple[tuple[str, str], ...] = ()):
    """Copy a log into an MCAP file message by message; ``edit(topic, msgtype, msg, log_ns)``
    returns the messages to write instead, [(topic, msgtype, msg, log_ns), ...] (None: the
    message unchanged; [] drops it). ``empty_topics``: (topic, msgtype) connections written
    without a message."""
    import os
    import shutil

    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    tmp = dst.parent / f".{dst.stem}.rewrite"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    with AnyReader([src], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        ts = reader.typestore
        writer = Writer(tmp / dst.stem, version=9, storage_plugin=StoragePlugin.MCAP)
        writer.open()
        conns: dict[str, object] = {}

        def put(topic, msgtype, msg, log_ns):
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            if msg is not None:
                writer.write(conns[topic], log_ns, ts.serialize_cdr(msg, msgtype))

        for conn, log_ns, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            out = edit(conn.topic, conn.msgtype, msg, log_ns) if edit else None
            for item in [(conn.topic, conn.msgtype, msg, log_ns)] if out is None else out:
                put(*item)
        for topic, msgtype in empty_topics:
            put(topic, msgtype, None, 0)
        writer.close()
    os.replace(tmp / dst.stem / f"{dst.stem}.mcap", dst)
    shutil.rmtree(tmp)
    return dst
