"""Decoding ``sensor_msgs/PointCloud2`` from its ``fields`` (no driver-specific layout assumed).

A PointCloud2 message describes its own layout: ``fields`` (name, byte offset, datatype, count)
inside a ``point_step``-byte record, ``row_step`` bytes per row of ``height`` x ``width`` points,
``is_bigendian``. Any offsets, datatypes, padding and endianness are decoded with one numpy
structured dtype built from the fields, so nothing is copied but the columns we keep.

Kept columns (by name, the first present wins):

- x, y, z (required): metres in the message's frame (``header.frame_id``).
- intensity / reflectivity / signal: float32, as stored (no scaling).
- per-point time t / time / timestamp / time_stamp / offset_time: converted to float32 seconds
  since the message's header stamp. Its unit is detected from its values: the span of one sweep
  (a LiDAR turns at 5-20 Hz, so a sweep lasts 0.05-0.2 s) is read in the candidate units
  (s, ms, us, ns) and the unit whose span falls in [MIN_SWEEP_S, MAX_SWEEP_S] is taken (integer
  fields: ns first, then us, ms; float fields: s first); values that are absolute Unix times
  (more than ABSOLUTE_AFTER_S) are made relative to the header stamp.
- ring: the row of an organised cloud (``height`` > 1), else a ``ring`` field, else 0.

Dropped points: no-returns ((0, 0, 0), as the Ouster driver writes them in its organised 128 x
1024 cloud) and points with a NaN or inf coordinate (``is_dense`` false clouds), and those outside
``[min_range_m, max_range_m]``. ``index`` keeps each kept point's position in the message (row-major)
so per-point labels stay aligned.

The Ouster ROS driver's default point (``ouster_ros::Point``, 48 bytes, 16-byte aligned): x y z
float32 at 0 4 8, intensity float32 at 16, t uint32 ns at 20, reflectivity uint16 at 24, ring
uint16 at 26, ambient uint16 at 28, range uint32 at 32 (:data:`OUSTER_FIELDS`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tasks.bounds import sweep_problem

#: sensor_msgs/PointField datatypes -> numpy base type (size in bytes follows)
DATATYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
INTENSITY_NAMES = ("intensity", "reflectivity", "signal", "i")
TIME_NAMES = ("t", "time", "timestamp", "time_stamp", "offset_time")
#: a sweep's time span must fall in this range, in seconds, for a unit to be taken
MIN_SWEEP_S, MAX_SWEEP_S = 0.01, 0.5
#: per-point times beyond this many seconds are absolute (Unix) times, not offsets in the sweep
ABSOLUTE_AFTER_S = 1.0e8
#: values per second of each unit (times are divided by it: ns / 1e9 as the CODa reader does)
PER_SECOND = {"s": 1.0, "ms": 1e3, "us": 1e6, "ns": 1e9}

#: the Ouster ROS driver's ``ouster_ros::Point``: (name, offset, datatype, count), point_step 48
OUSTER_FIELDS = (
    ("x", 0, 7, 1),
    ("y", 4, 7, 1),
    ("z", 8, 7, 1),
    ("intensity", 16, 7, 1),
    ("t", 20, 6, 1),
    ("reflectivity", 24, 4, 1),
    ("ring", 26, 4, 1),
    ("ambient", 28, 4, 1),
    ("range", 32, 6, 1),
)
OUSTER_POINT_STEP = 48


class PointLayoutError(ValueError):
    """A PointCloud2 whose fields cannot be decoded (the reader adds file, topic and stamp)."""


@dataclass(frozen=True)
class Field:
    name: str
    offset: int
    datatype: int
    count: int = 1


@dataclass(frozen=True)
class Layout:
    """What a cloud's fields mean to us: the columns kept and the time unit, in words for
    check-data (``describe``)."""

    intensity: str | None
    time: str | None
    time_unit: str | None
    time_absolute: bool
    ring: str | None

    def describe(self) -> str:
        parts = ["x y z", f"intensity: {self.intensity or 'none'}"]
        if self.time:
            rel = "absolute, made relative to the stamp" if self.time_absolute else "relative"
            parts.append(f"time: {self.time} in {self.time_unit} ({rel})")
        else:
            parts.append("time: none")
        return ", ".join(parts)


@dataclass(frozen=True)
class DecodedCloud:
    """One decoded sweep. points (N, 3) float32 metres, message frame; intensity (N,) float32
    (zeros when the cloud has none: intensity_present False); time_s (N,) float32 seconds since
    the header stamp, or None; ring (N,) uint16; index (N,) int64 position in the message."""

    points: np.ndarray
    intensity: np.ndarray
    time_s: np.ndarray | None
    ring: np.ndarray
    index: np.ndarray
    intensity_present: bool
    layout: Layout


def _dtype(fields: list[Field], point_step: int, bigendian: bool) -> np.dtype:
    order = ">" if bigendian else "<"
    names, formats, offsets = [], [], []
    spans: dict[str, tuple[int, int]] = {}
    for f in fields:
        if f.datatype not in DATATYPES:
            raise PointLayoutError(
                f"field {f.name!r} has datatype {f.datatype}, expected 1..8 "
                "(INT8 UINT8 INT16 UINT16 INT32 UINT32 FLOAT32 FLOAT64)"
            )
        base = np.dtype(order + DATATYPES[f.datatype])
        if f.count < 1 or f.offset < 0 or f.offset + base.itemsize * f.count > point_step:
            raise PointLayoutError(
                f"field {f.name!r} at offset {f.offset} ({f.count} x {base.itemsize} bytes) does "
                f"not fit a point_step of {point_step} bytes"
            )
        if f.name in names:
            continue  # a repeated name: the first one counts
        end = f.offset + base.itemsize * f.count
        for other, (start, stop) in spans.items():
            if f.offset < stop and start < end:  # x and y sharing bytes decode to garbage
                raise PointLayoutError(
                    f"field {f.name!r} (bytes {f.offset}..{end - 1}) overlaps field {other!r} "
                    f"(bytes {start}..{stop - 1}) in a point_step of {point_step} bytes"
                )
        spans[f.name] = (f.offset, end)
        names.append(f.name)
        formats.append(base if f.count == 1 else (base, (f.count,)))
        offsets.append(f.offset)
    return np.dtype(
        {"names": names, "formats": formats, "offsets": offsets, "itemsize": point_step}
    )


def time_unit(values: np.ndarray, integer: bool) -> tuple[str | None, bool]:
    """(unit, absolute) of per-point times from their values (see the module doc); (None, False)
    when no unit gives a plausible sweep span (the reader says so and drops the times)."""
    finite = values[np.isfinite(values)] if values.dtype.kind == "f" else values
    if finite.size == 0:
        return None, False
    lo, hi = float(finite.min()), float(finite.max())
    span = hi - lo
    candidates = ("ns", "us", "ms", "s") if integer else ("s", "ms", "us", "ns")
    for unit in candidates:
        absolute = lo / PER_SECOND[unit] > ABSOLUTE_AFTER_S
        if span == 0.0 and not absolute:
            return candidates[0], False  # one column only: every point at the stamp
        if MIN_SWEEP_S <= span / PER_SECOND[unit] <= MAX_SWEEP_S:
            return unit, absolute
    return None, False


def decode_pointcloud2(
    fields: list[Field],
    data: np.ndarray | bytes | memoryview,
    *,
    height: int,
    width: int,
    point_step: int,
    row_step: int,
    is_bigendian: bool = False,
    stamp_ns: int = 0,
    min_range_m: float = 0.0,
    max_range_m: float = math.inf,
) -> DecodedCloud:
    """Decode a PointCloud2 (see the module doc). ``stamp_ns``: the header stamp, for absolute
    per-point times. PointLayoutError names the field or size that does not fit."""
    names = [f.name for f in fields]
    missing = [c for c in "xyz" if c not in names]
    if missing:
        raise PointLayoutError(
            f"no {' '.join(missing)} field (fields: {', '.join(names) or 'none'}); x, y and z are "
            "required"
        )
    if point_step <= 0 or width < 0 or height < 0:
        raise PointLayoutError(f"point_step {point_step}, {height} x {width} points: not a cloud")
    if row_step < width * point_step:
        raise PointLayoutError(
            f"row_step {row_step} < width {width} x point_step {point_step}: rows overlap"
        )
    buf = np.frombuffer(data, dtype=np.uint8)
    if buf.size < height * row_step:
        raise PointLayoutError(
            f"{buf.size} data bytes, expected height {height} x row_step {row_step} = "
            f"{height * row_step} (a cut message?)"
        )
    dtype = _dtype(fields, point_step, bool(is_bigendian))
    n = height * width
    if row_step == width * point_step:
        records = buf[: n * point_step].view(dtype)
    else:  # padded rows: one view per row, concatenated
        rows = buf[: height * row_step].reshape(height, row_step)[:, : width * point_step]
        records = np.ascontiguousarray(rows).reshape(-1).view(dtype)
    for c in "xyz":
        if dtype.fields[c][0].shape:
            raise PointLayoutError(f"field {c!r} has count > 1; expected one value per point")
    xyz = np.empty((n, 3), dtype=np.float32)
    for k, c in enumerate("xyz"):
        xyz[:, k] = records[c]
    # plausibility (tasks/bounds.py) of the returns (NaN is a ROS organised cloud's no-return)
    problem = sweep_problem(xyz[np.isfinite(xyz).all(axis=1)])
    if problem:
        raise PointLayoutError(f"implausible sweep: {problem}")
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    # the CODa reader's range test: np.linalg.norm of float32 rows, which sums the squares as
    # (x*x + y*y) + z*z in float32; written out it is the same bits, 8x faster
    # (tests/test_log_decoding.py checks the equality)
    rng = np.sqrt(x * x + y * y + z * z)
    keep = np.isfinite(rng) & (rng > max(min_range_m, 1e-6)) & (rng <= max_range_m)
    index = np.flatnonzero(keep)
    intensity_name = next((c for c in INTENSITY_NAMES if c in dtype.names), None)
    if intensity_name is not None:
        intensity = records[intensity_name][index].astype(np.float32)
        present = bool(index.size == 0 or np.any(intensity != 0))
    else:
        intensity, present = np.zeros(index.size, np.float32), False
    time_name = next((c for c in TIME_NAMES if c in dtype.names), None)
    time_s, unit, absolute = None, None, False
    if time_name is not None:
        raw = records[time_name][index]
        unit, absolute = time_unit(raw, raw.dtype.kind in "iu")
        if unit is not None:
            if absolute:  # integer nanoseconds stay exact through the subtraction
                if unit == "ns" and raw.dtype.kind in "iu":
                    rel = (raw.astype(np.int64) - np.int64(stamp_ns)).astype(np.float64) / 1e9
                else:
                    rel = raw.astype(np.float64) / PER_SECOND[unit] - stamp_ns / 1e9
            else:
                rel = raw.astype(np.float64) / PER_SECOND[unit]
            time_s = rel.astype(np.float32)
    if height > 1:
        ring, ring_name = (index // max(width, 1)).astype(np.uint16), "row"
    elif "ring" in dtype.names:
        ring, ring_name = records["ring"][index].astype(np.uint16), "ring"
    else:
        ring, ring_name = np.zeros(index.size, np.uint16), None
    return DecodedCloud(
        points=xyz[index],
        intensity=intensity,
        time_s=time_s,
        ring=ring,
        index=index.astype(np.int64),
        intensity_present=present,
        layout=Layout(intensity_name, time_name, unit, absolute, ring_name),
    )


def encode_pointcloud2(
    columns: dict[str, np.ndarray], fields=OUSTER_FIELDS, point_step: int = OUSTER_POINT_STEP
) -> bytes:
    """Pack per-point columns ((N,) each, by field name; a field not given is 0) into
    ``point_step``-byte little-endian records laid out as ``fields`` (name, offset, datatype,
    count): the inverse of :func:`decode_pointcloud2`, used by the log writer."""
    dtype = _dtype([Field(*f) for f in fields], point_step, False)
    n = len(next(iter(columns.values())))
    out = np.zeros(n, dtype=dtype)
    for name, values in columns.items():
        out[name] = values
    return out.tobytes()
