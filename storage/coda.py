"""Reader for the CODa raw layout (UT Campus Object Dataset), real or synthetic.

Layout (ut-amrl/coda-devkit, docs/DATA_REPORT.md)::

    {root}/{modality}/{sensor}/{SEQ}/{modality}_{sensor}_{SEQ}_{FRAME}.{ext}
    {root}/calibrations/{SEQ}/calib_*.yaml
    {root}/poses/dense_global/{SEQ}.txt   (fallback: poses/dense/{SEQ}.txt)
    {root}/timestamps/{SEQ}.txt           {root}/metadata/{SEQ}.json

Frames. A raw frame number is a line of the timestamps file (and of the dense poses file, one
pose per os1 frame). The per-sequence downloads hold a sweep for every line; the split downloads
(tiny / small / medium / full) hold only the annotated frames. So the frames of a sequence are the
ones whose LiDAR file exists (``frames="files"``) or the ones the metadata's ObjectTracking /
SemanticSegmentation lists name (``frames="metadata"``), matched to timestamps and poses by number;
of those, a frame is kept when it lies at least ``frame_stride`` raw frames after the last kept one
(every 2nd frame of a full sequence, 5 Hz; gaps of a split are taken as they come).

LiDAR ``.bin``: float32, 128 x 1024 organised points, 4 channels (x y z intensity) or 5 (x y z
intensity t, t = nanoseconds since the sweep's first column as the devkit's decoder writes it);
``3d_comp`` sweeps of the devkit hold x y z only (intensity and t are zeros).

Cameras. ``2d_rect`` images are made by the devkit with ``cv2.initUndistortRectifyMap(K, D, R, P)``,
whose map uses ``P[:, :3] @ R`` (the 4th column of P is not read), so a LiDAR point x lands on the
rectified pixel ``P[:, :3] @ R @ T_cam_from_lidar @ x``. Each camera is therefore exposed as the
pinhole (``K = P[:, :3]``, ``T_cam_from_lidar = [[R, 0], [0, 1]] @ T_cam_from_lidar``) of its
rectified frame (storage.sequence_data.CameraCalibration); the files' values stay on ``.raw``.

Every error names the file, the frame where there is one, the value and what was expected. All are
:class:`CodaFormatError` (a :class:`storage.files.InputError`, a ValueError); those of one frame's
files are :class:`CodaFrameError`, which carries the path and the frame, so a caller can fail that
frame and go on. A malformed or degenerate box does not fail its frame: it is skipped and reported
in ``Frame.box_problems``. Only regular files are read (storage/files.py): a FIFO, device,
directory or symlink loop in place of a data file is a named error, never a hang.

What is checked when a sequence is opened (once, at the edge): timestamps (numbers, strictly
increasing), poses (one finite line per frame, unit quaternions, the pose times within
``POSE_TIME_TOLERANCE_S`` of the timestamps, translations within ``MAX_POSITION_M`` and speeds
between raw frames below ``MAX_SPEED_MPS``), calibration (finite numbers, rotations orthonormal
with determinant +1, positive focal lengths, whole positive image sizes), metadata types, and the
sweeps' channel count, taken from the sequence's first sweep of a valid size (every sweep must
then have that size). Per frame (``frame``, ``check_images``): sweep size and finite values, label
and box files, images decoded and of the calibrated size.
"""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from storage.files import InputError, open_regular, read_bytes, read_text, regular_stat, where
from storage.sequence_data import (
    Box3D,
    Calibration,
    CameraCalibration,
    Frame,
    RawCameraCalibration,
    SequenceInfo,
)

#: points per organised OS1-128 sweep (128 beams x 1024 columns), no-returns included
POINTS_PER_SWEEP = 128 * 1024
COLUMNS_PER_BEAM = 1024
LIDAR_SOURCES = ("3d_comp", "3d_raw")
IMAGE_SOURCES = ("2d_rect", "2d_raw")
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")
FRAME_SELECTIONS = ("files", "metadata")
#: the metadata lists that name annotated frames (coda-devkit helpers/metadata.py)
METADATA_TASKS = ("ObjectTracking", "SemanticSegmentation")
#: metadata ``lighting`` values that mean night (the devkit's METALighting.DARK is "dark")
NIGHT_WORDS = ("night", "dark")
NS_PER_S = 1_000_000_000
#: pose times may differ from the frame timestamps by this much (half a frame at 10 Hz)
POSE_TIME_TOLERANCE_S = 0.05
#: a robot faster than this between two raw frames is a broken pose, not a fast robot
MAX_SPEED_MPS = 20.0
#: pose translations beyond this distance from the map origin are not a campus-scale map
MAX_POSITION_M = 1.0e5
#: rotation matrices: |R R^T - I| and |det R - 1| within this
ROTATION_TOLERANCE = 1e-3
#: version of what opening a sequence checks and returns: a fingerprint memo made by another
#: version is not used (planning opens the sequence again); bump when the checks change
READER_VERSION = "2"
#: the layout folders that hold one sub-folder per sequence (``{modality}/{sensor}/{SEQ}/``)
SEQUENCE_MODALITIES = ("3d_comp", "3d_raw", "2d_rect", "2d_raw", "3d_bbox", "3d_semantic")


class CodaFormatError(InputError):
    """Bad or missing input in a CODa-layout dataset (``path`` / ``frame`` where known)."""


class CodaFrameError(CodaFormatError):
    """One frame's file is missing or unreadable: ``path`` and ``frame`` (raw number) say which.

    The sequence and its other frames may still be fine; a stage can fail this frame alone.
    """

    def __init__(self, message: str, path: Path, frame: int | None, sequence: str | None = None):
        super().__init__(message, path, frame, sequence)


def _where(path: Path, frame: int | None) -> str:
    return where(path, frame)


def _frame_error(exc: InputError, frame: int | None) -> CodaFrameError:
    """An InputError about one frame's file as that frame's CodaFrameError."""
    return CodaFrameError(
        str(exc), exc.path or Path("?"), frame if exc.frame is None else exc.frame
    )


@dataclass(frozen=True)
class LidarSweep:
    """One decoded sweep, no-return points removed.

    points: (N, 3) float32 LiDAR frame, metres. intensity: (N,) float32; intensity_present: False
    when every return has intensity 0 (not a measurement). time_s: (N,) float32 seconds since the
    sweep's first column (from the 5th channel's nanoseconds) or None (4-channel files). ring: (N,)
    uint8 beam index (0 = top row of the organised scan). index: (N,) int64 position in the
    organised 131,072-point scan (to align per-point label files). channels: 4 or 5.
    """

    points: np.ndarray
    intensity: np.ndarray
    time_s: np.ndarray | None
    ring: np.ndarray
    index: np.ndarray
    intensity_present: bool = True
    channels: int = 5


def _channels_of_size(size: int) -> int | None:
    per_channel = POINTS_PER_SWEEP * 4
    if size == 0 or size % per_channel or size // per_channel not in (4, 5):
        return None
    return size // per_channel


def lidar_channels(
    path: Path, frame: int | None = None, expected: tuple[int, Path] | None = None
) -> int:
    """Channels (4 or 5) of an organised OS1-128 ``.bin`` from its size alone (no read).

    expected: (channels, file they were taken from) of the sequence; a file of another size is an
    error even when that size is a whole sweep of the other channel count (a 5-channel sweep cut
    to exactly the 4-channel size would otherwise be read as 4 scrambled channels)."""
    path = Path(path)
    where = _where(path, frame)
    try:
        size = regular_stat(path, frame, "LiDAR file").st_size
    except InputError as exc:
        raise _frame_error(exc, frame) from None
    per_channel = POINTS_PER_SWEEP * 4
    if expected is not None and size != expected[0] * per_channel:
        raise CodaFrameError(
            f"{where}: {size} bytes but the sequence's sweeps have {expected[0]} float32 channels "
            f"({expected[0] * per_channel} bytes, as its first sweep {expected[1].name}); the file is truncated "
            "or from another recording",
            path,
            frame,
        )
    if size == 0 or size % per_channel:
        raise CodaFrameError(
            f"{where}: {size} bytes is not a whole organised 128x1024 sweep "
            f"(expected 4 or 5 float32 channels = {4 * per_channel} or {5 * per_channel} bytes); "
            "the file is truncated or not an OS1-128 sweep",
            path,
            frame,
        )
    channels = size // per_channel
    if channels not in (4, 5):
        raise CodaFrameError(
            f"{where}: {channels} channels inferred from {size} bytes; expected 4 (x y z intensity) "
            "or 5 (x y z intensity time)",
            path,
            frame,
        )
    return int(channels)


def read_lidar_raw(
    path: Path, frame: int | None = None, expected: tuple[int, Path] | None = None
) -> np.ndarray:
    """(131072, C) float32 organised sweep as stored (C = 4 or 5), finite values checked;
    ``expected``: the sequence's (channels, first sweep), see :func:`lidar_channels`."""
    path = Path(path)
    channels = lidar_channels(path, frame, expected)
    try:
        data = read_bytes(path, frame, "LiDAR file")
    except InputError as exc:
        raise _frame_error(exc, frame) from None
    if len(data) != POINTS_PER_SWEEP * channels * 4:  # changed between the stat and the read
        raise CodaFrameError(
            f"{_where(path, frame)}: read {len(data)} bytes, expected "
            f"{POINTS_PER_SWEEP * channels * 4}",
            path,
            frame,
        )
    raw = np.frombuffer(data, dtype="<f4").reshape(POINTS_PER_SWEEP, channels)
    bad = ~np.isfinite(raw).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise CodaFrameError(
            f"{_where(path, frame)}: {int(bad.sum())} points have NaN or inf values (first at point "
            f"{first}: {raw[first].tolist()}); expected finite floats (no-returns are zeros)",
            path,
            frame,
        )
    return raw


def read_lidar_bin(
    path: Path,
    min_range_m: float = 0.0,
    max_range_m: float = math.inf,
    frame: int | None = None,
    expected: tuple[int, Path] | None = None,
) -> LidarSweep:
    """Decode an organised OS1-128 ``.bin`` (float32 LE, 4 or 5 channels inferred from size, or
    ``expected`` = the sequence's (channels, first sweep))."""
    raw = read_lidar_raw(path, frame, expected)
    channels = raw.shape[1]
    rng = np.linalg.norm(raw[:, :3], axis=1)
    keep = (rng > max(min_range_m, 1e-6)) & (rng <= max_range_m)
    index = np.flatnonzero(keep)
    intensity = np.ascontiguousarray(raw[index, 3])
    time_s = (
        (raw[index, 4].astype(np.float64) / NS_PER_S).astype(np.float32) if channels == 5 else None
    )
    return LidarSweep(
        points=np.ascontiguousarray(raw[index, :3]),
        intensity=intensity,
        time_s=time_s,
        ring=(index // COLUMNS_PER_BEAM).astype(np.uint8),
        index=index.astype(np.int64),
        intensity_present=bool(index.size == 0 or np.any(intensity != 0)),
        channels=int(channels),
    )


def quat_wxyz_to_matrix(q: np.ndarray) -> np.ndarray:
    """(4,) quaternion (w, x, y, z) -> (3, 3) rotation matrix, float64 (normalises q)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def box_rotation(rpy: np.ndarray) -> np.ndarray:
    """CODa box angles (roll, pitch, yaw) -> (3, 3) rotation Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


def rectified_camera(
    R_rect: np.ndarray, P_rect: np.ndarray, T_cam_from_lidar: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The pinhole of a rectified image: (K (3, 3), T_rect_from_lidar (4, 4)) float64.

    R_rect (3, 3) rectification_matrix, P_rect (3, 4) projection_matrix, T_cam_from_lidar (4, 4)
    the raw camera's extrinsic. ``initUndistortRectifyMap(K, D, R, P)`` maps the rectified pixel
    (u, v) through ``(P[:, :3] @ R)^-1``, so K = P[:, :3] and T_rect_from_lidar = [[R, 0], [0, 1]]
    @ T_cam_from_lidar; P's 4th column (-fx * baseline on the right camera of a stereo pair)
    belongs to projecting points given in the *left* rectified frame and is not used here.
    """
    K = np.array(P_rect, dtype=np.float64)[:, :3].copy()
    R4 = np.eye(4)
    R4[:3, :3] = R_rect
    return K, R4 @ np.asarray(T_cam_from_lidar, dtype=np.float64)


_FRAME_NAME = re.compile(r"_(\d+)$")


def frame_number(path: Path) -> int | None:
    """The FRAME of ``{modality}_{sensor}_{SEQ}_{FRAME}.{ext}``, None if the name has none."""
    m = _FRAME_NAME.search(Path(path).name.split(".", 1)[0])
    return int(m.group(1)) if m else None


def stride_frames(candidates, stride: int) -> tuple[int, ...]:
    """Ascending raw frames, keeping one when it is >= ``stride`` raw frames after the last kept."""
    kept: list[int] = []
    for f in sorted(set(int(c) for c in candidates)):
        if not kept or f - kept[-1] >= stride:
            kept.append(f)
    return tuple(kept)


class CodaSequence:
    """One sequence of a CODa-layout root. Cheap to build (no sweep is read); frames on demand.

    frame_stride: keep a frame every k raw frames (2 for 5 Hz). lidar_source: ``3d_comp`` (what
    the downloads ship for os1) or ``3d_raw``; image_source: ``2d_rect`` or ``2d_raw``. frames:
    ``files`` (frames whose sweep exists) or ``metadata`` (frames named by the metadata lists).
    lighting: "day" / "night" for this sequence (the config's), None = the metadata's ``lighting``.
    lidar_height_m: used where ``calib_os1_to_base.yaml`` is missing (T_base_from_lidar = a pure
    lift of that height, with a warning in ``info.warnings``); None = that file is required.
    """

    def __init__(
        self,
        root: Path,
        sequence: str | int,
        *,
        frame_stride: int = 2,
        lidar_source: str = "3d_comp",
        image_source: str = "2d_rect",
        min_range_m: float = 0.5,
        max_range_m: float = math.inf,
        cameras: tuple[str, ...] = ("cam0", "cam1"),
        frames: str = "files",
        lighting: str | None = None,
        lidar_height_m: float | None = None,
    ):
        self.root = Path(root)
        self.sequence = str(sequence)
        if lidar_source not in LIDAR_SOURCES:
            raise CodaFormatError(f"lidar_source {lidar_source!r}: expected one of {LIDAR_SOURCES}")
        if image_source not in IMAGE_SOURCES:
            raise CodaFormatError(f"image_source {image_source!r}: expected one of {IMAGE_SOURCES}")
        if frames not in FRAME_SELECTIONS:
            raise CodaFormatError(f"frames {frames!r}: expected one of {FRAME_SELECTIONS}")
        if lighting not in (None, "day", "night"):
            raise CodaFormatError(
                f"lighting {lighting!r} for sequence {self.sequence}: expected day or night"
            )
        if frame_stride < 1:
            raise CodaFormatError(f"frame_stride {frame_stride}: expected >= 1")
        self.frame_stride = frame_stride
        self.lidar_source = lidar_source
        self.image_source = image_source
        self.min_range_m = min_range_m
        self.max_range_m = max_range_m
        self.cameras = cameras
        self.frame_selection = frames
        self.lidar_height_m = lidar_height_m
        self._lighting = lighting
        if self.sequence not in list_sequences(self.root):
            stamps = self.root / "timestamps" / f"{self.sequence}.txt"
            held = sequence_folders(self.root, self.sequence)
            if held:  # the sequence has files, but not the one that says which frames exist
                raise CodaFormatError(
                    f"{stamps}: timestamps file is missing (sequence {self.sequence} has "
                    f"{', '.join(held[:3])}{' ...' if len(held) > 3 else ''})",
                    stamps,
                )
            raise CodaFormatError(
                f"unknown sequence id {self.sequence!r} in {self.root}: no "
                f"timestamps/{self.sequence}.txt (available: {list_sequences(self.root) or 'none'})",
                stamps,
            )
        self.info = self._read_info()

    # -- paths ------------------------------------------------------------------------------
    def path(self, modality: str, sensor: str, frame: int, ext: str) -> Path:
        seq = self.sequence
        return self.root / modality / sensor / seq / f"{modality}_{sensor}_{seq}_{frame}{ext}"

    def lidar_path(self, frame: int) -> Path:
        return self.path(self.lidar_source, "os1", frame, ".bin")

    def image_path(self, camera: str, frame: int) -> Path:
        """The ``image_source`` image of ``camera`` at raw frame ``frame`` (.png, .jpg or .jpeg).

        No fallback to the other image source: its pixels belong to another camera model."""
        for ext in IMAGE_EXTENSIONS:
            candidate = self.path(self.image_source, camera, frame, ext)
            if _present(candidate):
                return candidate
        missing = self.path(self.image_source, camera, frame, ".png")
        raise CodaFrameError(
            f"{missing} (frame {frame}): image is missing (looked for {', '.join(IMAGE_EXTENSIONS)} "
            f"in {self.image_source})",
            missing,
            frame,
            self.sequence,
        )

    # -- sequence level ---------------------------------------------------------------------
    def _read_info(self) -> SequenceInfo:
        stamps_path = self.root / "timestamps" / f"{self.sequence}.txt"
        stamps_s = _read_timestamps(stamps_path)
        pose_path = self.root / "poses" / "dense_global" / f"{self.sequence}.txt"
        if not _present(pose_path):  # sequences 8, 14, 15 of CODa have no dense_global poses
            pose_path = self.root / "poses" / "dense" / f"{self.sequence}.txt"
        poses = _read_poses(
            pose_path, expected=len(stamps_s), stamps_path=stamps_path, stamps_s=stamps_s
        )
        metadata_path = self.root / "metadata" / f"{self.sequence}.json"
        metadata = _read_json(metadata_path) if _present(metadata_path) else {}
        _check_metadata(metadata, metadata_path)
        warnings: list[str] = []
        calibration = self._read_calibration(warnings)
        frames, selection = self._select_frames(len(stamps_s), metadata, metadata_path)
        lighting, source = self._resolve_lighting(metadata)
        channels = self._sweep_channels(frames)
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
            selection=selection,
            num_stamps=len(stamps_s),
            lighting=lighting,
            lighting_source=source,
            warnings=tuple(warnings),
            lidar_channels=channels[0] if channels else 0,
            lidar_channels_from=channels[1] if channels else None,
        )

    def _sweep_channels(self, frames) -> tuple[int, Path] | None:
        """(channels, file) of the first selected sweep whose size is a whole 4- or 5-channel
        sweep (sizes only); None when no sweep has such a size (each frame then fails alone)."""
        for f in frames:
            path = self.lidar_path(f)
            try:
                channels = _channels_of_size(regular_stat(path, f).st_size)
            except InputError:
                continue
            if channels is not None:
                return channels, path
        return None

    def lidar_frames_on_disk(self) -> list[int]:
        """Raw frame numbers that have a ``lidar_source`` sweep file (a directory listing)."""
        folder = self.root / self.lidar_source / "os1" / self.sequence
        if not folder.is_dir():
            return []
        prefix = f"{self.lidar_source}_os1_{self.sequence}_"
        found = []
        for p in folder.iterdir():
            if p.name.startswith(prefix) and p.suffix == ".bin":
                n = frame_number(p)
                if n is not None:
                    found.append(n)
        return sorted(found)

    def metadata_frames(self, metadata: dict | None = None) -> list[int]:
        """Raw frames named by the metadata's ObjectTracking / SemanticSegmentation lists."""
        metadata = self.info.metadata if metadata is None else metadata
        found = set()
        for task in METADATA_TASKS:
            for files in (metadata.get(task) or {}).values():
                for rel in files or ():
                    n = frame_number(Path(str(rel)))
                    if n is not None:
                        found.add(n)
        return sorted(found)

    def _select_frames(self, num_stamps: int, metadata: dict, metadata_path: Path):
        folder = self.root / self.lidar_source / "os1" / self.sequence
        if self.frame_selection == "metadata":
            candidates = self.metadata_frames(metadata)
            if not candidates:
                raise CodaFormatError(
                    f"{metadata_path}: no frames listed under {' / '.join(METADATA_TASKS)} "
                    "(dataset.frames: metadata needs them; use dataset.frames: files)"
                )
            how = f"metadata: {len(candidates)} annotated frames listed"
        else:
            candidates = self.lidar_frames_on_disk()
            if not candidates:
                other = [
                    s
                    for s in LIDAR_SOURCES
                    if s != self.lidar_source and (self.root / s / "os1" / self.sequence).is_dir()
                ]
                hint = (
                    f"; found {other[0]}/os1/{self.sequence}: set dataset.lidar_source: {other[0]}"
                    if other
                    else ""
                )
                raise CodaFormatError(
                    f"{folder}: no {self.lidar_source} sweeps for sequence {self.sequence}{hint}"
                )
            kind = "all frames" if len(candidates) == num_stamps else "split-style subset"
            how = f"files: {len(candidates)} of {num_stamps} frames have a {self.lidar_source} sweep ({kind})"
        beyond = [f for f in candidates if f >= num_stamps]
        if beyond:
            raise CodaFormatError(
                f"{self.lidar_path(beyond[0])} (frame {beyond[0]}): frame number beyond the "
                f"{num_stamps} lines of timestamps/{self.sequence}.txt ({len(beyond)} such frames)"
            )
        frames = stride_frames(candidates, self.frame_stride)
        if self.frame_stride > 1:
            how += f"; {len(frames)} kept at >= {self.frame_stride} raw frames apart"
        return frames, how

    def _resolve_lighting(self, metadata: dict) -> tuple[str, str]:
        if self._lighting is not None:
            return self._lighting, "config"
        value = metadata.get("lighting")
        if value is None:
            return "day", "default"
        return ("night" if str(value).lower() in NIGHT_WORDS else "day"), "metadata"

    def _read_calibration(self, warnings: list[str]) -> Calibration:
        folder = self.root / "calibrations" / self.sequence
        c01_path = folder / "calib_cam0_to_cam1.yaml"
        T_cam1_from_cam0 = read_extrinsic(c01_path)[0] if _present(c01_path) else None
        cameras = {}
        for cam in self.cameras:
            intr_path = folder / f"calib_{cam}_intrinsics.yaml"
            ext_path = folder / f"calib_os1_to_{cam}.yaml"
            if cam != "cam0" and not _present(intr_path):
                continue  # only cam0 is required
            intr = read_intrinsics(intr_path)
            if _present(ext_path):
                T, P_l2r = read_extrinsic(ext_path)
            elif cam == "cam1" and T_cam1_from_cam0 is not None and "cam0" in cameras:
                # as the devkit's gen_calibrations.py: T_os1_to_cam1 = T_cam0_to_cam1 @ T_os1_to_cam0
                T, P_l2r = T_cam1_from_cam0 @ cameras["cam0"].raw.T_cam_from_lidar, None
            else:
                T, P_l2r = read_extrinsic(ext_path)  # raises: file is missing
            raw = RawCameraCalibration(
                intr["K"], intr["distortion"], intr["R"], intr["P"], T, P_l2r
            )
            if self.image_source == "2d_rect":
                if not intr["has_rect"]:
                    warnings.append(
                        f"{intr_path}: no rectification_matrix / projection_matrix; 2d_rect "
                        "images are projected with camera_matrix and the raw extrinsic"
                    )
                K, T_cam = rectified_camera(intr["R"], intr["P"], T)
                cameras[cam] = CameraCalibration(
                    cam, K, np.zeros(5), intr["width"], intr["height"], T_cam, raw, rectified=True
                )
            else:
                if np.any(intr["distortion"] != 0):
                    warnings.append(
                        f"{cam}: 2d_raw images are distorted ({intr_path.name} k1={intr['distortion'][0]:.4g}) "
                        "and the pipeline projects with a pinhole; use 2d_rect"
                    )
                cameras[cam] = CameraCalibration(
                    cam,
                    intr["K"],
                    intr["distortion"],
                    intr["width"],
                    intr["height"],
                    T,
                    raw,
                    rectified=False,
                )
        base_path = folder / "calib_os1_to_base.yaml"
        if _present(base_path) or self.lidar_height_m is None:
            T_base, base_default = read_extrinsic(base_path)[0], False
        else:
            T_base, base_default = np.eye(4), True
            T_base[2, 3] = float(self.lidar_height_m)
            warnings.append(
                f"{base_path} is missing: T_base_from_lidar = the LiDAR "
                f"{self.lidar_height_m:g} m above the ground, axes aligned "
                "(dataset.lidar_height_m)"
            )
        return Calibration(
            cameras=cameras,
            T_base_from_lidar=T_base,
            base_is_default=base_default,
            T_cam1_from_cam0=T_cam1_from_cam0,
        )

    def _input_files(self, frames, *extra: Path) -> list[Path]:
        """Every file the selected frames read, for the content fingerprint."""
        files = [p for p in extra if _present(p)]
        files += sorted((self.root / "calibrations" / self.sequence).glob("*.yaml"))
        wanted = set(frames)
        patterns = [(self.lidar_source, "os1"), ("3d_bbox", "os1"), ("3d_semantic", "os1")]
        patterns += [(self.image_source, cam) for cam in self.cameras]
        for modality, sensor in patterns:
            folder = self.root / modality / sensor / self.sequence
            if not folder.is_dir():
                continue
            for p in sorted(folder.iterdir()):
                n = frame_number(p)
                if n is not None and n in wanted:
                    files.append(p)
        gt = self.root / "gt" / self.sequence
        if gt.is_dir():  # every entry that is not a folder: a FIFO or a broken link fails the hash
            files += sorted(Path(top) / name for top, dirs, names in os.walk(gt) for name in names)
        return files

    # -- frame level ------------------------------------------------------------------------
    def __len__(self) -> int:
        return self.info.num_frames

    def position(self, raw_frame: int) -> int:
        """The position in ``info.frame_indices`` of a raw frame number (ValueError if not selected)."""
        try:
            return self.info.frame_indices.index(int(raw_frame))
        except ValueError:
            raise ValueError(
                f"sequence {self.sequence}: raw frame {raw_frame} is not a selected frame"
            ) from None

    def frame(self, i: int) -> Frame:
        """The i-th selected frame (i indexes ``info.frame_indices``); CodaFrameError if its files
        are missing or unreadable."""
        if not 0 <= i < len(self):
            raise IndexError(
                f"sequence {self.sequence}: frame position {i} not in 0..{len(self) - 1}"
            )
        raw = self.info.frame_indices[i]
        try:
            return self._frame(i, raw)
        except CodaFrameError as exc:
            exc.sequence = self.sequence
            raise

    def _frame(self, i: int, raw: int) -> Frame:
        lidar_path = self.lidar_path(raw)
        info = self.info
        expected = (
            (info.lidar_channels, info.lidar_channels_from) if info.lidar_channels_from else None
        )
        sweep = read_lidar_bin(
            lidar_path, self.min_range_m, self.max_range_m, frame=raw, expected=expected
        )
        sem_path = self.path("3d_semantic", "os1", raw, ".bin")
        semantic = read_semantic(sem_path, raw)[sweep.index] if _present(sem_path) else None
        box_path = self.path("3d_bbox", "os1", raw, ".json")
        boxes, problems = read_boxes(box_path, frame=raw) if _present(box_path) else ((), ())
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
            box_problems=problems,
            intensity_present=sweep.intensity_present,
        )

    def frames(self):
        for i in range(len(self)):
            yield self.frame(i)

    def check_images(self, raw_frame: int) -> None:
        """Decode every camera's image of a raw frame and check its size against the calibration
        (CodaFrameError naming the file and frame otherwise). Header checks cannot see a corrupt
        or cut image; a stage that hands images on (detect, for the exports) calls this."""
        for name, cam in self.info.calibration.cameras.items():
            path = self.image_path(name, raw_frame)
            decode_image(path, raw_frame, (cam.width, cam.height), self.sequence)


def _sorted_ids(ids) -> list[str]:
    return sorted(set(ids), key=lambda s: (not s.isdigit(), int(s) if s.isdigit() else 0, s))


def list_sequences(root: Path) -> list[str]:
    """Sequence ids of a CODa-layout root (those with a timestamps file), numerically sorted."""
    folder = Path(root) / "timestamps"
    if not folder.is_dir():
        return []
    return _sorted_ids(p.stem for p in folder.glob("*.txt") if not p.name.startswith("."))


def _ids_in(folder: Path, files: bool, suffix: str = "") -> list[str]:
    try:
        entries = list(os.scandir(folder))
    except OSError:  # missing, not a folder, unreadable: no ids from here
        return []
    out = []
    for e in entries:
        if e.name.startswith((".", "_")):
            continue
        if files and e.name.endswith(suffix):
            out.append(e.name[: len(e.name) - len(suffix)])
        elif not files:
            out.append(e.name)
    return out


def sequence_ids(root: Path) -> list[str]:
    """Every sequence id that has any layout file or folder under ``root`` (timestamps, poses,
    metadata, calibrations or a ``{modality}/{sensor}/{SEQ}`` folder), numerically sorted: a
    sequence missing its timestamps file is still found, so a run can report it instead of
    leaving it out."""
    root = Path(root)
    ids = list_sequences(root)
    ids += _ids_in(root / "poses" / "dense_global", True, ".txt") + _ids_in(
        root / "poses" / "dense", True, ".txt"
    )
    ids += _ids_in(root / "metadata", True, ".json") + _ids_in(root / "calibrations", False)
    for modality in SEQUENCE_MODALITIES:
        for sensor in _ids_in(root / modality, False):
            ids += _ids_in(root / modality / sensor, False)
    return _sorted_ids(ids)


def sequence_folders(root: Path, sequence: str) -> list[str]:
    """The layout paths (relative to ``root``) that hold files of ``sequence``."""
    root, out = Path(root), []
    for rel in (
        f"timestamps/{sequence}.txt",
        f"poses/dense_global/{sequence}.txt",
        f"poses/dense/{sequence}.txt",
        f"metadata/{sequence}.json",
        f"calibrations/{sequence}",
    ):
        if os.path.lexists(root / rel):
            out.append(rel)
    for modality in SEQUENCE_MODALITIES:
        for sensor in _ids_in(root / modality, False):
            if os.path.lexists(root / modality / sensor / sequence):
                out.append(f"{modality}/{sensor}/{sequence}")
    return out


def check_dataset_root(root: Path) -> list[str]:
    """The sequence ids of a dataset root (:func:`sequence_ids`); CodaFormatError when the root is
    missing, not a folder, or holds no sequence at all."""
    root = Path(root)
    if not root.exists():
        raise CodaFormatError(f"dataset root {root} does not exist", root)
    if not root.is_dir():
        raise CodaFormatError(f"dataset root {root} is not a folder", root)
    ids = sequence_ids(root)
    if not ids:
        raise CodaFormatError(
            f"dataset root {root} holds no sequence (expected the CODa layout: "
            "timestamps/<SEQ>.txt, poses/, calibrations/<SEQ>/, 3d_comp/os1/<SEQ>/ ...)",
            root,
        )
    return ids


def sequence_layout(
    root: Path,
    sequence: str,
    lidar_source: str,
    image_source: str,
    cameras: tuple[str, ...] = ("cam0", "cam1"),
) -> list[tuple[str, bool]]:
    """(path, is a folder to list) of everything a sequence's files live in, for a stat
    signature: if no entry of these changed size, mtime or inode, the sequence reads the same.
    Plain strings: this runs for every sequence of every plan."""
    root, seq, join = os.fspath(root), str(sequence), os.path.join
    out = [
        (join(root, "timestamps", f"{seq}.txt"), False),
        (join(root, "poses", "dense_global", f"{seq}.txt"), False),
        (join(root, "poses", "dense", f"{seq}.txt"), False),
        (join(root, "metadata", f"{seq}.json"), False),
        (join(root, "calibrations", seq), True),
        (join(root, "gt", seq), True),
    ]
    for modality, sensor in [
        (lidar_source, "os1"),
        ("3d_bbox", "os1"),
        ("3d_semantic", "os1"),
        *[(image_source, cam) for cam in cameras],
    ]:
        out.append((join(root, modality, sensor, seq), True))
    return out


def _present(path: Path) -> bool:
    """The path exists as an entry (a broken or looping link counts: reading it gives the error)."""
    return os.path.lexists(path)


def image_size(path: Path, frame: int | None = None) -> tuple[int, int]:
    """(width, height) of an image from its header (not decoded)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with open_regular(path, frame, "image") as fh, Image.open(fh) as im:
            return int(im.size[0]), int(im.size[1])
    except InputError as exc:
        raise _frame_error(exc, frame) from None
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise CodaFrameError(
            f"{_where(path, frame)}: not a readable image ({exc})", path, frame
        ) from None


def decode_image(
    path: Path,
    frame: int | None,
    expect_size: tuple[int, int] | None = None,
    sequence: str | None = None,
) -> None:
    """Decode an image fully (a corrupt or cut file fails here) and check its size."""
    from PIL import Image, UnidentifiedImageError

    try:
        with open_regular(path, frame, "image") as fh, Image.open(fh) as im:
            im.load()
            size = (int(im.size[0]), int(im.size[1]))
    except InputError as exc:
        raise _frame_error(exc, frame) from None
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as exc:
        raise CodaFrameError(
            f"{_where(path, frame)}: image cannot be decoded ({exc})", path, frame, sequence
        ) from None
    if expect_size is not None and size != tuple(expect_size):
        raise CodaFrameError(
            f"{_where(path, frame)}: image is {size[0]} x {size[1]} px, the camera calibration "
            f"says {expect_size[0]} x {expect_size[1]}",
            path,
            frame,
            sequence,
        )


def read_semantic(path: Path, frame: int | None = None) -> np.ndarray:
    """(131072,) uint8 CODa 3d_semantic ids of an organised sweep (one byte per point)."""
    try:
        labels = np.frombuffer(read_bytes(path, frame, "3d_semantic file"), dtype=np.uint8)
    except InputError as exc:
        raise _frame_error(exc, frame) from None
    if labels.size != POINTS_PER_SWEEP:
        raise CodaFrameError(
            f"{_where(path, frame)}: {labels.size} labels, expected {POINTS_PER_SWEEP} "
            "(one byte per point of the organised sweep)",
            path,
            frame,
        )
    return labels


_BOX_KEYS = ("cX", "cY", "cZ", "l", "w", "h", "r", "p", "y")


def read_boxes(path: Path, frame: int | None = None) -> tuple[tuple[Box3D, ...], tuple[str, ...]]:
    """A CODa ``3d_bbox`` JSON file -> (valid boxes in the os1 frame, one message per skipped box).

    Skipped: a box that is not an object with classId and finite numbers cX cY cZ l w h r p y, a
    size that is not positive, an instanceId without an integer id after its last ':' (a track id
    is needed). A file that is not JSON or has no '3dbbox' list raises CodaFrameError.
    """
    path = Path(path)
    where = _where(path, frame)
    try:
        data = json.loads(read_text(path, frame, "3d_bbox file"))
    except InputError as exc:
        raise _frame_error(exc, frame) from None
    except json.JSONDecodeError as exc:
        raise CodaFrameError(f"{where}: invalid JSON ({exc})", path, frame) from None
    if not isinstance(data, dict) or not isinstance(data.get("3dbbox"), list):
        raise CodaFrameError(f"{where}: expected an object with a '3dbbox' list", path, frame)
    boxes, problems = [], []
    for k, entry in enumerate(data["3dbbox"]):
        try:
            values = [float(entry[key]) for key in _BOX_KEYS]
            class_name = str(entry["classId"])
        except (KeyError, TypeError, ValueError) as exc:
            problems.append(
                f"box {k}: malformed ({exc!r}); expected classId and {' '.join(_BOX_KEYS)}"
            )
            continue
        instance_id = str(entry.get("instanceId") or "")
        if not all(math.isfinite(v) for v in values):
            problems.append(f"box {k} ({instance_id or class_name}): non-finite values {values}")
            continue
        if min(values[3:6]) <= 0:
            problems.append(
                f"box {k} ({instance_id or class_name}): non-positive size l w h = {values[3:6]}"
            )
            continue
        box = Box3D(
            instance_id,
            class_name,
            np.array(values[0:3]),
            np.array(values[3:6]),
            np.array(values[6:9]),
            str((entry.get("labelAttributes") or {}).get("isOccluded", "Unknown")),
        )
        if box.track_id < 0:
            problems.append(
                f"box {k} ({class_name}): instanceId {instance_id!r} has no integer id "
                "after ':' (expected e.g. 'Pedestrian:12')"
            )
            continue
        boxes.append(box)
    return tuple(boxes), tuple(problems)


# -- calibration files ------------------------------------------------------------------------
def read_intrinsics(path: Path) -> dict:
    """A ``calib_{cam}_intrinsics.yaml`` -> dict(width, height, K (3, 3), distortion (5,), R (3, 3),
    P (3, 4), has_rect). R defaults to identity and P to [K | 0] where the file lacks them
    (has_rect False)."""
    data = _read_yaml(path)
    K = _yaml_matrix(data, "camera_matrix", (3, 3), path)
    dist = _yaml_matrix(data, "distortion_coefficients", None, path).reshape(-1)
    if dist.size not in (4, 5, 8):
        raise CodaFormatError(
            f"{path}: distortion_coefficients has {dist.size} values, expected 5 "
            "(plumb_bob k1 k2 p1 p2 k3)"
        )
    if np.any(dist[5:] != 0):
        raise CodaFormatError(
            f"{path}: distortion_coefficients {dist.tolist()}: only plumb_bob "
            "(k1 k2 p1 p2 k3) is supported"
        )
    dist = np.pad(dist[:5], (0, 5 - min(dist.size, 5)))
    width = _positive_int(data, "image_width", path)
    height = _positive_int(data, "image_height", path)
    has_rect = "rectification_matrix" in data and "projection_matrix" in data
    R = (
        _yaml_matrix(data, "rectification_matrix", (3, 3), path)
        if "rectification_matrix" in data
        else np.eye(3)
    )
    _check_rotation(R, path, "rectification_matrix")
    P = (
        _yaml_matrix(data, "projection_matrix", (3, 4), path)
        if "projection_matrix" in data
        else np.hstack([K, np.zeros((3, 1))])
    )
    for name, M in (("camera_matrix", K), ("projection_matrix", P)):
        if not (M[0, 0] > 0 and M[1, 1] > 0 and np.allclose(M[2, :3], [0, 0, 1])):
            raise CodaFormatError(
                f"{path}: {name} {M.tolist()} is not a camera matrix "
                "(expected fx, fy > 0 and a last row 0 0 1)"
            )
    return {
        "width": width,
        "height": height,
        "K": K,
        "distortion": dist,
        "R": R,
        "P": P,
        "has_rect": has_rect,
    }


def read_extrinsic(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """An extrinsic YAML -> (T_target_from_source (4, 4) float64, projection_matrix (3, 4) or None).

    ``extrinsic_matrix`` is either ``{rows: 4, cols: 4, data: [16]}`` (row-major; 3 x 4 accepted)
    or, as CODa's ``calib_cam0_to_cam1.yaml``, ``{R: {rows: 3, cols: 3, data: [9]}, T: [3]}``.
    A top-level ``projection_matrix`` (3 x 4, the devkit's P R T) is returned when present.
    """
    data = _read_yaml(path)
    node = _yaml_key(data, "extrinsic_matrix", path)
    T = np.eye(4)
    if isinstance(node, dict) and "R" in node and "T" in node:
        T[:3, :3] = _yaml_matrix(node, "R", (3, 3), path, "extrinsic_matrix.R")
        T[:3, 3] = _yaml_matrix(node, "T", (3, 1), path, "extrinsic_matrix.T").reshape(3)
    else:
        values = _yaml_matrix(data, "extrinsic_matrix", None, path).reshape(-1)
        if values.size not in (12, 16):
            raise CodaFormatError(
                f"{path}: extrinsic_matrix has {values.size} values, expected 4x4 "
                "(rows/cols/data) or {R: 3x3, T: [3]}"
            )
        T[:3] = values[:12].reshape(3, 4)
        if values.size == 16 and not np.allclose(values[12:], [0, 0, 0, 1], atol=1e-9):
            raise CodaFormatError(
                f"{path}: extrinsic_matrix last row {values[12:].tolist()}, expected 0 0 0 1"
            )
    _check_rotation(T[:3, :3], path, "extrinsic_matrix rotation")
    P = (
        _yaml_matrix(data, "projection_matrix", (3, 4), path)
        if "projection_matrix" in data
        else None
    )
    return T, P


def _check_rotation(R: np.ndarray, path: Path, name: str) -> None:
    """A rotation: orthonormal (R R^T = I) with determinant +1, within ROTATION_TOLERANCE."""
    err = float(np.max(np.abs(R @ R.T - np.eye(3))))
    if err > ROTATION_TOLERANCE:
        raise CodaFormatError(
            f"{path}: {name} is not orthonormal (max |R R^T - I| = {err:.3g}, a scaled, sheared "
            f"or zero matrix): {np.round(R, 6).tolist()}",
            path,
        )
    det = float(np.linalg.det(R))
    if abs(det - 1.0) > ROTATION_TOLERANCE:
        raise CodaFormatError(
            f"{path}: {name} has determinant {det:.4f}, expected +1 (a reflection, not a "
            f"rotation): {np.round(R, 6).tolist()}",
            path,
        )


def _check_metadata(metadata, path: Path) -> None:
    """The metadata fields the reader uses have the types CODa's devkit writes."""
    if not isinstance(metadata, dict):
        raise CodaFormatError(
            f"{path}: expected a JSON object, got {type(metadata).__name__}", path
        )
    lighting = metadata.get("lighting")
    if lighting is not None and not isinstance(lighting, str):
        raise CodaFormatError(
            f"{path}: 'lighting' is {lighting!r}, expected a string (e.g. \"dark\")", path
        )
    for task in METADATA_TASKS:
        lists = metadata.get(task)
        if lists is None:
            continue
        if not isinstance(lists, dict):
            raise CodaFormatError(
                f"{path}: {task!r} is a {type(lists).__name__}, expected an object of file "
                "lists (split -> [paths])",
                path,
            )
        for split, files in lists.items():
            if files is not None and (
                not isinstance(files, list) or not all(isinstance(f, str) for f in files)
            ):
                raise CodaFormatError(
                    f"{path}: {task}.{split} is {str(files)[:80]}, expected a list of file paths",
                    path,
                )


# -- small parsers ----------------------------------------------------------------------------
def _read_timestamps(path: Path) -> np.ndarray:
    try:
        lines = read_text(path, None, "timestamps file").split()
    except InputError as exc:
        raise CodaFormatError(str(exc), path) from None
    try:
        stamps = np.array([float(x) for x in lines], dtype=np.float64)
    except ValueError as exc:
        raise CodaFormatError(f"{path}: not a list of Unix seconds ({exc})") from None
    if stamps.size == 0:
        raise CodaFormatError(f"{path}: no timestamps")
    if not np.isfinite(stamps).all():
        raise CodaFormatError(
            f"{path}: non-finite timestamp at line {int(np.argmin(np.isfinite(stamps))) + 1}"
        )
    steps = np.diff(stamps)
    if (steps <= 0).any():
        k = int(np.flatnonzero(steps <= 0)[0])
        raise CodaFormatError(
            f"{path}: timestamps are not strictly increasing: line {k + 2} ({stamps[k + 1]:.6f}) "
            f"after line {k + 1} ({stamps[k]:.6f}) (frame {k + 1})"
        )
    return stamps


def read_pose_stamps(path: Path) -> np.ndarray:
    """(F,) float64 first column (Unix seconds) of a dense pose file."""
    rows = [
        line.split() for line in read_text(path, None, "poses file").splitlines() if line.strip()
    ]
    return np.array([float(r[0]) for r in rows], dtype=np.float64)


def _read_poses(
    path: Path, expected: int, stamps_path: Path, stamps_s: np.ndarray | None = None
) -> np.ndarray:
    """Pose lines ``ts x y z qw qx qy qz`` -> (F, 4, 4) float64 T_world_from_lidar; with
    ``stamps_s`` the pose times are checked against the frame timestamps, and the robot's
    position and speed for plausibility."""
    if not _present(path):
        raise CodaFormatError(
            f"{path}: poses file is missing (looked in poses/dense_global and poses/dense)", path
        )
    try:
        rows = [
            line.split()
            for line in read_text(path, None, "poses file").splitlines()
            if line.strip()
        ]
    except InputError as exc:
        raise CodaFormatError(str(exc), path) from None
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
            raise CodaFormatError(
                f"{path}: line {k + 1} (frame {k}) is not numeric: {row}"
            ) from None
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
        if stamps_s is not None and abs(values[0] - stamps_s[k]) > POSE_TIME_TOLERANCE_S:
            raise CodaFormatError(
                f"{path}: line {k + 1} (frame {k}): pose time {values[0]:.6f} differs from {stamps_path} line "
                f"{k + 1} ({stamps_s[k]:.6f}) by {values[0] - stamps_s[k]:.3f} s; expected within "
                f"{POSE_TIME_TOLERANCE_S} s (the poses of another recording?)",
                path,
                k,
            )
        if np.max(np.abs(values[1:4])) > MAX_POSITION_M:
            raise CodaFormatError(
                f"{path}: line {k + 1} (frame {k}): position {values[1:4].tolist()} is more than "
                f"{MAX_POSITION_M:g} m from the map origin; expected a campus-scale map frame",
                path,
                k,
            )
        poses[k, :3, :3] = quat_wxyz_to_matrix(values[4:8])
        poses[k, :3, 3] = values[1:4]
        if k and stamps_s is not None:
            step = float(np.linalg.norm(poses[k, :3, 3] - poses[k - 1, :3, 3]))
            dt = float(stamps_s[k] - stamps_s[k - 1])
            if step > MAX_SPEED_MPS * dt:
                raise CodaFormatError(
                    f"{path}: line {k + 1} (frame {k}): the robot moves {step:.3g} m in {dt:.3f} s from line {k} "
                    f"({step / dt:.3g} m/s); expected at most {MAX_SPEED_MPS:g} m/s",
                    path,
                    k,
                )
    return poses


def _read_yaml(path: Path) -> dict:
    try:
        data = yaml.load(read_text(path, None, "calibration file"), Loader=_YamlLoader)
    except InputError as exc:
        raise CodaFormatError(str(exc), path) from None
    except yaml.YAMLError as exc:
        raise CodaFormatError(f"{path}: invalid YAML ({exc})", path) from None
    if not isinstance(data, dict):
        raise CodaFormatError(f"{path}: expected a YAML mapping", path)
    return data


#: libyaml's safe loader where PyYAML has it (the calibration files are parsed at every open)
_YamlLoader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def _yaml_key(data: dict, key: str, path: Path, name: str | None = None):
    if key not in data:
        raise CodaFormatError(f"{path}: calibration key {name or key!r} is missing")
    return data[key]


def _positive_int(data: dict, key: str, path: Path) -> int:
    value = _yaml_key(data, key, path)
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float))
        or value <= 0
        or value != int(value)
    ):
        raise CodaFormatError(
            f"{path}: {key} is {value!r}, expected a positive whole number of pixels"
        )
    return int(value)


def _yaml_matrix(
    data: dict, key: str, shape: tuple[int, int] | None, path: Path, name: str | None = None
) -> np.ndarray:
    name = name or key
    node = _yaml_key(data, key, path, name)
    values = node.get("data") if isinstance(node, dict) else node
    try:
        arr = np.asarray(values, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise CodaFormatError(f"{path}: {name} is not a list of numbers") from None
    if shape is not None:
        if arr.size != shape[0] * shape[1]:
            raise CodaFormatError(
                f"{path}: {name} has {arr.size} values, expected {shape[0]}x{shape[1]}"
            )
        arr = arr.reshape(shape)
    if not np.isfinite(arr).all():
        raise CodaFormatError(f"{path}: {name} has non-finite values")
    return arr


def _read_json(path: Path, where: str | None = None):
    try:
        return json.loads(read_text(path, None, "JSON file"))
    except InputError as exc:
        raise CodaFormatError(str(exc), path) from None
    except json.JSONDecodeError as exc:
        raise CodaFormatError(f"{where or path}: invalid JSON ({exc})", path) from None
