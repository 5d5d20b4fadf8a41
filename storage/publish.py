"""Publication of a sequence: write everything aside, then make it visible by renames.

A sequence is written into a hidden staging directory (``OUT/.tmp-*``): the Zarr store by the
fuse / export stages, the table partitions by :func:`stage_table`. :func:`publish_sequence` renames
the store into ``occupancy/<sequence>/<version>.zarr``, each partition onto its place, and last
replaces ``occupancy/<sequence>/current.json``, so readers see the old version or the new one,
never a mix. :func:`sequence_writer` wraps this (publish on success, discard on error).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from storage.atomic import atomic_write_bytes, swap_in, temporary_name
from storage.layout import (
    CURRENT_FILE,
    OCCUPANCY_DIR,
    TMP_PREFIX,
    StoreError,
    check_name,
)
from storage.tables import (
    partition_dir,
    publish_partition,
    to_table,
    write_partition,
    write_table_file,
)


@dataclass(frozen=True)
class StagedSequence:
    """A sequence being written: everything lives under ``staging_dir`` until published.

    store_path: the Zarr store workers write to. tables_dir: staged Parquet files
    (``<table>.parquet``), see storage.tables.stage_table.
    """

    root: Path
    sequence: str
    version: str
    staging_dir: Path
    store_path: Path = field(init=False)
    tables_dir: Path = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "store_path", self.staging_dir / "occupancy.zarr")
        object.__setattr__(self, "tables_dir", self.staging_dir / "tables")


def stage_sequence(root: str | os.PathLike, sequence: str, version: str) -> StagedSequence:
    """Make a hidden staging directory ``root/.tmp-<sequence>-<version>-<uuid>`` for one write."""
    check_name("sequence", sequence)
    check_name("version", version)
    root = Path(root)
    staging = temporary_name(root / f"{sequence}-{version}")
    staging.mkdir(parents=True)
    (staging / "tables").mkdir()
    return StagedSequence(root, sequence, version, staging)


def publish_sequence(staged: StagedSequence, keep_old_versions: bool = False) -> Path:
    """Make a staged sequence visible; returns the published store path.

    Order: the store directory is renamed to ``occupancy/<seq>/<version>.zarr``; each staged
    table file replaces its partition file (one atomic rename each); finally ``current.json``
    is replaced to point at the new version. Until that last rename, readers keep seeing the
    previous version's arrays. Older versions are removed unless ``keep_old_versions``.
    """
    if not staged.staging_dir.is_dir():
        raise StoreError(f"publish_sequence: staging dir {staged.staging_dir} is gone")
    seq_dir = staged.root / OCCUPANCY_DIR / staged.sequence
    seq_dir.mkdir(parents=True, exist_ok=True)
    target = seq_dir / f"{staged.version}.zarr"
    if staged.store_path.exists():
        # the same version published before is moved aside first (hidden): never a mix of the two
        swap_in(staged.store_path, target)
    for staged_file in sorted(staged.tables_dir.glob("*.parquet")):
        publish_partition(staged.root, staged_file.stem, staged.sequence, staged_file)
    if target.exists():
        atomic_write_bytes(
            seq_dir / CURRENT_FILE,
            json.dumps({"version": staged.version}, indent=1, sort_keys=True).encode(),
            sync_folder=True,
        )
    if not keep_old_versions:
        for old in seq_dir.glob("*.zarr"):
            if old != target and target.exists():
                shutil.rmtree(old, ignore_errors=True)
    shutil.rmtree(staged.staging_dir, ignore_errors=True)
    return target


def withdraw_sequence(root: str | os.PathLike, sequence: str, error: str, row: dict) -> bool:
    """Take a sequence out of the published dataset because its last run failed: its arrays
    (``occupancy/<seq>/``, ``current.json`` first, so readers stop listing it at once) and its
    frames / instances partitions are removed, and its sequences-table row says ``status``
    "failed" with ``error`` (``row``: the other non-null columns: fingerprint, config_hash,
    code_version). Returns whether anything had been published."""
    check_name("sequence", sequence)
    root = Path(root)
    seq_dir = root / OCCUPANCY_DIR / sequence
    had = (seq_dir / CURRENT_FILE).exists()
    (seq_dir / CURRENT_FILE).unlink(missing_ok=True)
    shutil.rmtree(seq_dir, ignore_errors=True)
    for name in ("frames", "instances"):
        part = partition_dir(root, name, sequence)
        had |= part.exists()
        shutil.rmtree(part, ignore_errors=True)
    write_partition(
        root,
        "sequences",
        sequence,
        [{**row, "status": "failed", "error": error, "num_frames": 0, "occupancy_version": None}],
    )
    return had


def discard(staged: StagedSequence | str | os.PathLike) -> None:
    """Remove a staging directory (a failed or abandoned write); published data is untouched."""
    path = staged.staging_dir if isinstance(staged, StagedSequence) else Path(staged)
    if not path.name.startswith(TMP_PREFIX):
        raise StoreError(
            f"discard: {path} is not a staging directory (name must start {TMP_PREFIX!r})"
        )
    shutil.rmtree(path, ignore_errors=True)


@contextlib.contextmanager
def sequence_writer(
    root: str | os.PathLike, sequence: str, version: str
) -> Iterator[StagedSequence]:
    """``with sequence_writer(out, seq, key) as staged: ...`` publishes on success, discards on error."""
    staged = stage_sequence(root, sequence, version)
    try:
        yield staged
    except BaseException:
        discard(staged)
        raise
    publish_sequence(staged)


def stage_store(staged: StagedSequence, store: Path) -> None:
    """Put a finished Zarr store (the fuse stage's) into a staged sequence: its files hard-linked
    (copied where a link is refused, e.g. across file systems)."""

    def link(a, b):
        try:
            os.link(a, b)
        except OSError:
            shutil.copy2(a, b)

    shutil.copytree(store, staged.store_path, copy_function=link, dirs_exist_ok=True)


def stage_table(staged: StagedSequence, name: str, data: Any) -> Path:
    """Write a table partition into a staged sequence; it goes live with publish_sequence."""
    partition_dir(staged.root, name, staged.sequence)  # validates the name
    path = staged.tables_dir / f"{name}.parquet"
    write_table_file(to_table(name, data), path)
    return path
