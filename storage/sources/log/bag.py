"""Robot logs on disk: ROS 1 ``.bag``, ROS 2 bag folders (sqlite3 or MCAP storage) and ``.mcap``
files, opened with ``rosbags`` (pure Python, no ROS install).

What lives here: which paths are logs (:func:`find_logs`: a log file, a ROS 2 bag folder, or a
folder holding several; each log is a sequence named by its stem), the files of a log (for
fingerprints and the planner's stat signature), a quick fingerprint for caches, and
:class:`LogFile`, an open log: its topics, messages of some topics in log order (optionally in a
log-time window, which rosbags serves from the log's own chunk index without reading the rest),
and deserialization. Every failure is a :class:`LogFormatError` naming the file, and the topic and
stamp where there are some.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from storage.files import InputError

LOG_SUFFIXES = (".bag", ".mcap")
#: a ROS 2 bag folder holds this file beside its storage files (.db3 / .mcap)
ROS2_METADATA = "metadata.yaml"
#: bytes read at each end of every file of a log for its cache fingerprint
FINGERPRINT_EDGE_BYTES = 1 << 20


class LogFormatError(InputError):
    """Bad input in a robot log: ``path`` (the log), and ``topic`` / ``stamp_ns`` where known."""

    def __init__(
        self,
        message: str,
        path: Path | str | None = None,
        frame: int | None = None,
        sequence: str | None = None,
        topic: str | None = None,
        stamp_ns: int | None = None,
    ):
        super().__init__(message, path, frame, sequence)
        self.topic = topic
        self.stamp_ns = stamp_ns


def where(path: Path, topic: str | None = None, stamp_ns: int | None = None, k=None) -> str:
    """``path, topic T, stamp S ns (message k)``: how messages name a place in a log."""
    text = str(path)
    if topic is not None:
        text += f", topic {topic}"
    if stamp_ns is not None:
        text += f", stamp {int(stamp_ns)} ns ({int(stamp_ns) / 1e9:.6f} s)"
    if k is not None:
        text += f" (message {k})"
    return text


def is_log(path: Path) -> bool:
    """A ROS 1 / MCAP log file, or a ROS 2 bag folder."""
    path = Path(path)
    if path.is_dir():
        return (path / ROS2_METADATA).is_file()
    return path.suffix in LOG_SUFFIXES


def find_logs(root: Path) -> dict[str, Path]:
    """Sequence name -> log of a dataset root: the root itself when it is a log, else the logs
    directly inside it (files and ROS 2 bag folders), by stem; hidden names and ``gt`` skipped."""
    root = Path(root)
    if is_log(root):
        return {root.stem if root.is_file() else root.name: root}
    out: dict[str, Path] = {}
    try:
        entries = sorted(os.scandir(root), key=lambda e: e.name)
    except OSError:
        return {}
    for e in entries:
        if e.name.startswith((".", "_")) or e.name == "gt":
            continue
        p = Path(e.path)
        if is_log(p):
            name = p.stem if p.is_file() else p.name
            if name in out:
                raise LogFormatError(
                    f"{root}: two logs are named {name!r} ({out[name].name}, {p.name}); a "
                    "sequence is named by its log's stem, so rename one",
                    p,
                )
            out[name] = p
    return out


def holds_logs(root: Path) -> bool:
    """Whether a dataset root is a log or a folder holding logs (and so read by the log source)."""
    try:
        return bool(find_logs(root))
    except LogFormatError:
        return True


def log_files(path: Path) -> list[Path]:
    """The files of a log: itself, or a ROS 2 bag folder's metadata.yaml and storage files."""
    path = Path(path)
    if not path.is_dir():
        return [path]
    return sorted(p for p in path.iterdir() if p.is_file() and not p.name.startswith("."))


def log_layout(path: Path) -> list[tuple[str, bool]]:
    """(path, is a folder to list) entries of a log for the planner's stat signature."""
    path = Path(path)
    return [(os.fspath(path), path.is_dir())]


def quick_fingerprint(path: Path, salt: str = "") -> str:
    """A cache key of a log's content, read cheaply: every file's name, size, mtime and the
    sha256 of its first and last MiB (a log's index lives at its end: a rewritten or extended log
    changes it). Not the content hash (storage.manifest does that for the planner)."""
    h = hashlib.sha256(salt.encode())
    for f in log_files(path):
        st = f.stat()
        h.update(f"{f.name}:{st.st_size}:{st.st_mtime_ns};".encode())
        with open(f, "rb") as fh:
            h.update(fh.read(FINGERPRINT_EDGE_BYTES))
            if st.st_size > FINGERPRINT_EDGE_BYTES:
                fh.seek(max(FINGERPRINT_EDGE_BYTES, st.st_size - FINGERPRINT_EDGE_BYTES))
                h.update(fh.read())
    return h.hexdigest()[:32]


@dataclass(frozen=True)
class TopicInfo:
    """A topic of a log: msgtype ('sensor_msgs/msg/PointCloud2', ROS 1 names normalised), count
    (messages, from the log's index), connections (rosbags)."""

    name: str
    msgtype: str
    count: int
    connections: tuple


def _open_hint(path: Path, text: str) -> str:
    low = text.lower()
    if "not indexed" in low or "reindex" in low:
        return (
            f"{path}: the ROS 1 bag is not indexed (its recording was cut before `rosbag "
            f"record` closed it); reindex it with `rosbag reindex {path}` (ROS 1 tools), which "
            "writes the index in place and keeps a .orig.bag copy, then run again"
        )
    if path.suffix == ".mcap" and ("end magic" in low or "footer" in low or "summary" in low):
        from storage.sources.log.positions import mcap_last_whole_message

        whole, topic, log_ns = mcap_last_whole_message(path)
        last = (
            f"; its last whole message is on topic {topic} at log time {log_ns} ns "
            f"({log_ns / 1e9:.6f} s), {whole} of {path.stat().st_size} bytes whole"
            if log_ns is not None
            else ""
        )
        return (
            f"{path}: the MCAP file is truncated or was not closed (no valid footer: {text}"
            f"{last}); recover what it holds with `mcap recover {path} -o fixed.mcap` (the mcap "
            "CLI)"
        )
    return f"{path}: not a readable log ({text})"


class LogFile:
    """An open log. Not picklable on purpose: each process opens its own (:class:`LogSequence`
    reopens lazily)."""

    def __init__(self, path: Path):
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        self.path = Path(path)
        if not self.path.exists():
            raise LogFormatError(f"{self.path}: log not found", self.path)
        self.ros1 = self.path.is_file() and self.path.suffix == ".bag"
        try:
            self._reader = AnyReader(
                [self.path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)
            )
            self._reader.open()
        except Exception as exc:  # noqa: BLE001 - rosbags raises many kinds for a broken file
            raise LogFormatError(
                _open_hint(self.path, f"{type(exc).__name__}: {exc}"), path
            ) from None
        topics: dict[str, list] = {}
        for c in self._reader.connections:
            topics.setdefault(c.topic, []).append(c)
        self.topics = {
            name: TopicInfo(
                name, conns[0].msgtype, int(sum(c.msgcount for c in conns)), tuple(conns)
            )
            for name, conns in sorted(topics.items())
        }

        self.kind = "ros1" if self.ros1 else ("mcap" if self.path.suffix == ".mcap" else "ros2")
        self._fetcher = None

    def scan_positions(self, topics: list[str]):
        """Message positions of ``topics`` (storage.sources.log.positions.Positions), or None for a
        ROS 2 bag folder (read by log time instead)."""
        from storage.sources.log.positions import PositionError, ros1_positions, scan_mcap

        wanted = {c.id: t for t in topics for c in self.topics[t].connections}
        try:
            if self.kind == "mcap":
                return scan_mcap(self.path, wanted)
            if self.kind == "ros1":
                return ros1_positions(self._reader.readers[0], wanted)
        except (PositionError, OSError, ValueError, IndexError, KeyError) as exc:
            raise LogFormatError(
                f"{self.path}: the log's records cannot be walked ({type(exc).__name__}: {exc}); "
                "the log is truncated or damaged",
                self.path,
            ) from None
        return None

    def use_positions(self, positions) -> None:
        """Read messages back through these positions (:meth:`raw`)."""
        from storage.sources.log.positions import Fetcher

        self._fetcher = Fetcher(self.path, positions, self.ros1) if positions else None

    def raw(self, topic: str, k: int, log_ns: int, ordinal: int = 0, limit: int | None = None):
        """The serialised message k of ``topic`` (log time ``log_ns``): read at its position (its
        first ``limit`` bytes when given), or (ROS 2 bag folders) the ``ordinal``-th message at
        that log time."""
        if self._fetcher is not None:
            from storage.sources.log.positions import PositionError

            try:
                return self._fetcher.raw(topic, k, limit)
            except (PositionError, OSError, ValueError) as exc:
                raise LogFormatError(
                    f"{where(self.path, topic, None, k)}: message cannot be read "
                    f"({type(exc).__name__}: {exc}); the log is truncated or damaged",
                    self.path,
                    topic=topic,
                ) from None
        for j, (_, _, raw) in enumerate(self.messages([topic], log_ns, log_ns + 1)):
            if j == ordinal:
                return raw
        raise LogFormatError(
            f"{where(self.path, topic, None, k)}: no message at log time {log_ns} ns any more "
            "(the index was made from another version of the log?)",
            self.path,
            topic=topic,
        )

    def close(self) -> None:
        reader, self._reader = getattr(self, "_reader", None), None
        if reader is not None:
            reader.close()
        if getattr(self, "_fetcher", None) is not None:
            self._fetcher.close()

    def __enter__(self) -> LogFile:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def of_type(self, *msgtypes: str) -> list[TopicInfo]:
        return [t for t in self.topics.values() if t.msgtype in msgtypes]

    def deserialize(self, raw, msgtype: str, topic: str, stamp_ns=None):
        try:
            return self._reader.deserialize(raw, msgtype)
        except Exception as exc:  # noqa: BLE001 - a cut or foreign message
            raise LogFormatError(
                f"{where(self.path, topic, stamp_ns)}: message cannot be decoded as {msgtype} "
                f"({type(exc).__name__}: {exc}; a truncated log?)",
                self.path,
                topic=topic,
                stamp_ns=stamp_ns,
            ) from None

    def messages(
        self, topics: list[str], start: int | None = None, stop: int | None = None
    ) -> Iterator[tuple[str, int, bytes]]:
        """(topic, log time ns, raw bytes) of the topics' messages in log-time order, those with
        ``start <= log time < stop`` when given."""
        conns = [c for t in topics for c in self.topics[t].connections]
        if not conns:
            return
        try:
            for conn, log_ns, raw in self._reader.messages(conns, start=start, stop=stop):
                yield conn.topic, int(log_ns), raw
        except LogFormatError:
            raise
        except Exception as exc:  # noqa: BLE001 - a cut chunk, a bad compression block
            what = topics[0] if len(topics) == 1 else ", ".join(topics)
            at = f" from log time {start} ns" if start is not None else ""
            raise LogFormatError(
                f"{self.path}, topic {what}: reading messages{at} failed "
                f"({type(exc).__name__}: {exc}); the log is truncated or damaged",
                self.path,
                topic=topics[0] if len(topics) == 1 else None,
                stamp_ns=start,
            ) from None
