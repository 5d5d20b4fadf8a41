"""The occupancy store: one Zarr v3 group per sequence and version; field by field in SCHEMA.md.

Arrays (axis order ``[frame, x, y, z]``, grid in the ``base`` frame, see tasks.conventions):

- ``semantics`` uint8 (F, X, Y, Z): class id 0..10 (9 unclassified), fill FREE (10) -- unknown voxels hold FREE and
  are told apart by the masks (Occ3D convention).
- ``instances`` uint16 (F, X, Y, Z): pedestrian track id per voxel, 0 = none.
- ``mask_lidar``, ``mask_camera`` uint8 (F, X, Y, Z): 1 observed, 0 unknown.
- ``velocity`` float16 (F, X, Y, Z, 2): (vx, vy) of pedestrian voxels, m/s, base frame; 0 elsewhere.

Chunking (measured, see SCHEMA.md): a *write unit* is ``frames_per_chunk`` whole frames. Coarse
grids (a frame under ~1 MB) use one chunk per write unit; fine grids use ~1 MB spatial chunks
inside one shard per write unit. Frames never written cost nothing; on fine grids chunks equal
to the fill value (all free / all unknown) are not stored either (``skip_empty_chunks``). Writes must cover whole
write units: zarr loses data when two processes write parts of one chunk or shard
(zarr-python#3682), so :func:`write_frames` refuses misaligned regions.

Publication (staging directory, renames, ``current.json``) is :mod:`storage.publish`.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zarr
from zarr.codecs import ZstdCodec

from storage.layout import CURRENT_FILE, OCCUPANCY_DIR, StoreError
from tasks.conventions import CLASS_NAMES, FREE

STORE_FORMAT_VERSION = 2  # 2: class 9 unclassified, free 10

#: a frame (one uint8 grid) above this many bytes is "fine": spatial chunks inside shards.
FINE_FRAME_BYTES = 1 << 20
#: coarse grids: at most this many uncompressed bytes (uint8 arrays) in one multi-frame chunk.
MAX_COARSE_CHUNK_BYTES = 8 << 20
#: target bytes of one uncompressed spatial chunk on fine grids.
TARGET_CHUNK_BYTES = 1 << 20
ZSTD_LEVEL = 1
#: fine-grid chunks are halved along z down to this many voxels before x / y are cut.
MIN_SLAB_Z = 16

DIMS = ("frame", "x", "y", "z")


@dataclass(frozen=True)
class ArraySpec:
    dtype: np.dtype
    fill_value: Any
    extra_shape: tuple[int, ...] = ()
    extra_dims: tuple[str, ...] = ()
    description: str = ""


ARRAYS: dict[str, ArraySpec] = {
    "semantics": ArraySpec(
        np.dtype(np.uint8), FREE, description="class id, FREE where free or unknown"
    ),
    "instances": ArraySpec(np.dtype(np.uint16), 0, description="pedestrian track id, 0 none"),
    "mask_lidar": ArraySpec(
        np.dtype(np.uint8), 0, description="1 observed by the LiDAR, 0 unknown"
    ),
    "mask_camera": ArraySpec(np.dtype(np.uint8), 0, description="1 observed by cam0, 0 unknown"),
    "velocity": ArraySpec(
        np.dtype(np.float16), 0.0, (2,), ("component",), "pedestrian (vx, vy), m/s, base frame"
    ),
}


@dataclass(frozen=True)
class StoreLayout:
    """How a store is cut. Work split along frames must fall on multiples of ``frames_per_chunk``.

    num_frames: F. grid_shape: (X, Y, Z) voxels. frames_per_chunk: frames per write unit (chunk
    or shard). chunk_shape: the (inner) chunk of the uint8 arrays, (frames, cx, cy, cz).
    sharded: True when chunks sit inside shards of ``(frames_per_chunk, X', Y', Z')``.
    """

    num_frames: int
    grid_shape: tuple[int, int, int]
    frames_per_chunk: int
    chunk_shape: tuple[int, int, int, int]
    sharded: bool

    def write_units(self) -> list[tuple[int, int]]:
        """[start, stop) frame ranges of the write units, in order (the last may be partial)."""
        return [
            (s, min(s + self.frames_per_chunk, self.num_frames))
            for s in range(0, self.num_frames, self.frames_per_chunk)
        ]


def choose_chunks(
    grid_shape: tuple[int, int, int], frames_per_chunk: int
) -> tuple[tuple[int, ...], bool]:
    """Chunk shape (frames, cx, cy, cz) of a uint8 array and whether shards are used."""
    X, Y, Z = grid_shape
    frame_bytes = X * Y * Z
    if frame_bytes <= FINE_FRAME_BYTES:
        if frames_per_chunk * frame_bytes <= MAX_COARSE_CHUNK_BYTES:
            return (frames_per_chunk, X, Y, Z), False
        # many mid-size frames: whole-frame chunks of k frames (k divides the shard) in shards
        limit = max(1, MAX_COARSE_CHUNK_BYTES // frame_bytes)
        k = max(d for d in range(1, limit + 1) if frames_per_chunk % d == 0)
        return (k, X, Y, Z), True
    spatial = [X, Y, Z]
    # ~1 MB chunks cut as thin z slabs first: slabs above the ground are all free and skipped,
    # and a slab compresses 3.5x better than a cube (measured on 0.02 m output, SCHEMA.md)
    while math.prod(spatial) > TARGET_CHUNK_BYTES:
        axis = 2 if spatial[2] > MIN_SLAB_Z else int(np.argmax(spatial[:2]))
        spatial[axis] = math.ceil(spatial[axis] / 2)
    return (1, *spatial), True


def _shard_shape(
    chunks: tuple[int, ...], grid_shape: tuple[int, int, int], fpc: int
) -> tuple[int, ...]:
    spatial = tuple(math.ceil(n / c) * c for n, c in zip(grid_shape, chunks[1:]))
    return (fpc, *spatial)


def create_store(
    path: str | os.PathLike,
    num_frames: int,
    grid_shape: tuple[int, int, int],
    frames_per_chunk: int,
    attrs: Mapping[str, Any],
    skip_empty_chunks: bool | None = None,
) -> StoreLayout:
    """Create an empty store (all fill values) at ``path``; returns its layout.

    skip_empty_chunks: have :func:`write_frames` check each chunk and not store those equal to
    the fill value. Off by default (None): on 0.02 m output it saved ~10 % of the bytes (107 vs
    120 KB per frame) and read 1.3x faster but wrote 3.5x slower (0.23 vs 0.81 frames/s, `mobileocc
    bench --quick` on an idle 2-core machine); on coarse grids a many-frame chunk is never all fill
    and the check cost 4-5x the write time. Frames never written cost nothing either way.

    attrs: group attributes, JSON-serialisable; by convention ``range_min`` / ``range_max`` (3
    floats, m, base frame), ``voxel_size_m``, ``config_hash``, ``code_version``. ``frame``,
    the class table and the store format version are added here. An existing store is replaced.
    """
    grid_shape = tuple(int(n) for n in grid_shape)
    if len(grid_shape) != 3 or min(grid_shape) < 1:
        raise StoreError(
            f"create_store({path}): grid_shape must be 3 positive ints, got {grid_shape}"
        )
    if num_frames < 1 or frames_per_chunk < 1:
        raise StoreError(
            f"create_store({path}): num_frames ({num_frames}) and frames_per_chunk "
            f"({frames_per_chunk}) must be >= 1"
        )
    frames_per_chunk = min(int(frames_per_chunk), int(num_frames))
    chunks, sharded = choose_chunks(grid_shape, frames_per_chunk)
    if skip_empty_chunks is None:  # measured: the write cost outweighs ~10 % of the bytes
        skip_empty_chunks = False
    group_attrs = dict(attrs)
    group_attrs.update(
        {
            "frame": "base",
            "axis_order": list(DIMS),
            "class_names": list(CLASS_NAMES),
            "class_ids": list(range(len(CLASS_NAMES))),
            "free_class": FREE,
            "store_format_version": STORE_FORMAT_VERSION,
            "frames_per_chunk": frames_per_chunk,
            "skip_empty_chunks": bool(skip_empty_chunks),
        }
    )
    json.dumps(group_attrs)  # fail here, naming nothing half-created, if not serialisable
    group = zarr.open_group(str(path), mode="w", zarr_format=3, attributes=group_attrs)
    for name, spec in ARRAYS.items():
        shape = (int(num_frames), *grid_shape, *spec.extra_shape)
        arr_chunks = (*chunks, *spec.extra_shape)
        shards = None
        if sharded:
            shards = (*_shard_shape(chunks, grid_shape, frames_per_chunk), *spec.extra_shape)
        group.create_array(
            name,
            shape=shape,
            chunks=arr_chunks,
            shards=shards,
            dtype=spec.dtype,
            fill_value=spec.fill_value,
            compressors=ZstdCodec(level=ZSTD_LEVEL),
            dimension_names=(*DIMS, *spec.extra_dims),
            attributes={"description": spec.description},
        )
    return StoreLayout(int(num_frames), grid_shape, frames_per_chunk, tuple(chunks), sharded)


def open_layout(path: str | os.PathLike) -> StoreLayout:
    """The layout of an existing store."""
    group = _open_group(path, "r")
    sem = group["semantics"]
    fpc = int(group.attrs["frames_per_chunk"])
    return StoreLayout(
        int(sem.shape[0]),
        tuple(int(n) for n in sem.shape[1:]),
        fpc,
        tuple(sem.chunks),
        sem.shards is not None,
    )


def _open_group(path: str | os.PathLike, mode: str) -> zarr.Group:
    if not (Path(path) / "zarr.json").is_file():
        raise StoreError(f"no occupancy store at {path} (zarr.json missing)")
    return zarr.open_group(str(path), mode=mode, zarr_format=3)


def write_frames(path: str | os.PathLike, start: int, grids: Mapping[str, np.ndarray]) -> None:
    """Write frames [start, start + n) of some or all arrays.

    grids: name -> array of shape (n, X, Y, Z) (velocity (n, X, Y, Z, 2)) and the array's dtype
    (or one that casts to it safely). The region must start on a write-unit boundary and end on
    one or at the last frame; anything else raises :class:`StoreError` -- two writers sharing a
    chunk or shard would lose frames.
    """
    if not grids:
        return
    group = _open_group(path, "r+")
    fpc = int(group.attrs["frames_per_chunk"])
    skip_empty = bool(group.attrs.get("skip_empty_chunks", False))
    lengths = {name: np.shape(a)[0] if np.ndim(a) else -1 for name, a in grids.items()}
    if len(set(lengths.values())) != 1:
        raise StoreError(f"write_frames({path}): arrays disagree on the frame count: {lengths}")
    n = next(iter(lengths.values()))
    num_frames = group["semantics"].shape[0]
    stop = start + n
    if n < 1 or start < 0 or stop > num_frames:
        raise StoreError(
            f"write_frames({path}): region [{start}, {stop}) outside [0, {num_frames})"
        )
    if start % fpc != 0 or (stop % fpc != 0 and stop != num_frames):
        raise StoreError(
            f"write_frames({path}): region [{start}, {stop}) is not aligned to the write unit of "
            f"{fpc} frames (start and stop must be multiples of {fpc}, or stop = {num_frames})"
        )
    for name, data in grids.items():
        if name not in ARRAYS:
            raise StoreError(
                f"write_frames({path}): unknown array {name!r}, expected one of {list(ARRAYS)}"
            )
        arr = group[name]
        # zarr's all-fill check per chunk: worth it on fine grids only (measured, see SCHEMA.md)
        arr = arr.with_config({"write_empty_chunks": not skip_empty})
        data = np.asarray(data)
        if data.shape != (n, *arr.shape[1:]):
            raise StoreError(
                f"write_frames({path}): {name} frames [{start}, {stop}) have shape {data.shape}, "
                f"expected {(n, *arr.shape[1:])}"
            )
        if data.dtype != arr.dtype:
            both_float = data.dtype.kind == "f" and arr.dtype.kind == "f"
            if not (np.can_cast(data.dtype, arr.dtype, casting="safe") or both_float):
                raise StoreError(
                    f"write_frames({path}): {name} has dtype {data.dtype}, expected {arr.dtype}"
                )
            data = data.astype(arr.dtype)
        arr[start:stop] = data


def read_frames(
    path: str | os.PathLike, sl: slice | int = slice(None), names: tuple[str, ...] | None = None
) -> dict[str, np.ndarray]:
    """Read frames ``sl`` (a slice or one index) of the named arrays (default all) as numpy."""
    group = _open_group(path, "r")
    if isinstance(sl, (int, np.integer)):
        sl = slice(int(sl), int(sl) + 1)
    out = {}
    for name in names or tuple(ARRAYS):
        if name not in ARRAYS:
            raise StoreError(f"read_frames({path}): unknown array {name!r}")
        try:
            out[name] = group[name][sl]
        except (RuntimeError, ValueError, OSError) as exc:  # a codec refusing a damaged chunk
            raise StoreError(
                f"{Path(path) / name} frames {sl.start}-{sl.stop}: cannot be read "
                f"({type(exc).__name__}: {exc}); a published file is damaged: `mobileocc status "
                "--verify` names it, `mobileocc rebuild --verify` publishes the sequence again"
            ) from None
    return out


def read_attrs(path: str | os.PathLike) -> dict[str, Any]:
    """The group attributes of a store."""
    return dict(_open_group(path, "r").attrs)


def store_path(root: str | os.PathLike, sequence: str, version: str | None = None) -> Path:
    """Path of a published store; ``version=None``: the current one (StoreError if none)."""
    seq_dir = Path(root) / OCCUPANCY_DIR / sequence
    if version is None:
        current = seq_dir / CURRENT_FILE
        if not current.is_file():
            raise StoreError(
                f"sequence {sequence!r} has no published occupancy ({current} missing)"
            )
        version = json.loads(current.read_text())["version"]
    return seq_dir / f"{version}.zarr"
