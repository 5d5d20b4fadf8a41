"""The index of a robot log: where each message of the topics we read is, built in one streaming
pass and cached by the log's fingerprint.

Per sensor topic (PointCloud2, Image, CompressedImage, CameraInfo): each message's log time and
header stamp, in log order (the log time finds the message again through the log's own chunk
index, without reading anything else); the first CameraInfo's values; every ``/tf`` and
``/tf_static`` transform and every Odometry / PoseStamped pose (small: a few numbers each). What
the pass keeps grows by a few dozen bytes per message and never holds a sweep or an image, so
memory stays flat in the log's length. Cached as one ``.npz`` (no pickles) under the output's
``.cache/log-index/``, named by :func:`storage.sources.log.bag.quick_fingerprint`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from struct import error as struct_error

import numpy as np

from storage.npzio import NPZ_ERRORS, load_npz, save_npz_deterministic
from storage.sources.log.bag import LogFile, LogFormatError, quick_fingerprint, where
from storage.sources.log.images import CameraInfo
from storage.sources.log.positions import Positions

#: bump when what the index holds changes (old cache files are then not read)
INDEX_VERSION = "2"

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_COV_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
SENSOR_TYPES = (POINTCLOUD2, IMAGE, COMPRESSED_IMAGE, CAMERA_INFO)
#: bytes read of a sweep or an image message while indexing (its header: stamp and frame id)
HEAD_BYTES = 512
POSE_TYPES = (ODOMETRY, POSE_STAMPED, POSE_COV_STAMPED)


def stamp_ns(header) -> int:
    """Integer nanoseconds of a std_msgs/Header's stamp."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


@dataclass
class Stream:
    """One sensor topic: msgtype, frame_id (of its first message), log_ns and stamp_ns (n,)
    int64 in log order; ordinal (n,) int32: the message's rank among those of the topic at the
    same log time (messages are found again by log time where a log has no positions)."""

    msgtype: str
    frame_id: str
    log_ns: np.ndarray
    stamp_ns: np.ndarray
    ordinal: np.ndarray


@dataclass
class Transforms:
    """TF transforms in log order: frames (names), parent / child (n,) int32 indices into frames,
    stamp_ns (n,) int64, t (n, 3), q_wxyz (n, 4) float64; topic (n,) int32 into topics."""

    frames: list[str]
    parent: np.ndarray
    child: np.ndarray
    stamp_ns: np.ndarray
    t: np.ndarray
    q_wxyz: np.ndarray


@dataclass
class PoseTrack:
    """Poses of an Odometry / PoseStamped topic: T_frame_from_child at stamp_ns (n,);
    child_frame_id is '' for PoseStamped (the pose of the message's subject)."""

    msgtype: str
    frame_id: str
    child_frame_id: str
    stamp_ns: np.ndarray
    t: np.ndarray
    q_wxyz: np.ndarray


@dataclass
class LogIndex:
    fingerprint: str
    #: every topic: name -> (msgtype, message count)
    topics: dict[str, tuple[str, int]]
    streams: dict[str, Stream] = field(default_factory=dict)
    camera_info: dict[str, CameraInfo] = field(default_factory=dict)
    tf: Transforms | None = None
    tf_static: Transforms | None = None
    poses: dict[str, PoseTrack] = field(default_factory=dict)
    #: where the sensor topics' messages lie (storage.sources.log.positions), None for ROS 2 folders
    positions: Positions | None = None


def _camera_info(msg) -> CameraInfo:
    g = lambda *names: next(getattr(msg, n) for n in names if hasattr(msg, n))  # noqa: E731
    D = np.asarray(g("d", "D"), np.float64).reshape(-1)
    return CameraInfo(
        width=int(msg.width),
        height=int(msg.height),
        K=np.asarray(g("k", "K"), np.float64).reshape(3, 3),
        D=D,
        R=np.asarray(g("r", "R"), np.float64).reshape(3, 3),
        P=np.asarray(g("p", "P"), np.float64).reshape(3, 4),
        distortion_model=str(msg.distortion_model),
        frame_id=str(msg.header.frame_id).lstrip("/"),
    )


def _pose_of(msg, msgtype: str):
    pose = msg.pose.pose if msgtype in (ODOMETRY, POSE_COV_STAMPED) else msg.pose
    p, o = pose.position, pose.orientation
    return (p.x, p.y, p.z), (o.w, o.x, o.y, o.z)


class _TFBuilder:
    def __init__(self):
        self.frames: dict[str, int] = {}
        self.rows: list[tuple] = []

    def add(self, tr) -> None:
        parent = str(tr.header.frame_id).lstrip("/")
        child = str(tr.child_frame_id).lstrip("/")
        ids = [self.frames.setdefault(f, len(self.frames)) for f in (parent, child)]
        t, r = tr.transform.translation, tr.transform.rotation
        self.rows.append((*ids, stamp_ns(tr.header), t.x, t.y, t.z, r.w, r.x, r.y, r.z))

    def build(self) -> Transforms:
        a = np.array(self.rows, dtype=np.float64).reshape(-1, 10)
        return Transforms(
            frames=list(self.frames),
            parent=a[:, 0].astype(np.int32),
            child=a[:, 1].astype(np.int32),
            stamp_ns=np.array([r[2] for r in self.rows], dtype=np.int64),
            t=a[:, 3:6].copy(),
            q_wxyz=a[:, 6:10].copy(),
        )


def _iter_messages(log: LogFile, topics: list[str], positions: Positions | None, heads=()):
    """(topic, log_ns, k, raw) of the topics' messages in log-time order; k: the message's row
    in its topic's positions. Of the ``heads`` topics only the first bytes are read (the
    header: sweeps and images are not read whole here)."""
    if positions is None:
        counts: dict[str, int] = {}
        for topic, log_ns, raw in log.messages(topics):
            k = counts.get(topic, 0)
            counts[topic] = k + 1
            yield topic, log_ns, k, raw
        return
    parts = [(t, positions.topics[t]) for t in topics if len(positions.topics[t])]
    if not parts:
        return
    log_ns = np.concatenate([p[:, 0] for _, p in parts])
    which = np.concatenate([np.full(len(p), j) for j, (_, p) in enumerate(parts)])
    rows = np.concatenate([np.arange(len(p)) for _, p in parts])
    for i in np.lexsort((rows, which, log_ns)):
        topic, k = parts[which[i]][0], int(rows[i])
        limit = HEAD_BYTES if topic in heads else None
        yield topic, int(log_ns[i]), k, log.raw(topic, k, int(log_ns[i]), limit=limit)


def build_index(log: LogFile, fingerprint: str = "") -> LogIndex:
    """One pass over the log's sensor, TF and pose topics (see the module doc)."""
    from storage.sources.log.positions import PositionError, header_of

    index = LogIndex(fingerprint, {n: (t.msgtype, t.count) for n, t in log.topics.items()})
    wanted = [
        n for n, t in log.topics.items() if t.msgtype in SENSOR_TYPES + POSE_TYPES + (TF_MESSAGE,)
    ]
    index.positions = log.scan_positions(wanted)
    log.use_positions(index.positions)
    rows: dict[str, list] = {n: [] for n in wanted}
    frame_ids: dict[str, str] = {}
    last: dict[str, tuple[int, int]] = {}
    tf, tf_static = _TFBuilder(), _TFBuilder()
    heads = {n for n in wanted if log.topics[n].msgtype in (POINTCLOUD2, IMAGE, COMPRESSED_IMAGE)}
    for topic, log_ns, _, raw in _iter_messages(log, wanted, index.positions, heads):
        msgtype = log.topics[topic].msgtype
        if msgtype in SENSOR_TYPES and msgtype != CAMERA_INFO:
            try:  # the header alone: sweeps and images are not deserialised here
                stamp, frame_id = header_of(raw, log.ros1)
            except (PositionError, IndexError, struct_error) as exc:
                raise LogFormatError(
                    f"{where(log.path, topic, None)}: message header cannot be read ({exc}); "
                    "the log is truncated or damaged",
                    log.path,
                    topic=topic,
                ) from None
            frame_ids.setdefault(topic, frame_id.lstrip("/"))
            prev = last.get(topic)
            ordinal = prev[1] + 1 if prev and prev[0] == log_ns else 0
            last[topic] = (log_ns, ordinal)
            rows[topic].append((log_ns, stamp, ordinal))
            continue
        msg = log.deserialize(bytes(raw), msgtype, topic)
        if msgtype == TF_MESSAGE:
            builder = tf_static if topic.rstrip("/").endswith("tf_static") else tf
            for tr in msg.transforms:
                builder.add(tr)
            continue
        stamp = stamp_ns(msg.header)
        frame_ids.setdefault(topic, str(msg.header.frame_id).lstrip("/"))
        if msgtype in POSE_TYPES:
            t, q = _pose_of(msg, msgtype)
            child = str(getattr(msg, "child_frame_id", "")).lstrip("/")
            rows[topic].append((stamp, child, *t, *q))
            continue
        if topic not in index.camera_info:
            index.camera_info[topic] = _camera_info(msg)
        prev = last.get(topic)
        ordinal = prev[1] + 1 if prev and prev[0] == log_ns else 0
        last[topic] = (log_ns, ordinal)
        rows[topic].append((log_ns, stamp, ordinal))
    for topic in wanted:
        msgtype = log.topics[topic].msgtype
        if msgtype in POSE_TYPES:
            r = rows[topic]
            vals = np.array([x[2:] for x in r], np.float64).reshape(-1, 7)
            index.poses[topic] = PoseTrack(
                msgtype,
                frame_ids.get(topic, ""),
                r[0][1] if r else "",
                np.array([x[0] for x in r], np.int64),
                vals[:, :3].copy(),
                vals[:, 3:].copy(),
            )
        elif msgtype in SENSOR_TYPES:
            a = np.array(rows[topic], np.int64).reshape(-1, 3)
            index.streams[topic] = Stream(
                msgtype, frame_ids.get(topic, ""), a[:, 0].copy(), a[:, 1].copy(),
                a[:, 2].astype(np.int32),
            )  # fmt: skip
    index.tf, index.tf_static = tf.build(), tf_static.build()
    return index


# -- the cache ------------------------------------------------------------------------------------
def _pack(index: LogIndex) -> dict[str, np.ndarray]:
    meta = {
        "version": INDEX_VERSION,
        "fingerprint": index.fingerprint,
        "topics": index.topics,
        "streams": {n: [s.msgtype, s.frame_id] for n, s in index.streams.items()},
        "camera_info": {
            n: [c.width, c.height, c.distortion_model, c.frame_id]
            for n, c in index.camera_info.items()
        },
        "poses": {n: [p.msgtype, p.frame_id, p.child_frame_id] for n, p in index.poses.items()},
        "tf_frames": index.tf.frames if index.tf else [],
        "tf_static_frames": index.tf_static.frames if index.tf_static else [],
        "positions": (
            None
            if index.positions is None
            else {
                "topics": list(index.positions.topics),
                "compressions": index.positions.compressions,
            }
        ),
    }
    arrays = {"meta": np.frombuffer(json.dumps(meta).encode(), np.uint8)}
    for k, s in enumerate(index.streams.values()):
        arrays[f"s{k}_log"], arrays[f"s{k}_stamp"] = s.log_ns, s.stamp_ns
        arrays[f"s{k}_ordinal"] = s.ordinal
    for k, c in enumerate(index.camera_info.values()):
        arrays[f"c{k}"] = np.concatenate([c.K.ravel(), c.R.ravel(), c.P.ravel()])
        arrays[f"c{k}_D"] = c.D
    for k, p in enumerate(index.poses.values()):
        arrays[f"p{k}_stamp"], arrays[f"p{k}_tq"] = p.stamp_ns, np.c_[p.t, p.q_wxyz]
    if index.positions is not None:
        arrays["chunks"] = index.positions.chunks
        for k, p in enumerate(index.positions.topics.values()):
            arrays[f"pos{k}"] = p
    for name, tr in (("tf", index.tf), ("tfs", index.tf_static)):
        if tr is not None:
            arrays[f"{name}_ids"] = np.c_[tr.parent, tr.child].astype(np.int32)
            arrays[f"{name}_stamp"], arrays[f"{name}_tq"] = tr.stamp_ns, np.c_[tr.t, tr.q_wxyz]
    return arrays


def _unpack(z) -> LogIndex:
    meta = json.loads(bytes(z["meta"]).decode())
    index = LogIndex(meta["fingerprint"], {n: tuple(v) for n, v in meta["topics"].items()})
    for k, (n, (msgtype, frame_id)) in enumerate(meta["streams"].items()):
        index.streams[n] = Stream(
            msgtype, frame_id, z[f"s{k}_log"], z[f"s{k}_stamp"], z[f"s{k}_ordinal"]
        )
    for k, (n, (w, h, model, frame_id)) in enumerate(meta["camera_info"].items()):
        v = z[f"c{k}"]
        index.camera_info[n] = CameraInfo(
            w, h, v[:9].reshape(3, 3), z[f"c{k}_D"], v[9:18].reshape(3, 3), v[18:].reshape(3, 4),
            model, frame_id,
        )  # fmt: skip
    for k, (n, (msgtype, frame_id, child)) in enumerate(meta["poses"].items()):
        tq = z[f"p{k}_tq"]
        index.poses[n] = PoseTrack(
            msgtype, frame_id, child, z[f"p{k}_stamp"], tq[:, :3].copy(), tq[:, 3:].copy()
        )
    if meta["positions"] is not None:
        index.positions = Positions(
            {t: z[f"pos{k}"] for k, t in enumerate(meta["positions"]["topics"])},
            z["chunks"],
            list(meta["positions"]["compressions"]),
        )
    for name, frames, attr in (("tf", "tf_frames", "tf"), ("tfs", "tf_static_frames", "tf_static")):
        if f"{name}_ids" in z:
            ids, tq = z[f"{name}_ids"], z[f"{name}_tq"]
            setattr(
                index,
                attr,
                Transforms(
                    meta[frames],
                    ids[:, 0],
                    ids[:, 1],
                    z[f"{name}_stamp"],
                    tq[:, :3].copy(),
                    tq[:, 3:].copy(),
                ),  # fmt: skip
            )
    return index


def cache_path(cache_dir: Path, fingerprint: str) -> Path:
    return Path(cache_dir) / "log-index" / f"{fingerprint}.npz"


def load_index(log: LogFile, cache_dir: Path | None) -> LogIndex:
    """The log's index: from the cache when its fingerprint has one, else built (and cached)."""
    fingerprint = quick_fingerprint(log.path, INDEX_VERSION)
    path = cache_path(cache_dir, fingerprint) if cache_dir is not None else None
    if path is not None and path.is_file():
        try:
            index = _unpack(load_npz(path))
            if index.fingerprint == fingerprint:
                log.use_positions(index.positions)
                return index
        except (*NPZ_ERRORS, TypeError, IndexError):  # a damaged cache file is rebuilt
            pass
    index = build_index(log, fingerprint)
    if path is not None:
        save_npz_deterministic(path, compressed=False, **_pack(index))
    return index


__all__ = ["LogIndex", "LogFormatError", "build_index", "load_index"]
