"""Reader for the CODa raw layout (UT Campus Object Dataset), real or synthetic.

Layout (see ../shared/reference/coda-and-formats.md)::

    {root}/{modality}/{sensor}/{SEQ}/{modality}_{sensor}_{SEQ}_{FRAME}.{ext}
    {root}/calibrations/{SEQ}/calib_*.yaml
    {root}/poses/dense_global/{SEQ}.txt   (fallback: poses/dense/{SEQ}.txt)
    {root}/timestamps/{SEQ}.txt           {root}/metadata/{SEQ}.json

Every error names the file, the frame where there is one, the value and what was expected; the
errors are :class:`CodaFormatError` (a ValueError) so a flow can fail one sequence and go on.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from storage.model import Box3D, Calibration, CameraCalibration, Frame, SequenceInfo

#: points per organised OS1-128 sweep (128 beams x 1024 columns), no-returns included
POINTS_PER_SWEEP = 128 * 1024
COLUMNS_PER_BEAM = 1024
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")
OCCLUSION_LEVELS = ("None", "Light", "Medium", "Heavy", "Full", "Unknown")


class CodaFormatError(ValueError):
    """Bad or missing input in a CODa-layout dataset."""


@dataclass(frozen=True)
class LidarSweep:
    """One decoded sweep, no-return points removed.

    points: (N, 3) float32 LiDAR frame, metres. intensity: (N,) float32. time_s: (N,) float32
    per-point time offset or None (4-channel files). ring: (N,) uint8 beam index (0 = top row of the
    organised scan). index: (N,) int64 position in the organised 131,072-point scan (to align
    per-point label files).
    """

    points: np.ndarray
    intensity: np.ndarray
    time_s: np.ndarray | None
    ring: np.ndarray
    index: np.ndarray


def read_lidar_bin(path: Path, min_range_m: float = 0.0, max_range_m: float = math.inf,
                   frame: int | None = None) -> LidarSweep:
    """Decode an organised OS1-128 ``.bin`` (float32 LE, 4 or 5 channels inferred from size)."""
    path = Path(path)
    where = f"{path}" + (f" (frame {frame})" if frame is not None else "")
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise CodaFormatError(f"{where}: LiDAR file is missing") from None
    per_channel = POINTS_PER_SWEEP * 4
    if size == 0 or size % per_channel:
        raise CodaFormatError(
            f"{where}: {size} bytes is not a whole organised 128x1024 sweep "
            f"(expected 4 or 5 float32 channels = {4 * per_channel} or {5 * per_channel} bytes); "
            "the file is truncated or not an OS1-128 sweep"
        )
    channels = size // per_channel
    if channels not in (4, 5):
        raise CodaFormatError(
            f"{where}: {channels} channels inferred from {size} bytes; expected 4 (x y z intensity) "
            "or 5 (x y z intensity time)"
        )
    raw = np.fromfile(path, dtype="<f4").reshape(POINTS_PER_SWEEP, channels)
    bad = ~np.isfinite(raw).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise CodaFormatError(
            f"{where}: {int(bad.sum())} points have NaN or inf values (first at point {first}: "
            f"{raw[first].tolist()}); expected finite floats (no-returns are zeros)"
        )
    rng = np.linalg.norm(raw[:, :3], axis=1)
    keep = (rng > max(min_range_m, 1e-6)) & (rng <= max_range_m)
    index = np.flatnonzero(keep)
    return LidarSweep(
        points=np.ascontiguousarray(raw[index, :3]),
        intensity=np.ascontiguousarray(raw[index, 3]),
        time_s=np.ascontiguousarray(raw[index, 4]) if channels == 5 else None,
        ring=(index // COLUMNS_PER_BEAM).astype(np.uint8),
        index=index.astype(np.int64),
    )


def quat_wxyz_to_matrix(q: np.ndarray) -> np.ndarray:
    """(4,) quaternion (w, x, y, z) -> (3, 3) rotation matrix, float64 (normalises q)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def box_rotation(rpy: np.ndarray) -> np.ndarray:
    """CODa box angles (roll, pitch, yaw) -> (3, 3) rotation Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


def points_in_box(points: np.ndarray, box: Box3D, margin_m: float = 0.0) -> np.ndarray:
    """(N,) bool: points (N, 3) inside the rotated box (the devkit's own test ignores yaw)."""
    local = (points.astype(np.float64) - box.center) @ box_rotation(box.rpy)
    half = box.size / 2.0 + margin_m
    return np.all(np.abs(local) <= half, axis=1)


class CodaSequence:
    """One sequence of a CODa-layout root. Cheap to build; frames are read on demand.

    ``frame_stride`` keeps every k-th raw frame (2 for 5 Hz). ``lidar_source`` is ``3d_raw`` or
    ``3d_comp``; ``image_source`` ``2d_rect`` or ``2d_raw``.
    """

    def __init__(self, root: Path, sequence: str | int, *, frame_stride: int = 2,
                 lidar_source: str = "3d_raw", image_source: str = "2d_rect",
                 min_range_m: float = 0.5, max_range_m: float = math.inf,
                 cameras: tuple[str, ...] = ("cam0", "cam1")):
        self.root = Path(root)
        self.sequence = str(sequence)
        if lidar_source not in ("3d_raw", "3d_comp"):
            raise CodaFormatError(f"lidar_source {lidar_source!r}: expected 3d_raw or 3d_comp")
        if image_source not in ("2d_rect", "2d_raw"):
            raise CodaFormatError(f"image_source {image_source!r}: expected 2d_rect or 2d_raw")
        if frame_stride < 1:
            raise CodaFormatError(f"frame_stride {frame_stride}: expected >= 1")
        self.frame_stride = frame_stride
        self.lidar_source = lidar_source
        self.image_source = image_source
        self.min_range_m = min_range_m
        self.max_range_m = max_range_m
        self.cameras = cameras
        if self.sequence not in list_sequences(self.root):
            raise CodaFormatError(
                f"unknown sequence id {self.sequence!r} in {self.root}: no "
                f"timestamps/{self.sequence}.txt (available: {list_sequences(self.root) or 'none'})"
            )
        self.info = self._read_info()

    # -- paths ------------------------------------------------------------------------------
    def path(self, modality: str, sensor: str, frame: int, ext: str) -> Path:
        seq = self.sequence
        return self.root / modality / sensor / seq / f"{modality}_{sensor}_{seq}_{frame}{ext}"

    def image_path(self, camera: str, frame: int) -> Path:
        """The image of ``camera`` at raw frame ``frame`` (.png or .jpg; rectified falls back to raw)."""
        sources = [self.image_source] + [s for s in ("2d_rect", "2d_raw") if s != self.image_source]
        for source in sources:
            for ext in IMAGE_EXTENSIONS:
                candidate = self.path(source, camera, frame, ext)
                if candidate.exists():
                    return candidate
        raise CodaFormatError(
            f"{self.path(self.image_source, camera, frame, '.png')} (frame {frame}): image is "
            f"missing (looked for {', '.join(IMAGE_EXTENSIONS)} in {', '.join(sources)})"
        )

    # -- sequence level ---------------------------------------------------------------------
    def _read_info(self) -> SequenceInfo:
        stamps_path = self.root / "timestamps" / f"{self.sequence}.txt"
        stamps_s = _read_timestamps(stamps_path)
        pose_path = self.root / "poses" / "dense_global" / f"{self.sequence}.txt"
        if not pose_path.exists():  # sequences 8, 14, 15 of CODa have no dense_global poses
            pose_path = self.root / "poses" / "dense" / f"{self.sequence}.txt"
        poses = _read_poses(pose_path, expected=len(stamps_s), stamps_path=stamps_path)
        calibration = self._read_calibration()
        frames = tuple(range(0, len(stamps_s), self.frame_stride))
        metadata_path = self.root / "metadata" / f"{self.sequence}.json"
        metadata = _read_json(metadata_path) if metadata_path.exists() else {}
        idx = np.asarray(frames, dtype=np.int64)
        return SequenceInfo(
            sequence=self.sequence,
            root=self.root,
            frame_indices=frames,
            stamps_ns=np.round(stamps_s[idx] * 1e9).astype(np.int64),
            poses=poses[idx],
            calibration=calibration,
            metadata=metadata,
            files=tuple(self._input_files(frames, pose_path, stamps_path, metadata_path)),
        )

    def _read_calibration(self) -> Calibration:
        folder = self.root / "calibrations" / self.sequence
        cameras = {}
        for cam in self.cameras:
            intr_path = folder / f"calib_{cam}_intrinsics.yaml"
            ext_path = folder / f"calib_os1_to_{cam}.yaml"
            if cam != "cam0" and not intr_path.exists() and not ext_path.exists():
                continue  # only cam0 is required
            intr = _read_yaml(intr_path)
            K = _yaml_matrix(intr, "camera_matrix", (3, 3), intr_path)
            dist = _yaml_matrix(intr, "distortion_coefficients", None, intr_path).reshape(-1)
            width = _yaml_key(intr, "image_width", intr_path)
            height = _yaml_key(intr, "image_height", intr_path)
            T = _yaml_matrix(_read_yaml(ext_path), "extrinsic_matrix", (4, 4), ext_path)
            cameras[cam] = CameraCalibration(cam, K, dist, int(width), int(height), T)
        base_path = folder / "calib_os1_to_base.yaml"
        T_base = _yaml_matrix(_read_yaml(base_path), "extrinsic_matrix", (4, 4), base_path)
        return Calibration(cameras=cameras, T_base_from_lidar=T_base)

    def _input_files(self, frames, *extra: Path) -> list[Path]:
        """Every file the selected frames read, for the content fingerprint."""
        files = [p for p in extra if p.exists()]
        files += sorted((self.root / "calibrations" / self.sequence).glob("*.yaml"))
        wanted = set(frames)
        patterns = [(self.lidar_source, "os1"), ("3d_bbox", "os1"), ("3d_semantic", "os1")]
        patterns += [(src, cam) for src in ("2d_rect", "2d_raw") for cam in self.cameras]
        for modality, sensor in patterns:
            folder = self.root / modality / sensor / self.sequence
            if not folder.is_dir():
                continue
            for p in sorted(folder.iterdir()):
                stem = p.stem.rsplit("_", 1)[-1]
                if stem.isdigit() and int(stem) in wanted:
                    files.append(p)
        gt = self.root / "gt" / self.sequence
        if gt.is_dir():
            files += sorted(p for p in gt.rglob("*") if p.is_file())
        return files

    # -- frame level ------------------------------------------------------------------------
    def __len__(self) -> int:
        return self.info.num_frames

    def frame(self, i: int) -> Frame:
        """The i-th selected frame (i indexes ``info.frame_indices``)."""
        if not 0 <= i < len(self):
            raise IndexError(f"sequence {self.sequence}: frame position {i} not in 0..{len(self) - 1}")
        raw = self.info.frame_indices[i]
        lidar_path = self.path(self.lidar_source, "os1", raw, ".bin")
        sweep = read_lidar_bin(lidar_path, self.min_range_m, self.max_range_m, frame=raw)
        semantic = None
        sem_path = self.path("3d_semantic", "os1", raw, ".bin")
        if sem_path.exists():
            labels = np.fromfile(sem_path, dtype=np.uint8)
            if labels.size != POINTS_PER_SWEEP:
                raise CodaFormatError(
                    f"{sem_path} (frame {raw}): {labels.size} labels, expected {POINTS_PER_SWEEP}"
                )
            semantic = labels[sweep.index]
        box_path = self.path("3d_bbox", "os1", raw, ".json")
        boxes = read_boxes(box_path, frame=raw) if box_path.exists() else ()
        images = {cam: self.image_path(cam, raw) for cam in self.info.calibration.cameras}
        return Frame(
            sequence=self.sequence,
            index=raw,
            stamp_ns=int(self.info.stamps_ns[i]),
            points_lidar=sweep.points,
            intensity=sweep.intensity,
            T_world_from_lidar=self.info.poses[i],
            image_paths=images,
            lidar_path=lidar_path,
            point_time_s=sweep.time_s,
            semantic_labels=semantic,
            boxes=boxes,
        )

    def frames(self):
        for i in range(len(self)):
            yield self.frame(i)


def list_sequences(root: Path) -> list[str]:
    """Sequence ids of a CODa-layout root (those with a timestamps file), numerically sorted."""
    folder = Path(root) / "timestamps"
    if not folder.is_dir():
        return []
    ids = [p.stem for p in folder.glob("*.txt")]
    return sorted(ids, key=lambda s: (not s.isdigit(), int(s) if s.isdigit() else 0, s))


def read_boxes(path: Path, frame: int | None = None) -> tuple[Box3D, ...]:
    """Parse a CODa ``3d_bbox`` JSON file into boxes in the os1 frame."""
    where = f"{path}" + (f" (frame {frame})" if frame is not None else "")
    data = _read_json(path, where)
    if not isinstance(data, dict) or not isinstance(data.get("3dbbox"), list):
        raise CodaFormatError(f"{where}: expected an object with a '3dbbox' list")
    boxes = []
    for k, entry in enumerate(data["3dbbox"]):
        try:
            values = [float(entry[key]) for key in ("cX", "cY", "cZ", "l", "w", "h", "r", "p", "y")]
            class_name = str(entry["classId"])
            instance_id = str(entry.get("instanceId", f"{class_name}:{k}"))
        except (KeyError, TypeError, ValueError) as exc:
            raise CodaFormatError(f"{where}: box {k} is malformed ({exc!r}); expected classId, "
                                  "cX cY cZ l w h r p y") from None
        if not all(math.isfinite(v) for v in values) or min(values[3:6]) <= 0:
            raise CodaFormatError(f"{where}: box {k} ({instance_id}) has non-finite values or a "
                                  f"non-positive size: {values}")
        occlusion = str((entry.get("labelAttributes") or {}).get("isOccluded", "Unknown"))
        boxes.append(Box3D(instance_id, class_name, np.array(values[0:3]), np.array(values[3:6]),
                           np.array(values[6:9]), occlusion))
    return tuple(boxes)


# -- small parsers ----------------------------------------------------------------------------
def _read_timestamps(path: Path) -> np.ndarray:
    try:
        lines = path.read_text().split()
    except FileNotFoundError:
        raise CodaFormatError(f"{path}: timestamps file is missing") from None
    try:
        stamps = np.array([float(x) for x in lines], dtype=np.float64)
    except ValueError as exc:
        raise CodaFormatError(f"{path}: not a list of Unix seconds ({exc})") from None
    if stamps.size == 0:
        raise CodaFormatError(f"{path}: no timestamps")
    if not np.isfinite(stamps).all():
        raise CodaFormatError(f"{path}: non-finite timestamp at line {int(np.argmin(np.isfinite(stamps))) + 1}")
    steps = np.diff(stamps)
    if (steps <= 0).any():
        k = int(np.flatnonzero(steps <= 0)[0])
        raise CodaFormatError(
            f"{path}: timestamps are not strictly increasing: line {k + 2} ({stamps[k + 1]:.6f}) "
            f"after line {k + 1} ({stamps[k]:.6f}) (frame {k + 1})"
        )
    return stamps


def _read_poses(path: Path, expected: int, stamps_path: Path) -> np.ndarray:
    """Pose lines ``ts x y z qw qx qy qz`` -> (F, 4, 4) float64 T_world_from_lidar."""
    try:
        rows = [line.split() for line in path.read_text().splitlines() if line.strip()]
    except FileNotFoundError:
        raise CodaFormatError(
            f"{path}: poses file is missing (looked in poses/dense_global and poses/dense)"
        ) from None
    if len(rows) != expected:
        raise CodaFormatError(
            f"{path}: {len(rows)} pose lines but {stamps_path} has {expected} frames; expected one "
            "pose line per os1 frame"
        )
    poses = np.tile(np.eye(4), (expected, 1, 1))
    for k, row in enumerate(rows):
        try:
            values = np.array([float(x) for x in row], dtype=np.float64)
        except ValueError:
            raise CodaFormatError(f"{path}: line {k + 1} (frame {k}) is not numeric: {row}") from None
        if values.size != 8 or not np.isfinite(values).all():
            raise CodaFormatError(
                f"{path}: line {k + 1} (frame {k}) has {values.size} values {row}; expected 8 finite "
                "values 'ts x y z qw qx qy qz'"
            )
        if abs(np.linalg.norm(values[4:8]) - 1.0) > 1e-3:
            raise CodaFormatError(
                f"{path}: line {k + 1} (frame {k}): quaternion norm {np.linalg.norm(values[4:8]):.4f}, "
                "expected a unit quaternion (w x y z)"
            )
        poses[k, :3, :3] = quat_wxyz_to_matrix(values[4:8])
        poses[k, :3, 3] = values[1:4]
    return poses


def _read_yaml(path: Path) -> dict:
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise CodaFormatError(f"{path}: calibration file is missing") from None
    except yaml.YAMLError as exc:
        raise CodaFormatError(f"{path}: invalid YAML ({exc})") from None
    if not isinstance(data, dict):
        raise CodaFormatError(f"{path}: expected a YAML mapping")
    return data


def _yaml_key(data: dict, key: str, path: Path):
    if key not in data:
        raise CodaFormatError(f"{path}: calibration key {key!r} is missing")
    return data[key]


def _yaml_matrix(data: dict, key: str, shape: tuple[int, int] | None, path: Path) -> np.ndarray:
    node = _yaml_key(data, key, path)
    values = node.get("data") if isinstance(node, dict) else node
    try:
        arr = np.asarray(values, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise CodaFormatError(f"{path}: {key} is not a list of numbers") from None
    if shape is not None:
        if arr.size != shape[0] * shape[1]:
            raise CodaFormatError(
                f"{path}: {key} has {arr.size} values, expected {shape[0]}x{shape[1]}"
            )
        arr = arr.reshape(shape)
    if not np.isfinite(arr).all():
        raise CodaFormatError(f"{path}: {key} has non-finite values")
    return arr


def _read_json(path: Path, where: str | None = None):
    try:
        return json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise CodaFormatError(f"{where or path}: file is missing") from None
    except json.JSONDecodeError as exc:
        raise CodaFormatError(f"{where or path}: invalid JSON ({exc})") from None
