"""What a CODa-layout download holds, read cheaply: the file side of ``mobileocc check-data``.

:func:`inspect_sequence` opens a sequence with the reader (timestamps, poses, calibration, metadata,
a directory listing) and, for every selected frame, looks at file sizes only (``stat``): missing or
truncated sweeps, images, box and terrain-label files. It reads three sweeps in full (first, middle
and last selected frame) for the channel contents (intensity all zero? time unit?) and the
reprojection figures, and one image header per camera. ``deep=True`` reads every sweep, box file,
terrain-label file and image header instead.

Problems are ``(blocking, message)`` pairs: blocking ones stop a run (a missing or truncated file
of a selected frame, an image whose size is not the calibration's, a sequence that cannot be
opened); the others are worth knowing (defaults used, contents that are not measurements).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from storage.sources import CheckProblems
from storage.sources.coda import (
    IMAGE_EXTENSIONS,
    POINTS_PER_SWEEP,
    CodaFormatError,
    CodaSequence,
    frame_number,
    read_boxes,
    read_lidar_raw,
    read_pose_stamps,
    read_semantic,
)

#: sampled sweeps in the fast mode
SAMPLES = 3


@dataclass
class SequenceFacts(CheckProblems):
    """Facts about one sequence of a download (see the module docstring)."""

    sequence: str
    seq: CodaSequence | None = None
    error: str = ""
    lidar_files: int = 0
    missing: dict[str, list[int]] = field(default_factory=dict)  # what -> raw frames missing it
    truncated: list[str] = field(default_factory=list)
    channels: set[int] = field(default_factory=set)
    bbox_files: int = 0
    semantic_files: int = 0
    boxes_skipped: int = 0
    sample_frames: list[int] = field(default_factory=list)
    sample_points: list[np.ndarray] = field(default_factory=list)  # (N, 3) float32 LiDAR frame
    intensity_zero: list[int] = field(
        default_factory=list
    )  # sampled / read frames with all-zero intensity
    time_max_ns: float | None = None  # over the sampled / read sweeps; None: 4-channel files
    image_sizes: dict[str, tuple[int, int]] = field(default_factory=dict)
    pose_stamp_diff_s: float = 0.0
    frames_read: int = 0
    problems: list[tuple[bool, str]] = field(default_factory=list)


def _image(seq: CodaSequence, cam: str, frame: int) -> Path | None:
    for ext in IMAGE_EXTENSIONS:
        p = seq.path(seq.image_source, cam, frame, ext)
        if p.exists():
            return p
    return None


def inspect_sequence(open_sequence, sequence: str, deep: bool = False) -> SequenceFacts:
    """Facts about ``sequence``; ``open_sequence(sequence)`` builds its CodaSequence (the caller's
    config). Never raises for bad data: an unopenable sequence is a blocking problem."""
    from PIL import Image

    facts = SequenceFacts(sequence)
    try:
        seq = open_sequence(sequence)
    except CodaFormatError as exc:
        facts.error = str(exc)
        facts.problem(True, f"cannot be read: {exc}")
        return facts
    facts.seq = seq
    info = seq.info
    frames = list(info.frame_indices)
    facts.lidar_files = len(seq.lidar_frames_on_disk())
    cams = list(info.calibration.cameras)
    bbox_dir = seq.root / "3d_bbox" / "os1" / seq.sequence
    sem_dir = seq.root / "3d_semantic" / "os1" / seq.sequence
    bbox_frames = {frame_number(p) for p in bbox_dir.iterdir()} if bbox_dir.is_dir() else set()
    sem_frames = {frame_number(p) for p in sem_dir.iterdir()} if sem_dir.is_dir() else set()
    whole: list[int] = []
    for f in frames:
        path = seq.lidar_path(f)
        try:
            size = path.stat().st_size
        except FileNotFoundError:
            facts.missing.setdefault(seq.lidar_source, []).append(f)
            continue
        if (
            size == 0
            or size % (POINTS_PER_SWEEP * 4)
            or size // (POINTS_PER_SWEEP * 4) not in (4, 5)
        ):
            facts.truncated.append(f"{path.name}: {size} bytes (frame {f})")
        else:
            facts.channels.add(size // (POINTS_PER_SWEEP * 4))
            whole.append(f)
        for cam in cams:
            if _image(seq, cam, f) is None:
                facts.missing.setdefault(f"{seq.image_source} {cam}", []).append(f)
    facts.bbox_files = sum(f in bbox_frames for f in frames)
    facts.semantic_files = sum(f in sem_frames for f in frames)
    for what, lost in facts.missing.items():
        facts.problem(
            True,
            f"{what}: {len(lost)} of {len(frames)} selected frames have no file "
            f"(first: frame {lost[0]})",
        )
    for msg in facts.truncated[:3]:
        facts.problem(True, f"{seq.lidar_source} sweep truncated or not an OS1-128 sweep: {msg}")
    if len(facts.truncated) > 3:
        facts.problem(True, f"... and {len(facts.truncated) - 3} more truncated sweeps")
    if not frames:
        facts.problem(True, "no frames selected")

    # sweeps: a few in the fast mode, all in the deep one
    if deep:
        picked = whole
    else:
        picked = (
            sorted(
                {
                    whole[i]
                    for i in np.linspace(0, len(whole) - 1, min(SAMPLES, len(whole)))
                    .round()
                    .astype(int)
                }
            )
            if whole
            else []
        )
    times = []
    for f in picked:
        try:
            raw = read_lidar_raw(seq.lidar_path(f), f)
        except CodaFormatError as exc:
            facts.problem(True, str(exc))
            continue
        facts.frames_read += 1
        returns = np.linalg.norm(raw[:, :3], axis=1) > max(seq.min_range_m, 1e-6)
        if returns.any() and not np.any(raw[returns, 3] != 0):
            facts.intensity_zero.append(f)
        if raw.shape[1] == 5:
            times.append(float(raw[:, 4].max()))
        if (
            f in (picked[0], picked[len(picked) // 2], picked[-1])
            and len(facts.sample_points) < SAMPLES
        ):
            facts.sample_frames.append(f)
            facts.sample_points.append(np.ascontiguousarray(raw[returns, :3]))
    facts.time_max_ns = max(times) if times else None
    if facts.intensity_zero:
        facts.problem(
            False,
            f"intensity is 0 for every return in {len(facts.intensity_zero)} of {facts.frames_read} "
            f"read sweeps (first: frame {facts.intensity_zero[0]}): not measurements (the devkit's "
            "3d_comp keeps x y z only); exported intensities would be zeros",
        )
    if times and facts.time_max_ns == 0:
        facts.problem(
            False, "the time channel is 0 everywhere in the read sweeps (no per-point times)"
        )
    elif times and facts.time_max_ns < 1.0:
        facts.problem(
            False,
            f"the time channel peaks at {facts.time_max_ns:.3g}: looks like seconds, "
            "CODa writes nanoseconds (read as ns)",
        )

    # images: one header per camera (all in the deep mode)
    for cam in cams:
        calib = info.calibration.cameras[cam]
        for f in frames if deep else frames[:1]:
            path = _image(seq, cam, f)
            if path is None:
                continue
            try:
                with Image.open(path) as im:
                    size = im.size
            except Exception as exc:
                facts.problem(
                    True, f"{path} (frame {f}): not a readable image ({type(exc).__name__}: {exc})"
                )
                break
            facts.image_sizes.setdefault(cam, size)
            if size != (calib.width, calib.height):
                facts.problem(
                    True,
                    f"{path} (frame {f}): image is {size[0]}x{size[1]}, the calibration says "
                    f"{calib.width}x{calib.height}",
                )
                break

    if deep:
        for f in frames:
            if f in bbox_frames:
                try:
                    facts.boxes_skipped += len(
                        read_boxes(seq.path("3d_bbox", "os1", f, ".json"), f)[1]
                    )
                except CodaFormatError as exc:
                    facts.problem(True, str(exc))
            if f in sem_frames:
                try:
                    read_semantic(seq.path("3d_semantic", "os1", f, ".bin"), f)
                except CodaFormatError as exc:
                    facts.problem(True, str(exc))
        if facts.boxes_skipped:
            facts.problem(
                False,
                f"{facts.boxes_skipped} 3d_bbox boxes are malformed or degenerate and are skipped",
            )

    # poses vs timestamps: the dense poses carry each frame's time in their first column
    pose_path = seq.root / "poses" / "dense_global" / f"{seq.sequence}.txt"
    if not pose_path.exists():
        pose_path = seq.root / "poses" / "dense" / f"{seq.sequence}.txt"
        facts.problem(
            False, f"no poses/dense_global/{seq.sequence}.txt: poses/dense (not globally optimised)"
        )
    stamps = np.loadtxt(seq.root / "timestamps" / f"{seq.sequence}.txt", ndmin=1)
    facts.pose_stamp_diff_s = float(np.max(np.abs(read_pose_stamps(pose_path) - stamps)))
    if facts.pose_stamp_diff_s > 0.005:
        facts.problem(
            False,
            f"pose times differ from the frame timestamps by up to {facts.pose_stamp_diff_s * 1e3:.1f} ms",
        )
    for w in info.warnings:
        facts.problem(False, w)
    return facts
