"""Publication of a sequence: write everything aside, record the intent, then rename into place.

A sequence is written into a hidden staging directory (``OUT/.tmp-*``): the Zarr store by the
fuse / export stages, the table partitions by :func:`stage_table`. :func:`publish_sequence` then

1. lists every file to be published with its size and sha256 (storage.completion),
2. writes the *intent* ``OUT/.publishing/<sequence>.json`` (which staging directory, which
   version, the ``current.json`` to write), fsynced: from here the publication is committed,
3. renames the store to ``occupancy/<sequence>/<version>.zarr`` and each table file onto its
   partition, replaces ``occupancy/<sequence>/current.json`` (``{"version", "files"}``: the file
   list is what the published sequence must hold), removes older versions,
4. removes the intent, then the staging directory.

A kill between 2 and 4 leaves the intent: the next run (and any reader taking the store's read
lock, :func:`reading`) completes the publication from the staging directory before anything else
(:func:`recover_publications`, "roll forward"), so no reader ever works on a mix of an old
version's arrays and a new version's tables. :func:`withdraw_sequence` and :func:`remove_sequence`
go through an intent the same way. :func:`check_publication` compares a published sequence with
its ``current.json`` (``status --verify``); a sequence that does not match is published again.
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

from storage.atomic import atomic_write_bytes, move_into_place, swap_in, temporary_name
from storage.completion import check_files, describe
from storage.layout import (
    CURRENT_FILE,
    OCCUPANCY_DIR,
    PUBLISHING_DIR,
    TABLES_DIR,
    TMP_PREFIX,
    StoreError,
    check_name,
    recorded_path,
    shown,
)
from storage.manifest import read_lock, run_lock, writable_store
from storage.schemas import TABLE_NAMES
from storage.tables import (
    PARTITION_FILE,
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
    """Make a staged sequence visible; returns the published store path (module docstring: the
    steps, and what a kill at any of them leaves). Older versions are removed unless
    ``keep_old_versions``."""
    if not staged.staging_dir.is_dir():
        raise StoreError(f"publish_sequence: staging dir {staged.staging_dir} is gone")
    seq = staged.sequence
    rename = {
        "occupancy.zarr": f"{OCCUPANCY_DIR}/{seq}/{staged.version}.zarr",
        **{
            f"tables/{p.name}": f"{TABLES_DIR}/{p.stem}/sequence={seq}/{PARTITION_FILE}"
            for p in staged.tables_dir.glob("*.parquet")
        },
    }
    files = describe(staged.staging_dir, rename=rename)
    intent = {
        "action": "publish",
        "staging": staged.staging_dir.name,
        "version": staged.version,
        "keep_old_versions": keep_old_versions,
        "current": {"version": staged.version, "files": files},
    }
    _write_intent(staged.root, seq, intent)
    _complete(staged.root, seq, intent)
    return staged.root / OCCUPANCY_DIR / seq / f"{staged.version}.zarr"


def withdraw_sequence(root: str | os.PathLike, sequence: str, error: str, row: dict) -> bool:
    """Take a sequence out of the published dataset because its last run failed: its arrays
    (``occupancy/<seq>/``, ``current.json`` first, so readers stop listing it at once) and its
    frames / instances partitions are removed, and its sequences-table row says ``status``
    "failed" with ``error`` (``row``: the other non-null columns: fingerprint, config_hash,
    code_version). Returns whether anything had been published."""
    check_name("sequence", sequence)
    root = Path(root)
    had = (root / OCCUPANCY_DIR / sequence).exists() or any(
        partition_dir(root, name, sequence).exists() for name in ("frames", "instances")
    )
    failed = {**row, "status": "failed", "error": error, "num_frames": 0}
    intent = {"action": "withdraw", "row": {**failed, "occupancy_version": None}}
    _write_intent(root, sequence, intent)
    _complete(root, sequence, intent)
    return had


def remove_sequence(root: str | os.PathLike, sequence: str) -> bool:
    """Take a sequence out of the dataset entirely (its input is gone: ``--prune``): arrays,
    ``current.json`` and the partitions of every table. Returns whether anything was there."""
    check_name("sequence", sequence)
    root = Path(root)
    had = sequence in published_names(root)
    _write_intent(root, sequence, {"action": "remove"})
    _complete(root, sequence, {"action": "remove"})
    return had


def _intent_path(root: Path, sequence: str) -> Path:
    return Path(root) / PUBLISHING_DIR / f"{sequence}.json"


def _write_intent(root: Path, sequence: str, intent: dict) -> None:
    atomic_write_bytes(
        _intent_path(root, sequence), json.dumps(intent, sort_keys=True).encode(), sync_folder=True
    )


def _remove(path: Path) -> None:
    """Remove a published folder without readers ever seeing half of it: renamed aside (hidden)
    first, then deleted."""
    if not os.path.lexists(path):
        return
    aside = move_into_place(path, temporary_name(path))
    shutil.rmtree(aside, ignore_errors=True)


def _complete(root: Path, sequence: str, intent: dict) -> None:
    """Carry out an intent (again): every step may already have been done by a killed run."""
    root, seq_dir = Path(root), Path(root) / OCCUPANCY_DIR / sequence
    action = intent.get("action")
    if action == "publish":
        staging = root / intent["staging"]  # checked by _check_intent: a .tmp-* name in OUT
        target = seq_dir / f"{intent['version']}.zarr"
        seq_dir.mkdir(parents=True, exist_ok=True)
        store = staging / "occupancy.zarr"
        if store.is_dir():
            # the same version published before is moved aside first (hidden): never a mix
            swap_in(store, target)
        for staged_file in sorted((staging / "tables").glob("*.parquet")):
            publish_partition(root, staged_file.stem, sequence, staged_file)
        current = intent["current"]
        if check_files(root, current["files"]):
            # the staging of a killed run was lost (removed by hand): rather than a mix of
            # versions, the sequence is taken out whole; its export unit publishes it again
            _complete(root, sequence, {"action": "remove"})
            shutil.rmtree(staging, ignore_errors=True)
            return
        atomic_write_bytes(
            seq_dir / CURRENT_FILE,
            json.dumps(current, indent=1, sort_keys=True).encode(),
            sync_folder=True,
        )
        if not intent.get("keep_old_versions"):
            for old in seq_dir.glob("*.zarr"):
                if old != target:
                    _remove(old)
        _intent_path(root, sequence).unlink(missing_ok=True)
        shutil.rmtree(staging, ignore_errors=True)
        return
    if action not in ("withdraw", "remove"):
        raise StoreError(f"{_intent_path(root, sequence)}: unknown publication step {action!r}")
    (seq_dir / CURRENT_FILE).unlink(missing_ok=True)  # readers stop listing it at once
    _remove(seq_dir)
    for name in ("frames", "instances") if action == "withdraw" else TABLE_NAMES:
        _remove(partition_dir(root, name, sequence))
    if action == "withdraw":
        write_partition(root, "sequences", sequence, [intent["row"]])
    _intent_path(root, sequence).unlink(missing_ok=True)


def pending_publications(root: str | os.PathLike) -> list[str]:
    """Sequences whose publication, withdrawal or removal was interrupted (their intent is left)."""
    folder = Path(root) / PUBLISHING_DIR
    if not folder.is_dir():
        return []
    return sorted(p.stem for p in folder.glob("*.json") if not p.name.startswith("."))


def intent_problem(root: str | os.PathLike, sequence: str) -> str:
    """Why the intent ``OUT/.publishing/<sequence>.json`` cannot be carried out ("" when it
    can): unreadable, not JSON, or not an intent this code wrote (:func:`_check_intent`)."""
    try:
        _read_intent(Path(root), sequence)
    except StoreError as exc:
        return str(exc)
    return ""


def _read_intent(root: Path, sequence: str) -> dict:
    path = _intent_path(root, sequence)
    try:
        check_name("sequence", sequence)
        if not sequence.isprintable():
            raise StoreError("its name holds a control character")
        intent = json.loads(path.read_bytes())
        _check_intent(root, intent)
    except (OSError, ValueError) as exc:  # written atomically: only a foreign file is unreadable
        why = exc.strerror if isinstance(exc, OSError) else str(exc)
        raise StoreError(f"{shown(path)}: not a publication intent ({shown(why)})") from None
    return intent


def _check_intent(root: Path, intent: Any) -> None:
    """An intent names only what this module writes: a ``.tmp-*`` staging folder directly in
    OUT, a version usable as a name, file lists of paths inside OUT (storage.layout
    .recorded_path); anything else (a crafted intent naming a folder outside OUT) is refused
    with a ValueError, and nothing it names is touched."""
    if not isinstance(intent, dict):
        raise ValueError("not a JSON object")
    action = intent.get("action")
    if action == "withdraw":
        if not isinstance(intent.get("row"), dict):
            raise ValueError("a withdrawal without its sequences-table row")
        return
    if action == "remove":
        return
    if action != "publish":
        raise ValueError(f"unknown publication step {shown(repr(action))}")
    staging, version, current = intent.get("staging"), intent.get("version"), intent.get("current")
    if not isinstance(staging, str) or not staging.startswith(TMP_PREFIX) or "/" in staging:
        raise ValueError(
            f"its staging folder {shown(repr(staging))} is not a {TMP_PREFIX}* folder in the store"
        )
    recorded_path(root, staging, "the staging folder")
    if not isinstance(version, str):
        raise ValueError(f"its version {shown(repr(version))} is not a name")
    check_name("version", version)
    if (
        not isinstance(current, dict)
        or current.get("version") != version
        or not isinstance(current.get("files"), dict)
    ):
        raise ValueError("its current.json is not a file list of its version")
    for rel in current["files"]:
        recorded_path(root, rel, "a published file")


def _roll_back(root: Path, sequence: str, why: str) -> str:
    """An intent that cannot be carried out: removed; the sequence's published data is kept when
    it is whole (every file its ``current.json`` lists, at its size and content), else taken out
    (its export unit publishes it again). Returns the one line saying so."""
    path = _intent_path(root, sequence)
    seq_dir = root / OCCUPANCY_DIR / sequence
    kept = "no published data"
    if _usable_name(sequence):
        current, problem = _read_current(seq_dir / CURRENT_FILE)
        files = current.get("files") if isinstance(current, dict) else None
        if not problem and isinstance(files, dict):
            try:
                for rel in files:
                    recorded_path(root, rel, "a published file")
                problem = check_files(root, files, deep=True)
            except StoreError as exc:
                problem = str(exc)
        if not problem and not damaged_publication(root, sequence):
            kept = "its published data is whole and kept"
        elif seq_dir.exists() or published_version(root, sequence):
            _complete(root, sequence, {"action": "remove"})
            kept = "its published data was not whole and is taken out (the next run publishes it)"
    path.unlink(missing_ok=True)
    return f"{why}; rolled back: removed, {kept}"


def _usable_name(sequence: str) -> bool:
    try:
        check_name("sequence", sequence)
    except StoreError:
        return False
    return sequence.isprintable()


def recover_publications(
    root: str | os.PathLike, rolled_back: list[str] | None = None
) -> list[str]:
    """Complete every interrupted publication (call it holding the run lock, before the
    temporaries are swept: the staging directories it reads are temporaries); returns them. An
    intent that is not one this code wrote (garbage, a crafted path) is rolled back instead
    (:func:`_roll_back`), one line each appended to ``rolled_back``."""
    done = []
    for sequence in pending_publications(root):
        try:
            intent = _read_intent(Path(root), sequence)
            _complete(Path(root), sequence, intent)
        except (ValueError, TypeError, KeyError) as exc:  # StoreError too; OSError goes up
            line = _roll_back(Path(root), sequence, str(exc))
            if rolled_back is not None:
                rolled_back.append(line)
            continue
        done.append(sequence)
    return done


@contextlib.contextmanager
def reading(root: str | os.PathLike) -> Iterator[None]:
    """Read the published dataset under the store's read lock (shared with other readers, refused
    while a run holds it: storage.manifest.StoreLockedError; none on a read-only store, which no
    run can write). A publication interrupted by a
    killed run is completed first (briefly holding the run lock), so a reader sees whole
    versions only."""
    root = Path(root)
    pending = pending_publications(root)
    if pending and not writable_store(root):
        raise StoreError(
            f"dataset {shown(root)}: the publication of {shown(', '.join(pending))} was "
            "interrupted and the store is read-only, so it cannot be completed here; run "
            "`mobileocc rebuild` where the store is writable"
        )
    if pending:
        with run_lock(root):
            recover_publications(root)
    with read_lock(root):
        yield


def published_version(root: str | os.PathLike, sequence: str) -> str | None:
    """The version ``current.json`` names (None when there is none or it cannot be read)."""
    try:
        current = json.loads((Path(root) / OCCUPANCY_DIR / sequence / CURRENT_FILE).read_bytes())
        version = current.get("version") if isinstance(current, dict) else None
    except (OSError, ValueError):
        return None
    return version if isinstance(version, str) else None


def published_versions(root: str | os.PathLike) -> dict[str, str]:
    """sequence -> version of every sequence readers see (a ``current.json`` naming a version)."""
    occ = Path(root) / OCCUPANCY_DIR
    if not occ.is_dir():
        return {}
    found = {}
    for p in sorted(occ.iterdir()):
        if p.is_dir() and not p.name.startswith((".", "_")):
            version = published_version(root, p.name)
            if version is not None:
                found[p.name] = version
    return found


def published_names(root: str | os.PathLike) -> set[str]:
    """Every sequence with anything in the dataset: arrays, or a partition of any table (a
    withdrawn sequence keeps its sequences-table row)."""
    root = Path(root)
    names = set()
    occ = root / OCCUPANCY_DIR
    if occ.is_dir():
        names |= {p.name for p in occ.iterdir() if not p.name.startswith((".", "_"))}
    for name in TABLE_NAMES:
        base = root / TABLES_DIR / name
        if base.is_dir():
            names |= {p.name.split("=", 1)[1] for p in base.glob("sequence=*") if "=" in p.name}
    return names


def _read_current(path: Path) -> tuple[Any, str]:
    """A sequence's ``current.json`` parsed, and "" or why it cannot be read."""
    try:
        return json.loads(path.read_bytes()), ""
    except FileNotFoundError:
        return None, f"{path} is missing"
    except (OSError, ValueError) as exc:
        return None, f"{path} cannot be read ({exc})"


def check_publication(
    root: str | os.PathLike, sequence: str, version: str, deep: bool = False
) -> str:
    """The first problem of a published sequence ("" when it holds what was published as
    ``version``): an interrupted publication, ``current.json`` missing, unreadable or naming
    another version, or a published file (arrays, table partitions) missing, of another size or
    (``deep``) of other content."""
    root = Path(root)
    if sequence in pending_publications(root):
        garbage = intent_problem(root, sequence)
        if garbage:
            return f"{garbage} (the next run rolls it back)"
        return "its publication was interrupted (the next run completes it)"
    path = root / OCCUPANCY_DIR / sequence / CURRENT_FILE
    current, problem = _read_current(path)
    if problem:
        return problem
    if not isinstance(current, dict) or not isinstance(current.get("files"), dict):
        return f"{path} does not list the published files"
    if current.get("version") != version:
        return f"{path} names version {current.get('version')!r}, the manifest {version!r}"
    return check_files(root, current["files"], deep)


def damaged_publication(root: str | os.PathLike, sequence: str) -> str:
    """The first problem a reader must not go past in a published sequence ("" when none), one
    ``stat`` per file: ``current.json`` missing or unreadable, or a file it lists missing or of
    another size (a ``current.json`` of a store published before file lists: not checked)."""
    path = Path(root) / OCCUPANCY_DIR / sequence / CURRENT_FILE
    current, problem = _read_current(path)
    if problem:
        return problem
    version = current.get("version") if isinstance(current, dict) else None
    if not isinstance(version, str):
        return f"{path} does not name a version"
    if not (path.parent / f"{version}.zarr").is_dir():
        return f"{path} names version {version!r}, which is not there"
    files = current.get("files")
    return check_files(root, files) if isinstance(files, dict) else ""


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
