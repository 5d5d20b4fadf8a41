"""A robot log as a sequence: the :class:`LogSequence` source (ROS 1 bag, ROS 2 bag folder, MCAP).

Topics are found, not configured (every choice overridable, :class:`LogSettings`):

- the LiDAR: the sensor_msgs/PointCloud2 topic (one, or a known driver's name among several);
  its raw frame number is the sweep's index in the log (0-based), and frames are picked every
  ``frame_stride``-th sweep from the first, as the CODa reader picks them;
- cameras: (CompressedImage or Image) + CameraInfo pairs by namespace (``/stereo/left/...`` ->
  cam0, ``/stereo/right/...`` -> cam1, namespaces in sorted order); a rectified topic (``rect``
  in its name) is projected with the CameraInfo's P and R as CODa's ``2d_rect``, a raw one is
  undistorted and rectified with its D / R / P (storage.sources.log.images) into that same pinhole;
- calibration: the ``/tf_static`` chain base -> LiDAR -> each camera's optical frame;
- poses T_world_from_lidar at each picked sweep's stamp (linear + slerp, tasks.poses): from ``/tf``
  (world frame -> base), else a nav_msgs/Odometry or PoseStamped topic, else (or with
  ``poses: lidar-odometry``) from KISS-ICP over every sweep (tasks.poses.odometry), a product
  cached under ``.cache/odometry/`` keyed by the log's fingerprint and the odometry settings.

Per picked sweep, each camera's image nearest in stamp within ``max_image_offset_ms``; a frame
without one, or outside the poses' time range, is left out and reported (``info.warnings``).
The log is indexed once (storage.sources.log.index) and read message by message: memory stays
flat in the log's length. Every error is a :class:`LogFormatError` naming the file, the topic and
the stamp (and the raw frame where there is one).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from configs.sources import POSE_MODES, LogSettings
from storage.npzio import NPZ_ERRORS, load_npz
from storage.sequence_data import (
    Calibration,
    CameraCalibration,
    Frame,
    RawCameraCalibration,
    SequenceInfo,
)
from storage.sources import SelectedFrames
from storage.sources.log.bag import LogFile, LogFormatError, log_files, quick_fingerprint, where
from storage.sources.log.images import (
    CameraInfo,
    ImageDecodeError,
    Rectifier,
    decode_compressed,
    decode_raw,
)
from storage.sources.log.index import (
    CAMERA_INFO,
    COMPRESSED_IMAGE,
    IMAGE,
    ODOMETRY,
    POINTCLOUD2,
    POSE_COV_STAMPED,
    POSE_STAMPED,
    LogIndex,
    Transforms,
    load_index,
    stamp_ns,
)
from storage.sources.log.pointcloud import DecodedCloud, Field, PointLayoutError, decode_pointcloud2
from tasks.bounds import pose_track_problem, rigid_problem
from tasks.poses.tf import StampedEdge, TFGap, TFTree, static_edge

#: PointCloud2 topics of common drivers, preferred in this order when a log has several
KNOWN_LIDAR_TOPICS = (
    "/ouster/points",
    "/os_cloud_node/points",
    "/os1_cloud_node/points",
    "/velodyne_points",
    "/hesai/pandar",
    "/rslidar_points",
    "/livox/lidar",
    "/points_raw",
)
BASE_FRAMES = ("base_footprint", "base_link", "base")
WORLD_FRAMES = ("map", "world", "odom")
#: version of what opening a log checks and returns (the planner's memo of another is not used)
READER_VERSION = "2"  # 2: TF graph and sweep plausibility checked (issue 41)
#: version of the LiDAR-odometry product (bump when its poses change for the same inputs)
ODOMETRY_VERSION = "2"


@dataclass(frozen=True)
class CameraStream:
    """A camera of the log: its topics, whether the image topic is rectified, the CameraInfo."""

    name: str
    image_topic: str
    info_topic: str
    rectified: bool
    info: CameraInfo


@dataclass(frozen=True)
class LogFacts:
    """What check-data shows of a log beyond SequenceInfo: every topic (type, messages, rate,
    frame id), the mapping chosen, the LiDAR layout, the pose source, frames left out."""

    topics: tuple[tuple[str, str, int, float | None, str], ...]
    lidar_topic: str
    cameras: tuple[CameraStream, ...]
    base_frame: str | None
    world_frame: str | None
    pose_source: str
    lidar_layout: str
    left_out: tuple[tuple[int, str], ...]


def _rate_hz(stamps: np.ndarray) -> float | None:
    if len(stamps) < 2:
        return None
    span = (int(stamps[-1]) - int(stamps[0])) / 1e9
    return (len(stamps) - 1) / span if span > 0 else None


def _strip_transport(topic: str) -> str:
    for suffix in ("/compressed", "/theora", "/compressedDepth"):
        if topic.endswith(suffix):
            return topic[: -len(suffix)]
    return topic


def camera_namespace(image_topic: str) -> str:
    """``/stereo/left/image_rect_color/compressed`` -> ``/stereo/left``."""
    return _strip_transport(image_topic).rsplit("/", 1)[0] or "/"


def _image_rank(topic: str, msgtype: str) -> tuple:
    base = _strip_transport(topic).rsplit("/", 1)[-1]
    return ("rect" not in base, "color" not in base, msgtype != COMPRESSED_IMAGE, topic)


def _latest_static(tf: Transforms | None) -> TFTree:
    static: dict[str, tuple[str, np.ndarray]] = {}
    if tf is None:
        return TFTree(static)
    for k in np.argsort(tf.stamp_ns, kind="stable"):  # the latest value of each child wins
        child, parent = tf.frames[tf.child[k]], tf.frames[tf.parent[k]]
        static[child] = static_edge(parent, tf.t[k], tf.q_wxyz[k])
    return TFTree(static)


def _stamped_edges(tf: Transforms | None) -> dict[str, StampedEdge]:
    out: dict[str, StampedEdge] = {}
    if tf is None or len(tf.stamp_ns) == 0:
        return out
    for c in np.unique(tf.child):
        rows = np.flatnonzero(tf.child == c)
        order = np.argsort(tf.stamp_ns[rows], kind="stable")
        rows = rows[order]
        stamps = tf.stamp_ns[rows]
        last = np.r_[stamps[1:] != stamps[:-1], True]  # one value per stamp: the last written
        rows = rows[last]
        out[tf.frames[c]] = StampedEdge(
            tf.frames[int(tf.parent[rows[0]])], tf.stamp_ns[rows], tf.t[rows], tf.q_wxyz[rows]
        )
    return out


class LogSequence(SelectedFrames):
    """One robot log as a sequence. Cheap to reopen (the index is cached by fingerprint); frames
    are read on demand, one message at a time.

    path: the log (a .bag or .mcap file, or a ROS 2 bag folder); sequence: its name (the stem).
    frame_stride, min_range_m, max_range_m, cameras (names wanted, cam0 required), lighting,
    lidar_height_m (where the TF tree has no base frame): as :class:`storage.sources.coda.CodaSequence`.
    cache_dir: where the index and the odometry product are cached (None: not cached).
    with_poses: False skips computing LiDAR-odometry poses (planning, check-data): the info then
    holds identity poses and says so in ``pose_source``.
    """

    kind = "log"

    def __init__(
        self,
        path: Path,
        sequence: str | None = None,
        *,
        settings: LogSettings = LogSettings(),
        frame_stride: int = 2,
        min_range_m: float = 0.5,
        max_range_m: float = math.inf,
        cameras: tuple[str, ...] = ("cam0", "cam1"),
        lighting: str | None = None,
        lidar_height_m: float | None = None,
        cache_dir: Path | None = None,
        with_poses: bool = True,
    ):
        self.path = Path(path)
        self.sequence = str(sequence if sequence is not None else self.path.stem)
        self.root = self.path.parent
        if settings.poses not in POSE_MODES:
            raise LogFormatError(f"poses {settings.poses!r}: expected one of {POSE_MODES}")
        if frame_stride < 1:
            raise LogFormatError(f"frame_stride {frame_stride}: expected >= 1")
        if lighting not in (None, "day", "night"):
            raise LogFormatError(f"lighting {lighting!r} for {self.path}: expected day or night")
        self.settings = settings
        self.frame_stride = frame_stride
        self.min_range_m, self.max_range_m = min_range_m, max_range_m
        self.cameras = cameras
        self.lidar_height_m = lidar_height_m
        self.cache_dir = None if cache_dir is None else Path(cache_dir)
        self._lighting = lighting
        self._log: LogFile | None = None
        self._rectifiers: dict[str, Rectifier] = {}
        self.info = self._read_info(with_poses)

    # -- the open log (one per process) ------------------------------------------------------
    @property
    def log(self) -> LogFile:
        if self._log is None:
            self._log = LogFile(self.path)
        return self._log

    def close(self) -> None:
        if self._log is not None:
            self._log.close()
            self._log = None

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_log"], state["_rectifiers"] = None, {}
        return state

    def _error(self, message: str, topic=None, stamp=None, k=None, frame=None) -> LogFormatError:
        return LogFormatError(
            f"{where(self.path, topic, stamp, k)}: {message}",
            self.path,
            frame,
            self.sequence,
            topic=topic,
            stamp_ns=stamp,
        )

    # -- sequence level ----------------------------------------------------------------------
    def _read_info(self, with_poses: bool) -> SequenceInfo:
        index = load_index(self.log, self.cache_dir)
        self.index = index
        warnings: list[str] = []
        self.lidar_topic = self._lidar_topic(index)
        lidar = index.streams[self.lidar_topic]
        self._check_increasing(self.lidar_topic, lidar.stamp_ns)
        self.lidar_frame = lidar.frame_id
        static = _latest_static(index.tf_static)
        stamped = _stamped_edges(index.tf)
        self.tree = TFTree(static.static, stamped)
        self._check_tf(index, static, stamped)
        first_stamp = int(lidar.stamp_ns[0])
        self.camera_streams = self._camera_streams(index)
        calibration = self._calibration(warnings, first_stamp)
        picked = list(range(0, len(lidar.stamp_ns), self.frame_stride))
        left_out: list[tuple[int, str]] = []
        self._image_at = self._match_images(picked, left_out)
        picked = [f for f in picked if f not in dict(left_out)]
        poses, picked, self.pose_source = self._poses(picked, left_out, with_poses)
        if left_out:
            shown = ", ".join(f"{f} ({why})" for f, why in left_out[:5])
            more = f" and {len(left_out) - 5} more" if len(left_out) > 5 else ""
            warnings.append(f"{len(left_out)} picked sweep(s) left out: {shown}{more}")
        self.left_out = tuple(left_out)
        if not picked:
            raise self._error(
                "no frame left: every picked sweep lacks an image or a pose "
                f"({left_out[0][1] if left_out else 'no sweeps'})",
                self.lidar_topic,
            )
        idx = np.asarray(picked, np.int64)
        gt = self.root / "gt" / self.sequence
        gt_files = (
            sorted(Path(top) / name for top, _, names in os.walk(gt) for name in names)
            if gt.is_dir()
            else []
        )
        selection = (
            f"log: {len(lidar.stamp_ns)} sweeps on {self.lidar_topic}; {len(picked)} kept every "
            f"{self.frame_stride} sweep(s) from the first"
        )
        return SequenceInfo(
            sequence=self.sequence,
            root=self.root,
            frame_indices=tuple(int(f) for f in picked),
            stamps_ns=lidar.stamp_ns[idx].astype(np.int64),
            poses=poses,
            calibration=calibration,
            metadata={},
            files=tuple(log_files(self.path) + gt_files),
            selection=selection,
            num_stamps=len(lidar.stamp_ns),
            lighting=self._lighting or "day",
            lighting_source="config" if self._lighting else "default",
            warnings=tuple(warnings),
        )

    def _check_tf(self, index: LogIndex, static: TFTree, stamped: dict[str, StampedEdge]) -> None:
        """The TF graph is a tree of plausible transforms (tasks/bounds.py), else the sequence
        fails naming the topic and the value: a frame with two parents (in /tf_static, or one
        in /tf_static and another in /tf), a cycle, a /tf_static transform whose rotation is
        not one or whose translation is longer than a rig spans, a /tf value that is not finite."""
        tf = index.tf_static
        parents: dict[str, str] = {}
        if tf is not None:
            for k in range(len(tf.stamp_ns)):
                child, parent = tf.frames[tf.child[k]], tf.frames[tf.parent[k]]
                if parents.setdefault(child, parent) != parent:
                    raise self._error(
                        f"frame {child!r} has two parents, {parents[child]!r} and {parent!r}; "
                        "a TF tree gives each frame one",
                        "/tf_static",
                        int(tf.stamp_ns[k]),
                        k,
                    )
        for child, edge in stamped.items():
            if parents.get(child, edge.parent) != edge.parent:
                raise self._error(
                    f"frame {child!r} has the parent {parents[child]!r} in /tf_static and "
                    f"{edge.parent!r} in /tf; a TF tree gives each frame one",
                    "/tf",
                )
            values = np.concatenate([edge.translations, edge.quats_wxyz], axis=1)
            bad = ~np.isfinite(values).all(axis=1)
            if bad.any():
                k = int(np.flatnonzero(bad)[0])
                raise self._error(
                    f"{edge.parent!r} -> {child!r} value {k} is not finite ({values[k].tolist()})",
                    "/tf",
                    int(edge.stamps_ns[k]),
                )
        tree = TFTree(static.static, stamped)
        for frame in sorted(tree.frames()):
            seen = [frame]
            while (p := tree.parent(seen[-1])) is not None:
                if p in seen:
                    raise self._error(
                        f"the TF graph has a cycle: {' -> '.join(seen[seen.index(p) :] + [p])}",
                        "/tf_static" if p in static.static else "/tf",
                    )
                seen.append(p)
        for child, (parent, T) in static.static.items():
            problem = rigid_problem(T, f"{parent!r} -> {child!r}")
            if problem:
                raise self._error(problem, "/tf_static")

    def _check_increasing(self, topic: str, stamps: np.ndarray) -> None:
        if len(stamps) == 0:
            raise self._error("the topic has no messages", topic)
        steps = np.diff(stamps)
        if (steps <= 0).any():
            k = int(np.flatnonzero(steps <= 0)[0]) + 1
            raise self._error(
                f"header stamps go backwards: {int(stamps[k])} ns after {int(stamps[k - 1])} ns "
                f"(message {k - 1}); expected increasing stamps (two sensors on one topic, or a "
                "clock jump while recording?)",
                topic,
                int(stamps[k]),
                k,
            )

    def _lidar_topic(self, index: LogIndex) -> str:
        clouds = [n for n, (t, _) in index.topics.items() if t == POINTCLOUD2]
        chosen = self.settings.lidar_topic
        if chosen is not None:
            if chosen not in index.topics:
                raise self._error(
                    f"dataset.log.lidar_topic {chosen!r} is not in the log (PointCloud2 topics: "
                    f"{', '.join(clouds) or 'none'})"
                )
            if index.topics[chosen][0] != POINTCLOUD2:
                raise self._error(
                    f"is a {index.topics[chosen][0]}, expected sensor_msgs/PointCloud2", chosen
                )
        elif len(clouds) == 1:
            chosen = clouds[0]
        else:
            known = [t for t in KNOWN_LIDAR_TOPICS if t in clouds]
            if not clouds:
                raise self._error(
                    "no sensor_msgs/PointCloud2 topic (topics: "
                    f"{', '.join(f'{n} ({t})' for n, (t, _) in index.topics.items()) or 'none'})"
                )
            if not known:
                raise self._error(
                    f"{len(clouds)} PointCloud2 topics ({', '.join(clouds)}); say which is the "
                    "LiDAR with dataset.log.lidar_topic"
                )
            chosen = known[0]
        if index.topics[chosen][1] == 0 or len(index.streams[chosen].stamp_ns) == 0:
            raise self._error("the topic has no messages", chosen)
        return chosen

    def _camera_streams(self, index: LogIndex) -> list[CameraStream]:
        images = {n: t for n, (t, c) in index.topics.items() if t in (IMAGE, COMPRESSED_IMAGE)}
        by_ns: dict[str, list[str]] = {}
        for n in images:
            by_ns.setdefault(camera_namespace(n), []).append(n)
        auto = sorted(by_ns)
        out = []
        for k, name in enumerate(self.cameras):
            cfg = self.settings.camera(name)
            image_topic = cfg.image_topic
            if image_topic is None:
                if k >= len(auto):
                    if name == "cam0":
                        raise self._error(
                            "no camera: no sensor_msgs/Image or CompressedImage topic; "
                            "dataset.log.cameras.cam0.image_topic names one"
                        )
                    continue  # only cam0 is required
                image_topic = min(by_ns[auto[k]], key=lambda n: _image_rank(n, images[n]))
            elif image_topic not in images:
                raise self._error(
                    f"dataset.log.cameras.{name}.image_topic {image_topic!r} is not an image "
                    f"topic of the log (image topics: {', '.join(sorted(images)) or 'none'})"
                )
            info_topic = cfg.info_topic or camera_namespace(image_topic) + "/camera_info"
            if index.topics.get(info_topic, ("", 0))[0] != CAMERA_INFO or (
                info_topic not in index.camera_info
            ):
                infos = [n for n, (t, _) in index.topics.items() if t == CAMERA_INFO]
                images_at = index.streams[image_topic].stamp_ns
                raise self._error(
                    f"no sensor_msgs/CameraInfo for camera {name} ({image_topic}, first image at "
                    f"stamp {int(images_at[0]) if len(images_at) else '-'} ns): expected it on "
                    f"{info_topic} (CameraInfo topics: {', '.join(infos) or 'none'}; "
                    f"dataset.log.cameras.{name}.info_topic names another)",
                    info_topic,
                )
            if len(index.streams[image_topic].stamp_ns) == 0:
                raise self._error("the topic has no messages", image_topic)
            self._check_increasing(image_topic, index.streams[image_topic].stamp_ns)
            info = index.camera_info[info_topic]
            problem = info.check()
            if problem:
                raise self._error(
                    f"CameraInfo of camera {name}: {problem}",
                    info_topic,
                    int(index.streams[info_topic].stamp_ns[0]),
                )
            base = _strip_transport(image_topic).rsplit("/", 1)[-1]
            rectified = cfg.rectified if cfg.rectified is not None else "rect" in base
            out.append(CameraStream(name, image_topic, info_topic, rectified, info))
        return out

    def _static_lookup(self, target: str, source: str, stamp: int, what: str) -> np.ndarray:
        try:
            return self.tree.lookup(target, source)
        except TFGap as exc:
            raise self._error(f"{what}: {exc}", "/tf_static", stamp) from None

    def _calibration(self, warnings: list[str], stamp: int) -> Calibration:
        cameras = {}
        for cam in self.camera_streams:
            info = cam.info
            frame = info.frame_id or self.index.streams[cam.image_topic].frame_id
            T_raw = self._static_lookup(
                frame, self.lidar_frame, stamp, f"camera {cam.name} ({cam.image_topic})"
            )
            D = np.pad(info.D[:5], (0, max(0, 5 - len(info.D))))
            raw = RawCameraCalibration(info.K, D, info.R, info.P, T_raw, None)
            R4 = np.eye(4)
            R4[:3, :3] = info.R
            cameras[cam.name] = CameraCalibration(
                cam.name,
                np.array(info.P[:, :3], dtype=np.float64),
                np.zeros(5),
                info.width,
                info.height,
                R4 @ T_raw,
                raw,
                rectified=True,
            )
        base = self.settings.base_frame
        frames = self.tree.frames()
        if base is None:
            base = next((f for f in BASE_FRAMES if f in frames), None)
        elif base not in frames:
            raise self._error(
                f"dataset.log.base_frame {base!r} is not in the TF tree (frames: "
                f"{', '.join(sorted(frames)) or 'none'})",
                "/tf_static",
                stamp,
            )
        self.base_frame = base
        if base is not None:
            T_base = self._static_lookup(base, self.lidar_frame, stamp, "base frame")
            base_default = False
        elif self.lidar_height_m is not None:
            T_base, base_default = np.eye(4), True
            T_base[2, 3] = float(self.lidar_height_m)
            warnings.append(
                f"{self.path}: no base frame ({' / '.join(BASE_FRAMES)}) in the TF tree: "
                f"T_base_from_lidar = the LiDAR {self.lidar_height_m:g} m above the ground, axes "
                "aligned (dataset.lidar_height_m; dataset.log.base_frame names one)"
            )
        else:
            raise self._error(
                f"no base frame ({' / '.join(BASE_FRAMES)}) in the TF tree and no "
                "dataset.lidar_height_m",
                "/tf_static",
                stamp,
            )
        T01 = None
        if "cam0" in cameras and "cam1" in cameras:
            T01 = cameras["cam1"].raw.T_cam_from_lidar @ np.linalg.inv(
                cameras["cam0"].raw.T_cam_from_lidar
            )
        return Calibration(cameras, T_base, base_default, T01)

    def _match_images(self, picked: list[int], left_out: list) -> dict[str, dict[int, int]]:
        """camera -> raw frame -> index of its nearest image message (within the offset)."""
        lidar = self.index.streams[self.lidar_topic].stamp_ns
        limit = int(round(self.settings.max_image_offset_ms * 1e6))
        at: dict[str, dict[int, int]] = {}
        missing: dict[int, str] = {}
        for cam in self.camera_streams:
            stamps = self.index.streams[cam.image_topic].stamp_ns
            q = lidar[picked]
            hi = (
                np.clip(np.searchsorted(stamps, q), 1, len(stamps) - 1)
                if len(stamps) > 1
                else np.zeros(len(q), np.int64)
            )
            lo = np.maximum(hi - 1, 0)
            nearest = np.where(np.abs(stamps[hi] - q) < np.abs(stamps[lo] - q), hi, lo)
            off = np.abs(stamps[nearest] - q)
            at[cam.name] = {}
            for f, k, d in zip(picked, nearest.tolist(), off.tolist()):
                if d <= limit:
                    at[cam.name][f] = int(k)
                elif f not in missing:
                    missing[f] = (
                        f"no {cam.name} image within {self.settings.max_image_offset_ms:g} ms "
                        f"of stamp {int(lidar[f])} (nearest {d / 1e6:.1f} ms away)"
                    )
        left_out.extend(sorted(missing.items()))
        return at

    # -- poses ---------------------------------------------------------------------------------
    def _pose_mode(self) -> tuple[str, str | None]:
        mode, topic = self.settings.poses, self.settings.pose_topic
        pose_topics = [
            n
            for n, (t, c) in self.index.topics.items()
            if t in (ODOMETRY, POSE_STAMPED, POSE_COV_STAMPED) and c > 0
        ]
        if mode == "odometry" or (mode == "auto" and topic is not None):
            if topic is None:
                if len(pose_topics) != 1:
                    raise self._error(
                        f"poses: odometry needs one Odometry / PoseStamped topic, the log has "
                        f"{', '.join(pose_topics) or 'none'} (dataset.log.pose_topic names it)"
                    )
                topic = pose_topics[0]
            elif topic not in self.index.poses:
                raise self._error(
                    f"dataset.log.pose_topic {topic!r} is not an Odometry / PoseStamped topic "
                    f"of the log (those: {', '.join(pose_topics) or 'none'})"
                )
            return "odometry", topic
        if mode in ("tf", "lidar-odometry"):
            return mode, None
        if self._world_frame(required=False) is not None:
            return "tf", None
        if len(pose_topics) == 1:
            return "odometry", pose_topics[0]
        return "lidar-odometry", None

    def _world_frame(self, required: bool = True) -> str | None:
        world = self.settings.world_frame
        chain = self.tree.chain(self.lidar_frame)
        moving = [f for f in chain if f in self.tree.stamped]
        if world is not None:
            if world not in chain and required:
                raise self._error(
                    f"dataset.log.world_frame {world!r} is not above the LiDAR frame in the TF "
                    f"tree (the LiDAR's chain: {' -> '.join(chain)})",
                    "/tf",
                )
            return world if world in chain else None
        if not moving:
            if required:
                raise self._error(
                    "no /tf transform moves the LiDAR frame (its chain: "
                    f"{' -> '.join(chain)}); poses: tf needs world -> base transforms on /tf",
                    "/tf",
                )
            return None
        above = chain[chain.index(moving[-1]) + 1 :]  # frames above the last moving edge
        return next((f for f in WORLD_FRAMES if f in above), above[-1] if above else None)

    def _poses(self, picked: list[int], left_out: list, with_poses: bool):
        lidar = self.index.streams[self.lidar_topic].stamp_ns
        stamps = lidar[picked]
        gap = int(round(self.settings.max_pose_gap_ms * 1e6))
        mode, topic = self._pose_mode()
        if mode == "lidar-odometry":
            self.world_frame = f"{self.base_frame or 'base'} at the first sweep"
            if not with_poses:
                return np.tile(np.eye(4), (len(picked), 1, 1)), picked, "lidar-odometry"
            T_first = self.odometry_poses()
            T_bl = self.info_T_base_from_lidar()
            return T_bl @ T_first[picked], picked, "lidar-odometry"
        if mode == "tf":
            world = self._world_frame()
            self.world_frame = world
            valid = self._pose_coverage(self._tf_edges(world), stamps, gap)
            keep = [f for f, ok in zip(picked, valid) if ok]
            for f, ok in zip(picked, valid):
                if not ok:
                    left_out.append(
                        (f, f"no /tf {world} -> {self.lidar_frame} at stamp {int(lidar[f])}")
                    )
            try:
                poses = self.tree.lookup(world, self.lidar_frame, lidar[keep], gap)
            except TFGap as exc:
                raise self._error(str(exc), "/tf", int(lidar[keep][0]) if keep else None) from None
            self._check_track("/tf", lidar[keep], poses)
            return poses, keep, f"/tf ({world} -> {self.lidar_frame})"
        track = self.index.poses[topic]
        self._check_increasing(topic, track.stamp_ns)
        child = track.child_frame_id or self.base_frame or self.lidar_frame
        self.world_frame = track.frame_id
        edge = StampedEdge(track.frame_id, track.stamp_ns, track.t, track.q_wxyz)
        valid = self._pose_coverage([edge], stamps, gap)
        keep = [f for f, ok in zip(picked, valid) if ok]
        for f, ok in zip(picked, valid):
            if not ok:
                left_out.append((f, f"no {topic} pose at stamp {int(lidar[f])}"))
        T_child_from_lidar = self._static_lookup(
            child, self.lidar_frame, int(lidar[0]), f"{topic} child frame"
        )
        tree = TFTree({}, {child: edge})
        poses = tree.lookup(track.frame_id, child, lidar[keep], gap) @ T_child_from_lidar
        self._check_track(topic, lidar[keep], poses)
        return (
            poses,
            keep,
            f"{topic} ({track.msgtype.rsplit('/', 1)[-1]}, {track.frame_id} -> {child})",
        )

    def _check_track(self, topic: str, stamps: np.ndarray, poses: np.ndarray) -> None:
        """The LiDAR's world poses at the picked sweeps are finite and never jump faster than a
        robot drives (tasks/bounds.py), else the sequence fails naming the topic and stamp."""
        problem = pose_track_problem(stamps, poses[:, :3, 3]) if len(poses) else ""
        if not problem and len(poses) and not np.isfinite(poses).all():
            problem = "a pose rotation is not finite"
        if problem:
            k = int(problem.split()[1]) if problem.split()[1].isdigit() else 0
            raise self._error(f"implausible poses: {problem}", topic, int(stamps[k]))

    def _tf_edges(self, world: str) -> list[StampedEdge]:
        chain = self.tree.chain(self.lidar_frame)
        return [self.tree.stamped[f] for f in chain[: chain.index(world)] if f in self.tree.stamped]

    @staticmethod
    def _pose_coverage(edges: list[StampedEdge], stamps: np.ndarray, gap: int) -> np.ndarray:
        """(Q,) bool: every stamped edge has samples around each stamp (within ``gap``)."""
        ok = np.ones(len(stamps), bool)
        for e in edges:
            s = e.stamps_ns
            hi = np.searchsorted(s, stamps, side="left")
            exact = (hi < len(s)) & (s[np.minimum(hi, len(s) - 1)] == stamps)
            inside = (hi > 0) & (hi < len(s))
            span = s[np.minimum(hi, len(s) - 1)] - s[np.maximum(hi - 1, 0)]
            ok &= exact | (inside & (span <= gap))
        return ok

    def info_T_base_from_lidar(self) -> np.ndarray:
        base = self.base_frame
        if base is None:
            T = np.eye(4)
            T[2, 3] = float(self.lidar_height_m or 0.0)
            return T
        return self.tree.lookup(base, self.lidar_frame)

    def odometry_key(self) -> str:
        """The odometry product's key: its code version, settings, the log's fingerprint and the
        LiDAR topic (keyed like a stage)."""
        blob = json.dumps(
            {
                "version": ODOMETRY_VERSION,
                "settings": vars(self.settings.odometry),
                "log": quick_fingerprint(self.path),
                "topic": self.lidar_topic,
            },
            sort_keys=True,
        )
        return hashlib.sha256(blob.encode()).hexdigest()[:24]

    def odometry_poses(self) -> np.ndarray:
        """(S, 4, 4) float64 T_first_from_lidar at every sweep (KISS-ICP), from the cache when
        there (``cache_dir/odometry/<key>.npz``), else computed and cached."""
        from tasks.poses.odometry import LidarOdometry, two_way

        key = self.odometry_key()
        path = self.cache_dir / "odometry" / f"{key}.npz" if self.cache_dir else None
        s = self.settings.odometry
        n = len(self.index.streams[self.lidar_topic].stamp_ns)
        if path is not None and path.is_file():
            try:  # verified before use: a damaged or foreign cache file is computed again
                cached = load_npz(path, ["T_first_from_lidar"])["T_first_from_lidar"]
                if cached.shape == (n, 4, 4) and np.isfinite(cached).all():
                    return cached.astype(np.float64, copy=False)
            except NPZ_ERRORS:
                pass

        def run(order, sign):  # one pass, a sweep at a time (memory flat in the log's length)
            odo, out = LidarOdometry(s), []
            for k in order:
                cloud = self._cloud(k, s.scan_min_range_m, s.scan_max_range_m)
                t = None if cloud.time_s is None else sign * cloud.time_s
                out.append(odo.step(cloud.points, t))
            return np.stack(out)

        poses = run(range(n), 1.0)
        if s.two_way and n > 1:  # backwards from the last sweep: its times run backwards too
            poses = two_way(poses, run(range(n - 1, -1, -1), -1.0)[::-1])
        if path is not None:
            from storage.npzio import save_npz_deterministic

            save_npz_deterministic(
                path,
                T_first_from_lidar=poses,
                stamps_ns=self.index.streams[self.lidar_topic].stamp_ns,
            )
        return poses

    # -- messages ------------------------------------------------------------------------------
    def _raw(self, topic: str, k: int):
        stream = self.index.streams[topic]
        return self.log.raw(topic, k, int(stream.log_ns[k]), int(stream.ordinal[k]))

    def _message(self, topic: str, k: int, frame: int | None = None):
        stream = self.index.streams[topic]
        stamp = int(stream.stamp_ns[k])
        msg = self.log.deserialize(bytes(self._raw(topic, k)), stream.msgtype, topic, stamp)
        if stamp_ns(msg.header) != stamp:
            raise self._error(
                f"message {k} has stamp {stamp_ns(msg.header)} ns, the index says {stamp} ns "
                "(the index was made from another version of the file?)",
                topic,
                stamp,
                k,
                frame,
            )
        return msg

    def _cloud(self, k: int, min_range_m: float, max_range_m: float) -> DecodedCloud:
        from storage.sources.log.positions import PositionError, pointcloud2_of

        stamp = int(self.index.streams[self.lidar_topic].stamp_ns[k])
        try:
            msg = pointcloud2_of(self._raw(self.lidar_topic, k), self.log.ros1)
        except (PositionError, IndexError, ValueError) as exc:
            raise self._error(
                f"PointCloud2 cannot be read ({exc}); the log is truncated or damaged",
                self.lidar_topic,
                stamp,
                k,
                k,
            ) from None
        if msg.stamp_ns != stamp:
            raise self._error(
                f"sweep {k} has stamp {msg.stamp_ns} ns, the index says {stamp} ns (the index "
                "was made from another version of the file?)",
                self.lidar_topic,
                stamp,
                k,
                k,
            )
        try:
            return decode_pointcloud2(
                [Field(*f) for f in msg.fields],
                msg.data,
                height=msg.height,
                width=msg.width,
                point_step=msg.point_step,
                row_step=msg.row_step,
                is_bigendian=msg.is_bigendian,
                stamp_ns=stamp,
                min_range_m=min_range_m,
                max_range_m=max_range_m,
            )
        except PointLayoutError as exc:
            raise self._error(
                f"PointCloud2 cannot be decoded: {exc}", self.lidar_topic, stamp, k, k
            ) from None

    def lidar_layout(self) -> str:
        """The LiDAR's point layout in words (its first sweep), for check-data."""
        return self._cloud(0, self.min_range_m, self.max_range_m).layout.describe()

    def frame(self, i: int) -> Frame:
        """The i-th selected frame (its sweep decoded; images on demand with :meth:`image`)."""
        if not 0 <= i < len(self):
            raise IndexError(
                f"sequence {self.sequence}: frame position {i} not in 0..{len(self) - 1}"
            )
        raw = self.info.frame_indices[i]
        cloud = self._cloud(raw, self.min_range_m, self.max_range_m)
        return Frame(
            sequence=self.sequence,
            index=raw,
            stamp_ns=int(self.info.stamps_ns[i]),
            points_lidar=cloud.points,
            intensity=cloud.intensity,
            T_world_from_lidar=self.info.poses[i],
            image_paths={},
            lidar_path=self.path,
            point_time_s=cloud.time_s,
            intensity_present=cloud.intensity_present,
            point_index=cloud.index,
        )

    def image(self, camera: str, raw_frame: int) -> np.ndarray:
        """(H, W, 3) uint8 RGB of ``camera`` matched to raw frame ``raw_frame``, in the pinhole of
        its calibration (raw topics undistorted and rectified); size checked."""
        cam = next((c for c in self.camera_streams if c.name == camera), None)
        if cam is None:
            raise KeyError(
                f"{self.path}: no camera {camera!r} (cameras: {[c.name for c in self.camera_streams]})"
            )
        k = self._image_at[camera].get(int(raw_frame))
        stream = self.index.streams[cam.image_topic]
        if k is None:
            raise self._error(
                f"no {camera} image matched to raw frame {raw_frame}",
                cam.image_topic,
                frame=raw_frame,
            )
        stamp = int(stream.stamp_ns[k])
        msg = self._message(cam.image_topic, k, raw_frame)
        try:
            if stream.msgtype == COMPRESSED_IMAGE:
                rgb = decode_compressed(str(msg.format), msg.data)
            else:
                rgb = decode_raw(
                    str(msg.encoding), int(msg.height), int(msg.width), int(msg.step), msg.data,
                    bool(msg.is_bigendian),
                )  # fmt: skip
        except ImageDecodeError as exc:
            raise self._error(str(exc), cam.image_topic, stamp, k, raw_frame) from None
        if (rgb.shape[1], rgb.shape[0]) != (cam.info.width, cam.info.height):
            raise self._error(
                f"image is {rgb.shape[1]} x {rgb.shape[0]} px, its CameraInfo "
                f"({cam.info_topic}) says {cam.info.width} x {cam.info.height}",
                cam.image_topic,
                stamp,
                k,
                raw_frame,
            )
        if not cam.rectified and cam.info.needs_rectifying():
            if camera not in self._rectifiers:
                self._rectifiers[camera] = Rectifier(cam.info)
            rgb = self._rectifiers[camera](rgb)
        return rgb

    def source_paths(self, raw_frame: int) -> dict[str, str | None]:
        """``LOG#TOPIC@INDEX`` of the frame's sweep and images (LOG relative to :attr:`root`)."""
        out: dict[str, str | None] = {
            "lidar": f"{self.path.name}#{self.lidar_topic}@{int(raw_frame)}",
            "cam0": None,
            "cam1": None,
        }
        for cam in self.camera_streams:
            k = self._image_at[cam.name].get(int(raw_frame))
            out[cam.name] = None if k is None else f"{self.path.name}#{cam.image_topic}@{k}"
        return out

    def check_images(self, raw_frame: int) -> None:
        """Decode every camera's image of a raw frame (errors name file, topic and stamp)."""
        for cam in self.info.calibration.cameras:
            self.image(cam, raw_frame)

    def facts(self) -> LogFacts:
        """Topics, mapping and choices, for check-data."""
        rows = []
        for name, (msgtype, count) in self.index.topics.items():
            stream = self.index.streams.get(name)
            pose = self.index.poses.get(name)
            stamps = stream.stamp_ns if stream else (pose.stamp_ns if pose else None)
            frame_id = stream.frame_id if stream else (pose.frame_id if pose else "")
            rows.append(
                (name, msgtype, count, _rate_hz(stamps) if stamps is not None else None, frame_id)
            )
        return LogFacts(
            topics=tuple(rows),
            lidar_topic=self.lidar_topic,
            cameras=tuple(self.camera_streams),
            base_frame=self.base_frame,
            world_frame=getattr(self, "world_frame", None),
            pose_source=self.pose_source,
            lidar_layout=self.lidar_layout(),
            left_out=self.left_out,
        )
