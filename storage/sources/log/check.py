"""What a robot log holds, read cheaply: the log side of ``mobileocc check-data``.

:func:`inspect_log` opens a log as a sequence (the index pass: every topic's messages counted,
sensor headers read; LiDAR-odometry poses are not computed here), then decodes three sweeps
(first, middle and last selected frame) for the point layout and the reprojection figures, and
one image per camera. ``deep=True`` decodes every selected sweep and image instead.

Problems are ``(blocking, message)`` pairs as for the CODa layout (storage.sources.coda.check): a log
that cannot be opened as a sequence, or a sweep / image that cannot be decoded, blocks a run;
frames left out (no image within the offset, no pose), defaults used, intensity all zero are
worth knowing.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from storage.files import InputError
from storage.sources import CheckProblems
from storage.sources.log.reader import LogFacts, LogSequence

#: sampled sweeps in the fast mode
SAMPLES = 3


@dataclass
class LogCheckFacts(CheckProblems):
    """Facts about one log (see the module docstring)."""

    sequence: str
    seq: LogSequence | None = None
    error: str = ""
    facts: LogFacts | None = None
    sample_frames: list[int] = field(default_factory=list)
    sample_points: list[np.ndarray] = field(default_factory=list)  # (N, 3) float32 LiDAR frame
    intensity_zero: list[int] = field(default_factory=list)
    frames_read: int = 0
    images_read: int = 0
    problems: list[tuple[bool, str]] = field(default_factory=list)


def inspect_log(open_sequence, sequence: str, deep: bool = False) -> LogCheckFacts:
    """Facts about ``sequence``; ``open_sequence(sequence)`` builds its LogSequence (the caller's
    config, without LiDAR-odometry poses). Never raises for bad data."""
    out = LogCheckFacts(sequence)
    try:
        seq = open_sequence(sequence)
    except InputError as exc:
        out.error = str(exc)
        out.problem(True, f"cannot be read: {exc}")
        return out
    out.seq = seq
    out.facts = seq.facts()
    frames = list(seq.info.frame_indices)
    picks = frames if deep else sorted({frames[0], frames[len(frames) // 2], frames[-1]})
    out.sample_frames = picks
    for raw in picks:
        try:
            cloud = seq.frame(seq.position(raw))
        except InputError as exc:
            out.problem(True, str(exc))
            continue
        out.frames_read += 1
        out.sample_points.append(cloud.points_lidar)
        if not cloud.intensity_present:
            out.intensity_zero.append(raw)
    for raw in picks if deep else picks[:1]:
        try:
            seq.check_images(raw)
            out.images_read += len(seq.info.calibration.cameras)
        except InputError as exc:
            out.problem(True, str(exc))
    for w in seq.info.warnings:
        out.problem(False, w)
    if out.intensity_zero:
        out.problem(
            False,
            f"intensity is 0 in every point of {len(out.intensity_zero)} of {out.frames_read} "
            "sweeps read (no intensity / reflectivity / signal field, or not measured)",
        )
    missing = [c for c in ("cam0", "cam1") if c not in seq.info.calibration.cameras]
    if missing:
        out.problem(False, f"no {' / '.join(missing)} in the log (only cam0 is required)")
    return out
