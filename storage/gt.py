"""Ground truth of synthetic sequences: ``ROOT/gt/{SEQ}/`` (schema in storage/GT_FORMAT.md).

- ``gt/{SEQ}/sequence.npz``: what every frame shares (grid spec, body-model faces).
- ``gt/{SEQ}/gt_{SEQ}_{FRAME}.npz``: one frame (occupancy, per-point labels, people, cam0 labels).

npz files are written through a deterministic zip writer (fixed entry dates, sorted names,
deflate), so the same inputs give byte-identical files; ``np.load`` reads them.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from storage.files import InputError, open_regular
from storage.npzio import load_npz, save_npz_deterministic
from tasks.conventions import FREE, UNCLASSIFIED

#: Fields of a frame file: name -> (dtype, shape with -1 for free dims, documented in GT_FORMAT.md).
FRAME_FIELDS: dict[str, tuple[str, tuple[int, ...]]] = {
    "occupancy": ("uint8", (-1, -1, -1)),
    "occupancy_instance": ("uint16", (-1, -1, -1)),
    "point_class": ("uint8", (131072,)),
    "point_instance": ("uint16", (131072,)),
    "T_world_from_lidar": ("float64", (4, 4)),
    "T_world_from_base": ("float64", (4, 4)),
    "stamp_ns": ("int64", ()),
    "cam0_semantic": ("uint8", (-1, -1)),
    "cam0_instance": ("uint16", (-1, -1)),
    "track_id": ("int32", (-1,)),
    "betas": ("float32", (-1, 10)),
    "global_orient": ("float32", (-1, 3)),
    "body_pose": ("float32", (-1, 69)),
    "transl": ("float32", (-1, 3)),
    "vertices": ("float32", (-1, -1, 3)),
    "joints": ("float32", (-1, 24, 3)),
    "velocity_base": ("float32", (-1, 2)),
    "box2d": ("float32", (-1, 4)),
    "keypoints": ("float32", (-1, 17, 3)),
    "visible_fraction": ("float32", (-1,)),
    "box_center": ("float32", (-1, 3)),
    "box_size": ("float32", (-1, 3)),
    "box_yaw": ("float32", (-1,)),
}
#: Frame fields that ground truth written before they existed lacks (read as None there).
OPTIONAL_FRAME_FIELDS: dict[str, tuple[str, tuple[int, ...]]] = {
    "vertex_velocity_base": ("float32", (-1, -1, 3)),
}
SEQUENCE_FIELDS: dict[str, tuple[str, tuple[int, ...]]] = {
    "grid_range_min": ("float64", (3,)),
    "grid_voxel_size_m": ("float64", ()),
    "grid_shape": ("int64", (3,)),
    "person_faces": ("int64", (-1, 3)),
    "keypoint_vertex_ids": ("int64", (5,)),
    "T_base_from_lidar": ("float64", (4, 4)),
}


class GTFormatError(InputError):
    """A ground-truth file that is not a readable npz, or has a missing field or a wrong dtype /
    shape (``path``, and ``frame`` for a frame's file)."""


class GTMissingError(GTFormatError, FileNotFoundError):
    """A ground-truth file that is not there."""


def _load(path: Path, frame: int | None) -> dict[str, np.ndarray]:
    """Every array of a ground-truth npz (regular files only, no pickles); GTFormatError naming
    the file when it is not a readable npz."""
    try:
        with open_regular(path, frame, "ground-truth file") as fh:
            return load_npz(fh)  # each member's size checked before it is read
    except InputError as exc:
        raise GTFormatError(str(exc), path, frame) from None
    except (zipfile.BadZipFile, ValueError, OSError, EOFError, KeyError) as exc:
        where = f"{path}" + (f" (frame {frame})" if frame is not None else "")
        raise GTFormatError(
            f"{where}: not a readable ground-truth npz ({type(exc).__name__}: {exc})", path, frame
        ) from None


def write_npz_deterministic(path: Path, arrays: dict[str, np.ndarray]) -> Path:
    """np.savez_compressed-compatible file whose bytes depend only on ``arrays`` (entries sorted
    by name; see :mod:`storage.npzio`)."""
    return save_npz_deterministic(
        path, compressed=True, **{k: np.asarray(arrays[k]) for k in sorted(arrays)}
    )


def _check(
    path: Path, arrays: dict, spec: dict, optional: dict | None = None, frame: int | None = None
) -> None:
    for name, (dtype, shape) in {**spec, **(optional or {})}.items():
        if name not in arrays:
            if name in spec:
                raise GTFormatError(f"{path}: missing field {name!r}", path, frame)
            continue
        a = np.asarray(arrays[name])
        ok = (
            a.dtype == np.dtype(dtype)
            and a.ndim == len(shape)
            and all(s == -1 or s == d for s, d in zip(shape, a.shape))
        )
        if not ok:
            raise GTFormatError(
                f"{path}: field {name!r} is {a.dtype} {a.shape}, expected {dtype} {shape}",
                path,
                frame,
            )


def gt_dir(root: Path, seq: int | str) -> Path:
    return Path(root) / "gt" / str(seq)


def frame_path(root: Path, seq: int | str, frame: int) -> Path:
    return gt_dir(root, seq) / f"gt_{seq}_{frame}.npz"


def write_sequence_gt(root: Path, seq: int | str, arrays: dict[str, np.ndarray]) -> Path:
    """Write ``sequence.npz`` (fields SEQUENCE_FIELDS)."""
    path = gt_dir(root, seq) / "sequence.npz"
    _check(path, arrays, SEQUENCE_FIELDS)
    return write_npz_deterministic(path, {k: np.asarray(arrays[k]) for k in SEQUENCE_FIELDS})


def write_frame_gt(root: Path, seq: int | str, frame: int, arrays: dict[str, np.ndarray]) -> Path:
    """Write one frame's ground truth (fields FRAME_FIELDS and those of OPTIONAL_FRAME_FIELDS
    given, validated)."""
    path = frame_path(root, seq, frame)
    _check(path, arrays, FRAME_FIELDS, OPTIONAL_FRAME_FIELDS)
    names = [*FRAME_FIELDS, *(k for k in OPTIONAL_FRAME_FIELDS if arrays.get(k) is not None)]
    return write_npz_deterministic(path, {k: np.asarray(arrays[k]) for k in names})


@dataclass(frozen=True)
class GTSequence:
    """grid_range_min (3,) m base frame; grid_voxel_size_m; grid_shape (3,) [x, y, z];
    person_faces (F, 3) int64; keypoint_vertex_ids (5,) COCO face vertex ids;
    T_base_from_lidar (4, 4); frames: the frame numbers present, ascending."""

    grid_range_min: np.ndarray
    grid_voxel_size_m: float
    grid_shape: tuple[int, int, int]
    person_faces: np.ndarray
    keypoint_vertex_ids: np.ndarray
    T_base_from_lidar: np.ndarray
    frames: tuple[int, ...]


@dataclass(frozen=True)
class GTFrame:
    """One frame's ground truth; every field as documented in storage/GT_FORMAT.md."""

    occupancy: np.ndarray
    occupancy_instance: np.ndarray
    point_class: np.ndarray
    point_instance: np.ndarray
    T_world_from_lidar: np.ndarray
    T_world_from_base: np.ndarray
    stamp_ns: int
    cam0_semantic: np.ndarray
    cam0_instance: np.ndarray
    track_id: np.ndarray
    betas: np.ndarray
    global_orient: np.ndarray
    body_pose: np.ndarray
    transl: np.ndarray
    vertices: np.ndarray
    joints: np.ndarray
    velocity_base: np.ndarray
    box2d: np.ndarray
    keypoints: np.ndarray
    visible_fraction: np.ndarray
    box_center: np.ndarray
    box_size: np.ndarray
    box_yaw: np.ndarray
    #: (K, V, 3) per-vertex world velocity in base axes, m/s; None in ground truth written before it
    vertex_velocity_base: np.ndarray | None = None


def list_gt_frames(root: Path, seq: int | str) -> list[int]:
    """Frame numbers with a ground-truth file, ascending."""
    d = gt_dir(root, seq)
    prefix = f"gt_{seq}_"
    out = []
    for p in d.glob(f"{prefix}*.npz"):
        tail = p.stem[len(prefix) :]
        if tail.isdigit():
            out.append(int(tail))
    return sorted(out)


def read_sequence_gt(root: Path, seq: int | str) -> GTSequence:
    """Read ``gt/{SEQ}/sequence.npz``; raises GTFormatError (GTMissingError, also a
    FileNotFoundError, when it is not there) naming the file."""
    path = gt_dir(root, seq) / "sequence.npz"
    if not path.exists():
        raise GTMissingError(f"{path}: no ground truth for sequence {seq}", path)
    a = _load(path, None)
    _check(path, a, SEQUENCE_FIELDS)
    return GTSequence(
        a["grid_range_min"],
        float(a["grid_voxel_size_m"]),
        tuple(int(v) for v in a["grid_shape"]),
        a["person_faces"],
        a["keypoint_vertex_ids"],
        a["T_base_from_lidar"],
        tuple(list_gt_frames(root, seq)),
    )


def read_frame_gt(root: Path, seq: int | str, frame: int) -> GTFrame:
    """Read one frame's ground truth as arrays."""
    path = frame_path(root, seq, frame)
    if not path.exists():
        raise GTMissingError(
            f"{path} (frame {frame}): no ground truth for sequence {seq} frame {frame}", path, frame
        )
    a = _load(path, frame)
    _check(path, a, FRAME_FIELDS, OPTIONAL_FRAME_FIELDS, frame)
    kw = {f.name: a.get(f.name) for f in fields(GTFrame)}
    kw["stamp_ns"] = int(kw["stamp_ns"])
    if np.any(np.asarray(kw["occupancy"]) == UNCLASSIFIED):  # the truth always knows the class
        raise GTFormatError(
            f"{path} (frame {frame}): occupancy holds class {UNCLASSIFIED}: simulated before class "
            f"{UNCLASSIFIED} became 'unclassified' (free was {UNCLASSIFIED}, now {FREE}); "
            "simulate again",
            path,
            frame,
        )
    return GTFrame(**kw)
