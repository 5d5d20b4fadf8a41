"""What the exports share: deterministic tokens, scene / file names, pose conversions, inputs."""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from storage.atomic import atomic_write_text
from storage.dataset import Dataset

CAM_CHANNEL = "CAM_FRONT"
LIDAR_CHANNEL = "LIDAR_TOP"


def token(kind: str, *parts: object) -> str:
    """A 32-hex-character token, a pure function of (kind, parts): stable across runs."""
    key = "/".join(["mobileocc", kind, *(str(p) for p in parts)])
    return hashlib.sha1(key.encode()).hexdigest()[:32]


def scene_name(prefix: str, sequence: str, log: bool = False) -> str:
    """A sequence's scene: ``<prefix>-<sequence>`` (CODa's sequences are numbers), or a robot
    log's own name (``log``: the sequence is the log's file / folder stem)."""
    return str(sequence) if log else f"{prefix}-{sequence}"


def from_log(frames: list[dict]) -> bool:
    """Whether a sequence's frames (the frames table's rows) come from a robot log: their source
    paths are message references ``LOG#TOPIC@INDEX`` (storage/sources/log/refs.py)."""
    from storage.sources.log.refs import parse_ref

    return bool(frames) and parse_ref(frames[0]["lidar_path"]) is not None


def sample_token(sequence: str, frame: int) -> str:
    return token("sample", sequence, int(frame))


def sample_file_name(scene: str, channel: str, stamp_us: int, ext: str) -> str:
    """nuScenes-style sample file name, e.g. ``samples/CAM_FRONT/coda-0__CAM_FRONT__1675...png``."""
    return f"samples/{channel}/{scene}__{channel}__{stamp_us}{ext}"


def quat_wxyz_from_matrix(R: np.ndarray) -> list[float]:
    """(3, 3) rotation -> quaternion [w, x, y, z] with w >= 0 (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    t = np.trace(R)
    if t > 0:
        s = 2.0 * np.sqrt(1.0 + t)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = [0.0] * 4
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    q = np.asarray(q)
    q = q / np.linalg.norm(q)
    if q[0] < 0:
        q = -q
    return [float(v) for v in q]


def pose_record(T: np.ndarray) -> dict:
    """4x4 pose -> {"translation": [x, y, z], "rotation": [w, x, y, z]}."""
    T = np.asarray(T, dtype=np.float64).reshape(4, 4)
    return {
        "translation": [float(v) for v in T[:3, 3]],
        "rotation": quat_wxyz_from_matrix(T[:3, :3]),
    }


def mat4(values) -> np.ndarray:
    return np.asarray(values, dtype=np.float64).reshape(4, 4)


@dataclass(frozen=True)
class SequenceExportInfo:
    """Per-sequence facts both exports need, read from the dataset tables."""

    sequence: str
    frames: list[dict]  # rows of the frames table, sorted by frame
    K: np.ndarray  # (3, 3)
    T_cam0_from_lidar: np.ndarray
    T_base_from_lidar: np.ndarray
    width: int
    height: int

    @property
    def T_base_from_cam0(self) -> np.ndarray:
        return self.T_base_from_lidar @ np.linalg.inv(self.T_cam0_from_lidar)


def sequence_info(ds: Dataset, sequence: str) -> SequenceExportInfo:
    seqs = ds.table("sequences", sequence).to_pylist()
    if len(seqs) != 1:
        raise ValueError(
            f"dataset {ds.root}: sequences table has {len(seqs)} rows for {sequence!r}, expected 1"
        )
    row = seqs[0]
    for key in ("K", "T_cam0_from_lidar", "T_base_from_lidar", "image_width", "image_height"):
        if row[key] is None:
            raise ValueError(
                f"dataset {ds.root}: sequence {sequence!r} has no {key} in the sequences table"
            )
    frames = ds.table("frames", sequence).to_pylist()
    for a, b in zip(frames, frames[1:]):  # scenes are listed in time order (prev / next, infos)
        if int(b["stamp_ns"]) <= int(a["stamp_ns"]):
            raise ValueError(
                f"dataset {ds.root}: sequence {sequence!r} frame {b['frame']} has stamp_ns "
                f"{b['stamp_ns']}, not after frame {a['frame']}'s {a['stamp_ns']}"
            )
    return SequenceExportInfo(
        sequence=sequence,
        frames=frames,
        K=np.asarray(row["K"], dtype=np.float64).reshape(3, 3),
        T_cam0_from_lidar=mat4(row["T_cam0_from_lidar"]),
        T_base_from_lidar=mat4(row["T_base_from_lidar"]),
        width=int(row["image_width"]),
        height=int(row["image_height"]),
    )


def resolve(
    path: str | None,
    source_root: Path | None,
    what: str,
    sequence: str,
    frame: int,
    built_from: Path | None = None,
) -> Path:
    """A source path from the frames table (relative to the raw data root), made absolute against
    ``source_root``; an absolute path (tables written by other tools) is taken as it is.
    FileNotFoundError names the file, the root used and ``built_from`` (the recorded data root)
    when it differs."""
    if not path:
        raise ValueError(f"sequence {sequence!r} frame {frame}: no {what} path in the frames table")
    p = Path(path)
    if not p.is_absolute() and source_root is not None:
        p = Path(source_root) / p
    if not p.is_file():
        moved = (
            f"; the dataset was built from the raw data root {built_from}"
            if built_from is not None and Path(built_from) != Path(source_root or "")
            else ""
        )
        raise FileNotFoundError(
            f"sequence {sequence!r} frame {frame}: {what} file {p} does not exist "
            f"(frames table path {path!r}, source root {source_root}{moved})"
        )
    return p


def link_or_copy(src: Path, dst: Path) -> None:
    """Hard-link ``src`` at ``dst`` (copy when linking fails, e.g. across filesystems)."""
    import shutil

    dst.parent.mkdir(parents=True, exist_ok=True)
    if dst.exists():
        dst.unlink()
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def recorded_source_root(dataset_root: str | os.PathLike) -> Path | None:
    """The raw data root the dataset was built from (OUT/manifest.json, storage.manifest), or
    None (no manifest, or none recorded)."""
    from storage.manifest import OutputError, recorded_data_root

    try:
        return recorded_data_root(Path(dataset_root))
    except (OSError, OutputError):
        return None


#: FlashOcc / BEVDet's nuScenes detection classes (their configs' ``class_names``): the label
#: index of a box in the training infos' ``ann_infos`` is its position here
DETECTION_CLASSES = (
    "car",
    "truck",
    "construction_vehicle",
    "bus",
    "trailer",
    "barrier",
    "motorcycle",
    "bicycle",
    "pedestrian",
    "traffic_cone",
)


def grid_metadata(ds: Dataset, sequences: list[str]) -> dict:
    """What a trainer needs to know about the label grids, from the stores' attributes: frame,
    range, voxel size, shape, class names, free id; and the matching FlashOcc settings.

    All ``sequences`` must share one grid and class table (ValueError naming the two that differ).
    """
    if not sequences:
        raise ValueError(f"dataset {ds.root}: no sequences to export")
    first = None
    for seq in sequences:
        a = ds.attrs(seq)
        shape = [int(n) for n in ds.arrays(seq, lazy="zarr")["semantics"].shape[1:4]]
        grid = {
            "range_min": [float(v) for v in a["range_min"]],
            "range_max": [float(v) for v in a["range_max"]],
            "voxel_size_m": float(a["voxel_size_m"]),
            "shape": shape,
            "class_names": list(a["class_names"]),
            "free_class": int(a["free_class"]),
        }
        if first is None:
            first = (seq, grid)
        elif grid != first[1]:
            raise ValueError(
                f"dataset {ds.root}: sequences {first[0]!r} and {seq!r} have different grids or "
                f"class tables ({first[1]} vs {grid}); export them separately"
            )
    g = first[1]
    lo, hi, vs = g["range_min"], g["range_max"], g["voxel_size_m"]
    return {
        "grid": {
            "frame": "base (the robot base on the ground, = the nuScenes ego frame)",
            "axis_order": ["x", "y", "z"],
            "range_min": lo,
            "range_max": hi,
            "voxel_size_m": vs,
            "shape": g["shape"],
            "index": "floor((p - range_min) / voxel_size_m)",
        },
        "class_names": g["class_names"],
        "num_classes": len(g["class_names"]),
        "free_class": g["free_class"],
        # Occ3D's own names: its "others" is our "unclassified" (occupied, class unknown)
        "occ3d_class_names": ["others" if n == "unclassified" else n for n in g["class_names"]],
        "unknown": "not a class: voxels with mask_camera == 0 (camera view) or mask_lidar == 0 (LiDAR) "
        "are unknown to that sensor; semantics holds the free id where mask_lidar == 0 (every "
        "occupied voxel is in mask_lidar) and keeps the class of occupied voxels hidden from the "
        "camera (mask_camera == 0)",
        "flashocc": flashocc_settings(ds, sequences, g),
    }


#: FlashOcc's LSS feature stride (``downsample``) and the input heights whose frustum coverage the
#: metadata lists (widths: the source aspect, rounded to multiples of the stride)
FLASHOCC_DOWNSAMPLE = 16
FLASHOCC_INPUT_HEIGHTS = (256, 384, 512, 768)
#: LSS depth bins: from FLASHOCC_DEPTH_MIN_M in FLASHOCC_DEPTH_STEP_M steps past the grid's far
#: corner (seen from the camera)
FLASHOCC_DEPTH_MIN_M = 0.5
FLASHOCC_DEPTH_STEP_M = 0.25


def flashocc_settings(ds: Dataset, sequences: list[str], grid: dict) -> dict:
    """FlashOcc config values for ``grid`` (:func:`grid_metadata`'s): grid_config with a depth
    range covering the grid, Dz, num_classes, the BEV augmentation flips that keep the grid onto
    itself (a flip about an axis the grid is not symmetric about moves every frustum point out),
    and per input size the share of camera-visible BEV cells the frustum reaches (the smallest
    over the sequences' cameras; tasks/occupancy/lss_frustum.py)."""
    from tasks.occupancy.lss_frustum import frustum_coverage

    lo, hi, vs, shape = grid["range_min"], grid["range_max"], grid["voxel_size_m"], grid["shape"]
    cams = {}
    for seq in sequences:
        info = sequence_info(ds, seq)
        key = (info.K.tobytes(), info.T_base_from_cam0.tobytes(), info.width, info.height)
        cams.setdefault(key, info)
    corners = np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )
    far = max(
        float(np.linalg.norm(corners - i.T_base_from_cam0[:3, 3], axis=1).max())
        for i in cams.values()
    )
    depth = [FLASHOCC_DEPTH_MIN_M, float(np.ceil(far)) + 0.5, FLASHOCC_DEPTH_STEP_M]
    first = next(iter(cams.values()))
    sizes = []
    for h in FLASHOCC_INPUT_HEIGHTS:
        w = int(round(h * first.width / first.height / FLASHOCC_DOWNSAMPLE)) * FLASHOCC_DOWNSAMPLE
        cover = min(
            frustum_coverage(
                i.K,
                i.T_base_from_cam0,
                (i.width, i.height),
                (h, w),
                tuple(depth),
                tuple(shape),
                lo,
                hi,
                vs,
                FLASHOCC_DOWNSAMPLE,
            )
            for i in cams.values()
        )
        sizes.append({"input_size": [h, w], "frustum_coverage": round(cover, 4)})
    symmetric = [abs(lo[a] + hi[a]) < 1e-9 for a in (0, 1)]
    return {
        "grid_config": {
            "x": [lo[0], hi[0], vs],
            "y": [lo[1], hi[1], vs],
            "z": [lo[2], hi[2], hi[2] - lo[2]],
            "depth": depth,
        },
        "Dz": shape[2],
        "num_classes": len(grid["class_names"]),
        "free_index": grid["free_class"],
        "cams": [CAM_CHANNEL],
        "detection_classes": list(DETECTION_CLASSES),
        "bda_aug_conf": {
            "rot_lim": [0.0, 0.0],
            "scale_lim": [1.0, 1.0],
            "flip_dx_ratio": 0.5 if symmetric[0] else 0.0,
            "flip_dy_ratio": 0.5 if symmetric[1] else 0.0,
        },
        "src_size": [first.height, first.width],
        "downsample": FLASHOCC_DOWNSAMPLE,
        "input_sizes": sizes,
    }


def write_json(path: Path, obj) -> None:
    """Write JSON (sorted keys, NaN refused) atomically (:mod:`storage.atomic`)."""
    import json

    atomic_write_text(path, json.dumps(obj, indent=1, sort_keys=True, allow_nan=False))
