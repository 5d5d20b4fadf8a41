"""Reader for the CODa raw layout (UT Campus Object Dataset), real or synthetic: the CODa
sequence source (storage.sources.SequenceSource).

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
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from storage.files import InputError, open_regular, read_bytes, read_text, regular_stat
from storage.sequence_data import Box3D, Calibration, Frame, SequenceInfo
from storage.sources import SelectedFrames
from storage.sources.coda.calibration import read_calibration
from storage.sources.coda.layout import (
    COLUMNS_PER_BEAM,
    FRAME_SELECTIONS,
    IMAGE_EXTENSIONS,
    IMAGE_SOURCES,
    LIDAR_SOURCES,
    MAX_POSITION_M,
    MAX_SPEED_MPS,
    METADATA_TASKS,
    NIGHT_WORDS,
    NS_PER_S,
    POINTS_PER_SWEEP,
    POSE_TIME_TOLERANCE_S,
    CodaFormatError,
    CodaFrameError,
    _frame_error,
    _present,
    _where,
    frame_number,
    list_sequences,
    sequence_folders,
    stride_frames,
)
from tasks.bounds import sweep_problem
from tasks.poses.rotations import quat_wxyz_to_matrix


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
    problem = sweep_problem(raw[:, :3])  # tasks/bounds.py
    if problem:
        raise CodaFrameError(f"{_where(path, frame)}: implausible sweep: {problem}", path, frame)
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


def box_rotation(rpy: np.ndarray) -> np.ndarray:
    """CODa box angles (roll, pitch, yaw) -> (3, 3) rotation Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


class CodaSequence(SelectedFrames):
    """The CODa sequence source (storage.sources.SequenceSource). One sequence of a CODa-layout root. Cheap to build (no sweep is read); frames on demand.

    frame_stride: keep a frame every k raw frames (2 for 5 Hz). lidar_source: ``3d_comp`` (what
    the downloads ship for os1) or ``3d_raw``; image_source: ``2d_rect`` or ``2d_raw``. frames:
    ``files`` (frames whose sweep exists) or ``metadata`` (frames named by the metadata lists).
    lighting: "day" / "night" for this sequence (the config's), None = the metadata's ``lighting``.
    lidar_height_m: used where ``calib_os1_to_base.yaml`` is missing (T_base_from_lidar = a pure
    lift of that height, with a warning in ``info.warnings``); None = that file is required.
    """

    kind = "coda"

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
        """(channels, file) of the sequence's sweeps: the channel count most of the selected
        sweeps' sizes give (sizes only), and the first sweep of that count. A majority, not the
        first sweep: a first sweep cut to exactly the 4-channel size must be the frame named,
        not every good 5-channel frame after it (issue 41). None when no sweep has a whole
        4- or 5-channel size (each frame then fails alone)."""
        found: dict[int, list[Path]] = {}
        for f in frames:
            path = self.lidar_path(f)
            try:
                channels = _channels_of_size(regular_stat(path, f).st_size)
            except InputError:
                continue
            if channels is not None:
                found.setdefault(channels, []).append(path)
        if not found:
            return None
        # most sweeps; a tie goes to 5 channels (CODa's 3d_raw), a cut never adds a channel
        channels = max(found, key=lambda c: (len(found[c]), c))
        return channels, found[channels][0]

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
        return read_calibration(
            self.root / "calibrations" / self.sequence,
            self.cameras,
            self.image_source,
            self.lidar_height_m,
            warnings,
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
            point_index=sweep.index,
        )

    def image(self, camera: str, raw_frame: int) -> np.ndarray:
        """(H, W, 3) uint8 RGB of ``camera``'s image at a raw frame, its size checked against the
        calibration (storage.images.read_rgb)."""
        from storage.images import read_rgb

        cam = self.info.calibration.cameras[camera]
        return read_rgb(self.image_path(camera, raw_frame), (cam.width, cam.height))

    def source_paths(self, raw_frame: int) -> dict[str, str | None]:
        """The frame's sweep and images relative to the root (cam0: "" and cam1: None where the
        sequence has no such camera)."""
        from storage.sources import source_relative

        cams = self.info.calibration.cameras
        return {
            "lidar": source_relative(self.lidar_path(raw_frame), self.root),
            "cam0": source_relative(self.image_path("cam0", raw_frame), self.root)
            if "cam0" in cams
            else "",
            "cam1": source_relative(self.image_path("cam1", raw_frame), self.root)
            if "cam1" in cams
            else None,
        }

    def check_images(self, raw_frame: int) -> None:
        """Decode every camera's image of a raw frame and check its size against the calibration
        (CodaFrameError naming the file and frame otherwise). Header checks cannot see a corrupt
        or cut image; a stage that hands images on (detect, for the exports) calls this."""
        for name, cam in self.info.calibration.cameras.items():
            path = self.image_path(name, raw_frame)
            decode_image(path, raw_frame, (cam.width, cam.height), self.sequence)


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


#: the EXIF tag of the orientation (1: as stored)
EXIF_ORIENTATION = 0x0112
#: more pixels than this in an image header is refused before decoding: Pillow's own default
#: limit, kept here because other libraries (the nuScenes devkit) switch Pillow's off process-wide
MAX_IMAGE_PIXELS = 2 * 89_478_485


def decode_image(
    path: Path,
    frame: int | None,
    expect_size: tuple[int, int] | None = None,
    sequence: str | None = None,
) -> None:
    """Decode an image fully (a corrupt or cut file fails here) and check its size, from the
    header before decoding (a header claiming 60000 x 60000 px is never decoded). An EXIF
    orientation other than "as stored" is refused: viewers and OpenCV turn such an image, our
    readers take the stored pixels, and which of the two the calibration fits cannot be told."""
    from PIL import Image, UnidentifiedImageError

    def fail(message: str) -> CodaFrameError:
        return CodaFrameError(f"{_where(path, frame)}: {message}", path, frame, sequence)

    try:
        with open_regular(path, frame, "image") as fh, Image.open(fh) as im:
            size = (int(im.size[0]), int(im.size[1]))
            if size[0] * size[1] > MAX_IMAGE_PIXELS:
                raise fail(
                    f"image header claims an implausible size ({size[0]} x {size[1]} px, more "
                    f"than {MAX_IMAGE_PIXELS} pixels; never decoded)"
                    + (
                        f"; the camera calibration says {expect_size[0]} x {expect_size[1]}"
                        if expect_size
                        else ""
                    )
                )
            if expect_size is not None and size != tuple(expect_size):
                raise fail(
                    f"image is {size[0]} x {size[1]} px, the camera calibration says "
                    f"{expect_size[0]} x {expect_size[1]}"
                )
            orientation = im.getexif().get(EXIF_ORIENTATION, 1)
            if orientation != 1:
                raise fail(
                    f"image has EXIF orientation {orientation} (stored rotated or mirrored; "
                    "viewers turn it, the pipeline reads the stored pixels): write it without "
                    "the orientation tag, as the camera stored it"
                )
            im.load()
    except CodaFrameError:
        raise
    except InputError as exc:
        raise _frame_error(exc, frame) from None
    except Image.DecompressionBombError as exc:  # raised by the header alone: nothing decoded
        expected = f"; the camera calibration says {expect_size[0]} x {expect_size[1]}"
        raise fail(
            f"image header claims an implausible size ({exc}){expected if expect_size else ''}"
        ) from None
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as exc:
        raise fail(f"image cannot be decoded ({exc})") from None


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


def _read_json(path: Path, where: str | None = None):
    try:
        return json.loads(read_text(path, None, "JSON file"))
    except InputError as exc:
        raise CodaFormatError(str(exc), path) from None
    except json.JSONDecodeError as exc:
        raise CodaFormatError(f"{where or path}: invalid JSON ({exc})", path) from None
