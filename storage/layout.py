"""Where things are in an output store (``OUT``), and the error every store module raises.

``OUT/occupancy/<sequence>/<version>.zarr`` and ``current.json`` (storage.occupancy_store,
storage.publish), ``OUT/tables/<table>/sequence=<seq>/part.parquet`` (storage.tables); hidden
``.tmp-*`` entries are work in progress, never read.
"""

from __future__ import annotations

import os
from pathlib import Path, PurePosixPath

OCCUPANCY_DIR = "occupancy"
TABLES_DIR = "tables"
CURRENT_FILE = "current.json"
#: ``OUT/.publishing/<sequence>.json``: a publication in progress (storage.publish)
PUBLISHING_DIR = ".publishing"
TMP_PREFIX = ".tmp-"


class StoreError(ValueError):
    """Bad input to the store: wrong shape, dtype, misaligned region, missing store."""


def check_name(kind: str, value: str) -> None:
    """A sequence or version name usable as one path component (raises StoreError)."""
    if not value or value.startswith((".", "_")) or "/" in value or "\\" in value or "=" in value:
        raise StoreError(
            f"invalid {kind} {value!r}: must be non-empty, no '/', '=', leading '.' or '_'"
        )


def shown(value: object) -> str:
    """``value`` as text safe to print on a terminal: every character that is not printable (a
    newline, a tab, an ANSI escape, a byte of a non-UTF-8 file name) shown as its Python escape
    (``\\n``, ``\\x1b``, ``\\udcff``), so a name from a user's data or a store can neither
    forge an output line nor drive the terminal. Every message that prints such a name goes
    through it (the run summary, ``status``, the command-line error lines)."""
    text = str(value)
    if text.isprintable():
        return text
    return "".join(
        c if c.isprintable() else c.encode("unicode_escape", "backslashreplace").decode("ascii")
        for c in text
    )


def recorded_path(root: str | os.PathLike, rel: object, what: str, links: bool = True) -> Path:
    """``root / rel`` for a path recorded in a file of the store (a publication intent, a
    completion record, a manifest row, a cache): nothing written in OUT is trusted to name a
    path, so ``rel`` must be a non-empty relative POSIX path with no ``..`` component and no
    symbolic link on the way (whoever can write OUT must not make a run read or remove anything
    outside it). Raises StoreError naming ``what`` and the path (escaped) otherwise. ``links``
    False: the text alone is checked, no ``lstat`` per component (file lists checked on every
    plan: a store's own files; nothing is removed through them)."""
    text = rel if isinstance(rel, str) else None
    bad = (
        "is not a path"
        if not text
        else "is absolute"
        if text.startswith("/") or "\\" in text or PurePosixPath(text).is_absolute()
        else "leaves the store (..)"
        if ".." in PurePosixPath(text).parts
        else "holds a control character"
        if not text.isprintable()
        else ""
    )
    if bad:
        raise StoreError(f"{what}: the recorded path {shown(repr(rel))} {bad}; refused")
    root = Path(root)
    if not links:
        return root / text
    path = root
    for part in PurePosixPath(text).parts:
        path = path / part
        if path.is_symlink():
            raise StoreError(
                f"{what}: the recorded path {shown(text)} goes through the symbolic link "
                f"{shown(path)}; refused"
            )
    return path
