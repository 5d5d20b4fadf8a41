"""The CODa raw layout: where a sequence's files are, the sequences of a root, the reader's errors.

Layout (ut-amrl/coda-devkit, docs/DATA_REPORT.md)::

    {root}/{modality}/{sensor}/{SEQ}/{modality}_{sensor}_{SEQ}_{FRAME}.{ext}
    {root}/calibrations/{SEQ}/calib_*.yaml
    {root}/poses/dense_global/{SEQ}.txt   (fallback: poses/dense/{SEQ}.txt)
    {root}/timestamps/{SEQ}.txt           {root}/metadata/{SEQ}.json

Every error is a :class:`CodaFormatError` (a :class:`storage.files.InputError`, a ValueError);
those of one frame's files are :class:`CodaFrameError`, which carries the path and the frame, so
a caller can fail that frame and go on.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from storage.files import InputError, where
from tasks.bounds import MAX_POSE_SPEED_M_S, MAX_POSITION_M, ROTATION_TOLERANCE  # noqa: F401 - re-exported

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
#: plausibility bounds of poses and rotations: one home for every source, tasks/bounds.py
MAX_SPEED_MPS = MAX_POSE_SPEED_M_S
#: version of what opening a sequence checks and returns: a fingerprint memo made by another
#: version is not used (planning opens the sequence again); bump when the checks change
#: (3: sweeps beyond MAX_POINT_COORDINATE_M or all zeros, calibration translations bounded)
READER_VERSION = "3"
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
