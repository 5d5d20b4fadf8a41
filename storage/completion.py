"""Completion records: what a finished unit wrote, so that "done" can be checked, not assumed.

A stage writes its products into a hidden staging folder; when the stage has returned, the runner
writes ``complete.json`` into that folder **last** (:func:`write_record`): every other file in the
folder with its size and sha256, plus the stage, sequence and key. The folder is then renamed into
its key-named place. A unit's output is usable only while :func:`check_record` finds the record and
every file it lists at its recorded size (``deep``: with its recorded content hash too). A folder
without a record (a run killed mid-way, a stage of an older version) or with a missing, truncated
or (deep) rewritten file is a cache miss: the unit runs again, never fails its sequence for it.

The record holds only sizes and content hashes, so the same products give the same bytes (a record
is part of the unit's output and byte-identical across runs and machines). The same file list
describes a published sequence (``occupancy/<seq>/current.json``, storage.publish).

Cost: writing a record reads the folder's files once more (right after they were written, from
the page cache); the quick check is one ``stat`` per file; the deep check reads every file.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable, Mapping
from pathlib import Path

from storage.atomic import atomic_write_bytes
from storage.layout import TMP_PREFIX, StoreError, recorded_path

RECORD = "complete.json"
RECORD_VERSION = 1

#: relative path (POSIX) -> [size in bytes, sha256 hex]
FileList = dict[str, list]


def file_sha256(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _walk(folder: Path, record: str = RECORD) -> Iterable[Path]:
    """Every regular file under ``folder`` (sorted; temporaries and the record itself left out)."""
    for dirpath, dirnames, filenames in os.walk(folder):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith(TMP_PREFIX))
        for name in sorted(filenames):
            if name.startswith(TMP_PREFIX) or (name == record and Path(dirpath) == folder):
                continue
            yield Path(dirpath) / name


def describe(
    base: str | os.PathLike,
    files: Iterable[str | os.PathLike] | None = None,
    rename: Mapping[str, str] | None = None,
    record: str = RECORD,
) -> FileList:
    """The file list of ``files`` (default: every file under ``base``), keyed by their paths
    relative to ``base`` (POSIX separators); ``rename``: a prefix of those paths -> the prefix
    they will have once published (a staged file listed under its final name)."""
    base = Path(base)
    out: FileList = {}
    for path in _walk(base, record) if files is None else (Path(f) for f in files):
        rel = Path(path).relative_to(base).as_posix()
        for old, new in (rename or {}).items():
            if rel == old or rel.startswith(old.rstrip("/") + "/"):
                rel = new + rel[len(old) :]
                break
        out[rel] = [os.stat(path).st_size, file_sha256(path)]
    return dict(sorted(out.items()))


def write_record(folder: str | os.PathLike, name: str = RECORD, **about: str) -> FileList:
    """Write ``folder/complete.json`` (or ``name``) listing every file in ``folder`` (call it
    last, when nothing else will be written there); ``about``: stage, sequence, key. Returns the
    file list."""
    folder = Path(folder)
    files = describe(folder, record=name)
    body = {"version": RECORD_VERSION, **about, "files": files}
    atomic_write_bytes(folder / name, json.dumps(body, sort_keys=True, indent=1).encode())
    return files


def read_record(folder: str | os.PathLike, name: str = RECORD) -> dict:
    """The record of ``folder``; ValueError naming the file when it is missing or unreadable."""
    path = Path(folder) / name
    try:
        body = json.loads(path.read_bytes())
    except FileNotFoundError:
        raise ValueError(f"{path} is missing (its writer did not finish)") from None
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path} cannot be read ({exc})") from None
    if (
        not isinstance(body, dict)
        or body.get("version") != RECORD_VERSION
        or not isinstance(body.get("files"), dict)
    ):
        raise ValueError(f"{path} is not a completion record of version {RECORD_VERSION}")
    return body


def check_files(base: str | os.PathLike, files: Mapping[str, list], deep: bool = False) -> str:
    """The first problem of a file list under ``base`` ("" when every file is there at its size,
    and with ``deep`` its content hash): a missing file, another size, other content, or a path
    that is absolute or leaves ``base`` (storage.layout.recorded_path)."""
    base = Path(base)
    for rel, entry in files.items():
        try:  # a record names paths inside its folder only: never read anything outside
            path = recorded_path(base, rel, f"the file list of {base}", links=False)
        except StoreError as exc:
            return str(exc)
        try:
            size, digest = int(entry[0]), str(entry[1])
        except (TypeError, ValueError, IndexError):
            return f"the record's entry for {path} is malformed"
        try:
            st = os.stat(path)
        except FileNotFoundError:
            return f"{path} is missing"
        except OSError as exc:
            return f"{path} cannot be read ({exc.strerror or exc})"
        if st.st_size != size:
            return f"{path} is {st.st_size} bytes, {size} were written"
        if deep:
            try:
                actual = file_sha256(path)
            except OSError as exc:
                return f"{path} cannot be read ({exc.strerror or exc})"
            if actual != digest:
                return f"{path} does not hold what was written (sha256 differs)"
    return ""


def check_record(folder: str | os.PathLike, deep: bool = False, name: str = RECORD) -> str:
    """The first problem of a unit's output folder ("" when it is whole): no folder, no record,
    or a listed file missing, of another size or (``deep``) of other content."""
    folder = Path(folder)
    if not folder.is_dir():
        return f"{folder} is missing"
    try:
        body = read_record(folder, name)
    except ValueError as exc:
        return str(exc)
    return check_files(folder, body["files"], deep)
