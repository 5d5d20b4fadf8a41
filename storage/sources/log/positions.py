"""Where each message of a log lies, and reading it back in one slice (no copy for uncompressed
chunks).

- MCAP files (``.mcap``): the data section is scanned record by record (``opcode u8, length u64,
  content``); a Chunk record (``start u64, end u64, uncompressed_size u64, crc u32, compression
  string, records``) holds Message records (``channel u16, sequence u32, log_time u64,
  publish_time u64, data``). An uncompressed chunk's messages are slices of the file itself; a
  compressed one (zstd, lz4) is decompressed when one of its messages is read (the last chunk is
  kept).
- ROS 1 bags: rosbags has read the bag's own index (per connection: time, chunk position,
  offset in the chunk); a message record there is ``header_len u32, header, data_len u32, data``.
- ROS 2 bag folders (sqlite3 or MCAP storage inside): no positions; messages are found again by
  their log time through rosbags (storage.sources.log.bag.LogFile.messages).

Positions per topic are ``(n, 4) int64``: log time ns, chunk id (-1: the offset is in the file),
offset, length. Chunks are ``(m, 3) int64``: file offset of the chunk's (compressed) records,
their size, uncompressed size, with ``compressions`` (m,) names.

Also the few message layouts read without a full deserialisation (they hold the bulk of a log):
std_msgs/Header (stamp, frame_id) and sensor_msgs/PointCloud2, in ROS 2's CDR and ROS 1's
serialisation.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

MCAP_MAGIC = b"\x89MCAP0\r\n"
OP_MESSAGE, OP_CHUNK, OP_DATA_END, OP_FOOTER = 0x05, 0x06, 0x0F, 0x02

_u16 = struct.Struct("<H").unpack_from
_u32 = struct.Struct("<I").unpack_from
_u64 = struct.Struct("<Q").unpack_from
_msg_head = struct.Struct("<HIQQ").unpack_from  # channel, sequence, log_time, publish_time


class PositionError(ValueError):
    """A log whose records cannot be walked (cut or damaged): the offset in words."""


@dataclass
class Positions:
    """Message positions of a log: topic -> (n, 4) int64 [log_ns, chunk, offset, length];
    chunks (m, 3) int64 [offset, size, uncompressed size]; compressions (m,) names."""

    topics: dict[str, np.ndarray]
    chunks: np.ndarray
    compressions: list[str]


class _File:
    """Reads a file by offset (``os.pread``: nothing of the file stays mapped or buffered, so
    memory does not grow with what was read)."""

    def __init__(self, fd: int, size: int):
        self.fd, self.size = fd, size

    def read(self, offset: int, length: int) -> bytes:
        if offset < 0 or offset + length > self.size:
            raise PositionError(
                f"{length} bytes at byte {offset} run past the file's end ({self.size} bytes)"
            )
        data = os.pread(self.fd, length, offset)
        if len(data) != length:
            raise PositionError(f"read {len(data)} of {length} bytes at byte {offset}")
        return data


def scan_mcap(path: Path, channels: dict[int, str]) -> Positions:
    """Positions of the messages of ``channels`` (channel id -> topic) in an MCAP file."""
    from rosbags.rosbag2.storage_mcap import DECOMPRESSORS

    rows: dict[str, list] = {t: [] for t in set(channels.values())}
    chunks: list[tuple[int, int, int]] = []
    compressions: list[str] = []
    fd = os.open(path, os.O_RDONLY)
    try:
        f = _File(fd, os.fstat(fd).st_size)
        if f.read(0, 8) != MCAP_MAGIC:
            raise PositionError("not an MCAP file (no magic)")
        pos = 8
        while pos < f.size:
            head = f.read(pos, 9)
            op, length = head[0], _u64(head, 1)[0]
            body = pos + 9
            if body + length > f.size:
                raise PositionError(
                    f"record {op:#04x} at byte {pos} claims {length} bytes, {f.size - body} remain"
                )
            if op == OP_MESSAGE:
                _add(rows, channels, f.read(body, 22), body, length, -1)
            elif op == OP_CHUNK:
                fixed = f.read(body, 32)
                uncompressed, name_len = _u64(fixed, 16)[0], _u32(fixed, 28)[0]
                compression = f.read(body + 32, name_len).decode()
                rec_len = _u64(f.read(body + 32 + name_len, 8), 0)[0]
                start = body + 40 + name_len
                if compression == "":
                    _walk(rows, channels, f, start, rec_len, -1)
                else:
                    if compression not in DECOMPRESSORS:
                        raise PositionError(f"chunk compression {compression!r} at byte {pos}")
                    cid = len(chunks)
                    chunks.append((start, rec_len, uncompressed))
                    compressions.append(compression)
                    data = DECOMPRESSORS[compression](f.read(start, rec_len), uncompressed)
                    _walk(rows, channels, _File.of(data), 0, len(data), cid)
            elif op in (OP_DATA_END, OP_FOOTER):
                break
            pos = body + length
    finally:
        os.close(fd)
    return Positions(_arrays(rows), np.array(chunks, np.int64).reshape(-1, 3), compressions)


def mcap_last_whole_message(path: Path) -> tuple[int, str | None, int | None]:
    """Where a cut MCAP file stops holding whole records: (bytes of whole records, the topic and
    log time of the last whole message before the cut, or None). Chunks are taken whole or not
    at all (a compressed chunk's messages are read)."""
    from rosbags.rosbag2.storage_mcap import DECOMPRESSORS

    topics: dict[int, str] = {}
    last: tuple[str | None, int | None] = (None, None)
    fd = os.open(path, os.O_RDONLY)
    try:
        f = _File(fd, os.fstat(fd).st_size)
        pos = 8
        while pos + 9 <= f.size:
            head = f.read(pos, 9)
            op, length = head[0], _u64(head, 1)[0]
            body = pos + 9
            if body + length > f.size:
                break
            if op == 0x04:  # Channel: id u16, schema u16, topic string
                rec = f.read(body, min(length, 4096))
                n = _u32(rec, 4)[0]
                topics[_u16(rec, 0)[0]] = rec[8 : 8 + n].decode("utf-8", "replace")
            elif op == OP_MESSAGE:
                channel, _, log_time, _ = _msg_head(f.read(body, 22), 0)
                last = (topics.get(channel), log_time)
            elif op == OP_CHUNK:
                fixed = f.read(body, 32)
                uncompressed, name_len = _u64(fixed, 16)[0], _u32(fixed, 28)[0]
                compression = f.read(body + 32, name_len).decode()
                rec_len = _u64(f.read(body + 32 + name_len, 8), 0)[0]
                start = body + 40 + name_len
                inner: _File = f
                if compression:
                    data = DECOMPRESSORS[compression](f.read(start, rec_len), uncompressed)
                    inner, start, rec_len = _Bytes(data), 0, len(data)
                q = start
                while q + 9 <= start + rec_len:
                    h = inner.read(q, 9)
                    if h[0] == 0x04:
                        rec = inner.read(q + 9, min(_u64(h, 1)[0], 4096))
                        topics[_u16(rec, 0)[0]] = rec[8 : 8 + _u32(rec, 4)[0]].decode()
                    elif h[0] == OP_MESSAGE:
                        channel, _, log_time, _ = _msg_head(inner.read(q + 9, 22), 0)
                        last = (topics.get(channel), log_time)
                    q += 9 + _u64(h, 1)[0]
            pos = body + length
    except (PositionError, OSError, KeyError, ValueError):
        pass
    finally:
        os.close(fd)
    return pos, last[0], last[1]


class _Bytes(_File):
    """A decompressed chunk read like a file."""

    def __init__(self, data: bytes):
        self.data, self.size = data, len(data)

    def read(self, offset: int, length: int) -> bytes:
        if offset < 0 or offset + length > self.size:
            raise PositionError(f"{length} bytes at byte {offset} run past the chunk's end")
        return self.data[offset : offset + length]


_File.of = staticmethod(lambda data: _Bytes(data))  # type: ignore[attr-defined]


def _walk(rows, channels, f: _File, start: int, length: int, chunk: int) -> None:
    pos, end = start, start + length
    while pos < end:
        head = f.read(pos, 9)
        op, rec_len = head[0], _u64(head, 1)[0]
        if op == OP_MESSAGE:
            _add(rows, channels, f.read(pos + 9, 22), pos + 9, rec_len, chunk)
        pos += 9 + rec_len
    if pos != end:
        raise PositionError(f"chunk records overrun their chunk by {pos - end} bytes")


def _add(rows, channels, head: bytes, body: int, length: int, chunk: int) -> None:
    channel, _, log_time, _ = _msg_head(head, 0)
    topic = channels.get(channel)
    if topic is not None:
        rows[topic].append((log_time, chunk, body + 22, length - 22))


def _arrays(rows: dict[str, list]) -> dict[str, np.ndarray]:
    out = {}
    for topic, r in rows.items():
        a = np.array(r, dtype=np.int64).reshape(-1, 4)
        out[topic] = a[np.argsort(a[:, 0], kind="stable")]
    return out


def ros1_positions(reader, topics: dict[int, str]) -> Positions:
    """Positions from a rosbags ROS 1 reader's own index (``reader.indexes``, ``reader.chunks``)
    for connections ``topics`` (connection id -> topic)."""
    chunk_ids: dict[int, int] = {}
    chunks, compressions = [], []
    rows: dict[str, list] = {t: [] for t in set(topics.values())}
    fd = os.open(reader.path, os.O_RDONLY)
    try:
        f = _File(fd, os.fstat(fd).st_size)
        for conn_id, topic in topics.items():
            for entry in reader.indexes.get(conn_id, ()):
                chunk = reader.chunks[entry.chunk_pos]
                name = _ros1_compression(chunk.decompressor)
                if name == "none":
                    at = chunk.datapos + entry.offset
                    rows[topic].append((entry.time, -1, *_ros1_data(f, at)))
                    continue
                if entry.chunk_pos not in chunk_ids:
                    chunk_ids[entry.chunk_pos] = len(chunks)
                    chunks.append((chunk.datapos, chunk.datasize, 0))
                    compressions.append(name)
                rows[topic].append((entry.time, chunk_ids[entry.chunk_pos], entry.offset, -1))
    finally:
        os.close(fd)
    return Positions(_arrays(rows), np.array(chunks, np.int64).reshape(-1, 3), compressions)


def _ros1_compression(decompressor) -> str:
    from rosbags.rosbag1.reader import decompressors

    return next((k for k, v in decompressors.items() if v is decompressor), "?")


def _ros1_data(f: _File, at: int) -> tuple[int, int]:
    """(offset, length) of the data of the ROS 1 record at ``at`` (skipping connection records
    the bag may interleave)."""
    while True:
        header_len = _u32(f.read(at, 4), 0)[0]
        header = f.read(at + 4, header_len)
        data_at = at + 4 + header_len
        data_len = _u32(f.read(data_at, 4), 0)[0]
        if b"op=\x02" in header:
            return data_at + 4, data_len
        at = data_at + 4 + data_len


class Fetcher:
    """Reads messages back by position (one per process; opens the file lazily)."""

    def __init__(self, path: Path, positions: Positions, ros1: bool):
        self.path, self.positions, self.ros1 = Path(path), positions, ros1
        self._file: _File | None = None
        self._chunk: tuple[int, _Bytes] | None = None

    def _open(self) -> _File:
        if self._file is None:
            fd = os.open(self.path, os.O_RDONLY)
            self._file = _File(fd, os.fstat(fd).st_size)
        return self._file

    def close(self) -> None:
        if self._file is not None:
            os.close(self._file.fd)
        self._file = self._chunk = None

    def __getstate__(self):
        return {**self.__dict__, "_file": None, "_chunk": None}

    def raw(self, topic: str, k: int, limit: int | None = None) -> bytes:
        """Message k of ``topic`` (its first ``limit`` bytes when given)."""
        _, chunk, offset, length = (int(v) for v in self.positions.topics[topic][k])
        f = self._open() if chunk < 0 else self._chunk_data(chunk)
        if length < 0:  # ROS 1 in a compressed chunk: the record's data within it
            offset, length = _ros1_data(f, offset)
        return f.read(offset, length if limit is None else min(limit, length))

    def _chunk_data(self, chunk: int) -> _Bytes:
        if self._chunk is None or self._chunk[0] != chunk:
            start, size, uncompressed = (int(v) for v in self.positions.chunks[chunk])
            name = self.positions.compressions[chunk]
            raw = self._open().read(start, size)
            if self.ros1:
                from rosbags.rosbag1.reader import decompressors

                data = decompressors[name](raw)
            else:
                from rosbags.rosbag2.storage_mcap import DECOMPRESSORS

                data = DECOMPRESSORS[name](raw, uncompressed)
            self._chunk = (chunk, _Bytes(bytes(data)))
        return self._chunk[1]


# -- message layouts ------------------------------------------------------------------------------
class _Cursor:
    """Reads ROS 2 CDR (aligned, relative to the byte after the 4-byte encapsulation header) or
    ROS 1 (packed) fields from a buffer."""

    def __init__(self, buf, ros1: bool):
        self.buf, self.ros1 = buf, ros1
        if ros1:
            self.pos, self.origin, self.end = 0, 0, "<"
        else:
            self.end = ">" if buf[1] == 0 else "<"  # CDR_BE = 00 00, CDR_LE = 00 01
            self.pos, self.origin = 4, 4

    def _align(self, n: int) -> None:
        if not self.ros1:
            self.pos += -(self.pos - self.origin) % n

    def u8(self) -> int:
        v = self.buf[self.pos]
        self.pos += 1
        return v

    def u32(self) -> int:
        self._align(4)
        (v,) = struct.unpack_from(self.end + "I", self.buf, self.pos)
        self.pos += 4
        return v

    def i32(self) -> int:
        self._align(4)
        (v,) = struct.unpack_from(self.end + "i", self.buf, self.pos)
        self.pos += 4
        return v

    def string(self) -> str:
        n = self.u32()
        raw = bytes(self.buf[self.pos : self.pos + n])
        self.pos += n
        return raw.rstrip(b"\0").decode("utf-8", "replace")

    def header(self) -> tuple[int, str]:
        if self.ros1:
            self.u32()  # seq
        sec, nsec = self.i32(), self.u32()
        return sec * 1_000_000_000 + nsec, self.string()

    def blob(self) -> memoryview:
        n = self.u32()
        if self.pos + n > len(self.buf):
            raise PositionError(f"a {n}-byte array ends past its message ({len(self.buf)} bytes)")
        out = memoryview(self.buf)[self.pos : self.pos + n]
        self.pos += n
        return out


def header_of(buf, ros1: bool) -> tuple[int, str]:
    """(stamp ns, frame_id) of a message whose first field is a std_msgs/Header."""
    return _Cursor(buf, ros1).header()


@dataclass(frozen=True)
class RawCloud:
    """A sensor_msgs/PointCloud2 read in place: data is a view into the log."""

    stamp_ns: int
    frame_id: str
    height: int
    width: int
    fields: list[tuple[str, int, int, int]]
    is_bigendian: bool
    point_step: int
    row_step: int
    data: memoryview


def pointcloud2_of(buf, ros1: bool) -> RawCloud:
    """Parse a serialised PointCloud2 without copying its data."""
    c = _Cursor(buf, ros1)
    stamp, frame_id = c.header()
    height, width = c.u32(), c.u32()
    fields = []
    for _ in range(c.u32()):
        name = c.string()
        offset = c.u32()
        datatype = c.u8()
        count = c.u32()
        fields.append((name, offset, datatype, count))
    bigendian = bool(c.u8())
    point_step, row_step = c.u32(), c.u32()
    data = c.blob()
    return RawCloud(stamp, frame_id, height, width, fields, bigendian, point_step, row_step, data)
