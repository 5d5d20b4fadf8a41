"""Atomic writes: every file and folder the project writes appears whole or not at all.

A file is written under a hidden temporary name beside its target (``TMP_PREFIX`` of
:mod:`storage.layout`, the target's name and a random suffix, so two writers of the same target
never share a temporary), flushed and fsynced, then renamed onto the target with one
``os.replace``: a reader sees the old file or the new one, never a part. A failure removes the
temporary and leaves the target as it was; a killed process leaves only a ``.tmp-*`` file, which
``storage.manifest.sweep_temporaries`` removes under the output store. ``sync_folder=True`` also
fsyncs the folder after the rename, so the rename itself survives a power cut (the publication
points: ``manifest.json``, ``current.json``).

Folders are published the same way: written in full under a hidden name, then renamed into place
(:func:`move_into_place`), or swapped for the folder already there (:func:`swap_in`).

This module is the only place that renames onto a published name (``os.replace``); a test keeps it
so (tests/test_atomic.py).
"""

from __future__ import annotations

import errno
import os
import shutil
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from storage.layout import TMP_PREFIX


def temporary_name(target: str | os.PathLike) -> Path:
    """A fresh hidden path beside ``target``: ``<folder>/.tmp-<name>-<random>``."""
    target = Path(target)
    return target.with_name(f"{TMP_PREFIX}{target.name}-{uuid.uuid4().hex[:12]}")


def named(exc: OSError, path: str | os.PathLike) -> OSError:
    """The same OSError with the file named (a failed write() does not say which file)."""
    if exc.filename:
        return exc
    return type(exc)(exc.errno, exc.strerror or str(exc), str(path))


def _fsync_path(path: Path, directory: bool = False) -> None:
    fd = os.open(path, os.O_RDONLY | (os.O_DIRECTORY if directory else 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextmanager
def write_atomically(target: str | os.PathLike, sync_folder: bool = False) -> Iterator[Path]:
    """``with write_atomically(path) as tmp: write(tmp)``: the file written to ``tmp`` replaces
    ``path`` (fsynced first) when the block ends without an error; otherwise ``tmp`` is removed
    and ``path`` is untouched. The folder is created where missing. An OSError without a file
    name (a full disk, a file size limit) is raised naming ``path``."""
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_name(target)
    try:
        yield tmp
        _fsync_path(tmp)
        os.replace(tmp, target)
        if sync_folder:
            _fsync_path(target.parent, directory=True)
    except OSError as exc:
        raise named(exc, target) from None
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write_bytes(target: str | os.PathLike, data: bytes, sync_folder: bool = False) -> Path:
    """Write ``data`` to ``target`` atomically (:func:`write_atomically`); returns the path."""
    with write_atomically(target, sync_folder) as tmp, open(tmp, "wb") as fh:
        fh.write(data)
    return Path(target)


def atomic_write_text(target: str | os.PathLike, text: str, sync_folder: bool = False) -> Path:
    """Write ``text`` (UTF-8) to ``target`` atomically; returns the path."""
    return atomic_write_bytes(target, text.encode("utf-8"), sync_folder)


def move_into_place(source: str | os.PathLike, target: str | os.PathLike) -> Path:
    """Rename a finished file (onto any file at ``target``) or folder (onto nothing, or an empty
    folder) with one ``os.replace``; both on one file system. Returns ``target``."""
    os.replace(source, target)
    return Path(target)


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def swap_in(new: str | os.PathLike, target: str | os.PathLike) -> Path:
    """Publish the finished folder ``new`` as ``target``, replacing the folder there: the old one
    is first renamed aside to a hidden name, then ``new`` onto ``target``, then the old one is
    deleted (a kill in between leaves a ``.tmp-*`` folder, never a mix). Returns ``target``."""
    new, target = Path(new), Path(target)
    aside = temporary_name(target) if target.exists() else None
    if aside is not None:
        os.replace(target, aside)
    try:
        os.replace(new, target)
    except OSError:
        if aside is not None:  # put the old one back
            os.replace(aside, target)
        raise
    if aside is not None:
        _remove(aside)
    return target


@contextmanager
def staged_folder(target: str | os.PathLike, replace: bool = True) -> Iterator[Path]:
    """``with staged_folder(final) as tmp: write into tmp``: a hidden folder beside ``final``,
    published as ``final`` when the block ends without an error (removed on an error, or ignored
    after a kill and swept later). replace: swap it in for any folder already at ``final``
    (:func:`swap_in`); False: a folder already there is kept and the new one dropped (key-named
    outputs: same key, same content; also when another writer publishes the same key meanwhile)."""
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_name(target)
    tmp.mkdir()
    try:
        yield tmp
    except BaseException:
        _remove(tmp)
        raise
    try:
        if replace:
            swap_in(tmp, target)
        elif not target.exists():
            move_into_place(tmp, target)
    except OSError:
        if replace or not target.exists():
            raise
        # another writer published the same key meanwhile: keep theirs
    finally:
        if tmp.exists():
            _remove(tmp)


def _mount_point(path: Path) -> Path:
    path = Path(os.path.abspath(path))
    while not os.path.ismount(path) and path != path.parent:
        path = path.parent
    return path


def os_error_line(exc: OSError) -> str:
    """One line for a write that failed: a full disk names the file system (its mount point) and
    what is free there; a read-only one says so; any other error its file and reason."""
    where = exc.filename or ""
    if exc.errno in (errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)):
        place = Path(where or ".")
        while not place.exists() and place != place.parent:
            place = place.parent
        try:
            free = f"{shutil.disk_usage(place).free / 1e6:.1f} MB free"
        except OSError:
            free = "free space unknown"
        return (
            f"no space left on the file system at {_mount_point(place)} ({free}) writing "
            f"{where or 'a file'}; free space there and run the same command again (finished "
            "work is kept)"
        )
    if exc.errno == errno.EROFS:
        return f"{where}: read-only file system; this command cannot write there"
    return f"{where + ': ' if where else ''}{exc.strerror or exc}"
