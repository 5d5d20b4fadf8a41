"""Sequence sources: what a stage needs of a sequence, behind one protocol, whatever holds it.

Two implementations: the CODa raw layout (:mod:`storage.sources.coda`) and robot logs, ROS 1 /
ROS 2 bags and MCAP (:mod:`storage.sources.log`). Nothing outside those packages knows a layout:
stages, check-data, evaluate, export and the planner read a sequence through
:class:`SequenceSource` and a dataset root through the source's kind (flows/pipeline/inputs.py
``Source`` / ``LogSource``: ``sequence_ids``, ``layout``, ``open``).

Frames, units and arrays are those of :mod:`tasks.conventions`; the data model (SequenceInfo,
Frame, Calibration) is :mod:`storage.sequence_data`.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Protocol

import numpy as np

from storage.sequence_data import Frame, SequenceInfo


class SequenceSource(Protocol):
    """One sequence, opened. Cheap to open (no sweep read); frames on demand.

    ``kind``: "coda" or "log". ``sequence``: its name (a CODa id, a log's stem). ``root``: the
    folder whose ``gt/{sequence}/`` holds the simulator's ground truth, if any. ``info``: frame
    indices (raw frame numbers, ascending) and stamps, calibration (K / P / R,
    T_cam_from_lidar, T_base_from_lidar), poses T_world_from_lidar per selected frame, lighting,
    the input files (for the content fingerprint), warnings.
    """

    kind: str
    sequence: str
    root: Path
    info: SequenceInfo

    def __len__(self) -> int: ...

    def position(self, raw_frame: int) -> int:
        """The position in ``info.frame_indices`` of a raw frame (ValueError if not selected)."""
        ...

    def frame(self, i: int) -> Frame:
        """The i-th selected frame: its sweep decoded (points, intensity, per-point time), its
        pose, its labels where the source has any. An InputError naming the file and the frame
        when its input is bad (the frame can fail alone)."""
        ...

    def frames(self) -> Iterator[Frame]: ...

    def image(self, camera: str, raw_frame: int) -> np.ndarray:
        """(H, W, 3) uint8 RGB of ``camera`` at a raw frame, in the pinhole of its calibration
        (``info.calibration.cameras[camera]``), its size checked."""
        ...

    def check_images(self, raw_frame: int) -> None:
        """Decode every camera's image of a raw frame (InputError when one is bad)."""
        ...

    def source_paths(self, raw_frame: int) -> dict[str, str | None]:
        """Where a frame's raw data are, for the frames table: ``lidar``, ``cam0``, ``cam1``
        (relative to the dataset root; a log's as ``LOG#TOPIC@INDEX``)."""
        ...


class SelectedFrames:
    """The frame-level part of :class:`SequenceSource` common to every source: the selected
    frames' count, a raw frame's position among them, and all frames in order (its ``frame``)."""

    sequence: str
    info: SequenceInfo

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
        raise NotImplementedError

    def frames(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self.frame(i)


class CheckProblems:
    """What a source's check found (``problems``: (blocking, message) pairs, declared by each
    facts class)."""

    problems: list[tuple[bool, str]]

    def problem(self, blocking: bool, message: str) -> None:
        self.problems.append((blocking, message))

    @property
    def blocking(self) -> bool:
        return any(b for b, _ in self.problems)


def source_relative(path: str | os.PathLike, source_root: str | os.PathLike) -> str:
    """``path`` (a source file under ``source_root``) as a POSIX path relative to ``source_root``:
    what the frames table stores, so the dataset reads the same wherever the raw data is mounted."""
    p, root = Path(path), Path(source_root)
    try:
        return p.relative_to(root).as_posix()
    except ValueError:
        try:
            return p.resolve().relative_to(root.resolve()).as_posix()
        except ValueError:
            raise ValueError(f"source file {p} is not under the dataset root {root}") from None
