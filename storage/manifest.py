"""The stage cache: content fingerprints, stage keys, key-named outputs, the manifest, the run lock.

The manifest (``OUT/manifest.json``) is the source of truth of what was processed: one row per
(sequence, stage) with the stage key, where the output is, the status and the error. During a run
every finished unit is appended as one JSON line to ``OUT/manifest.journal`` (flushed and fsynced:
a killed run loses at most the units in flight); :meth:`Manifest.save` compacts the rows into
``manifest.json`` (write aside, fsync, rename) and removes the journal, and :meth:`Manifest.load`
replays a journal left by a killed run. Appending is O(1) per unit, where rewriting the whole
manifest after each unit was O(units) (O(units^2) per run: measured in flows/bench/planning.py).
A stage is fresh when its row is ``done``, its key equals the key computed now, and its output
still exists; otherwise it runs again (and so does everything downstream, whose keys include the
upstream keys).

Keys (prior art: Bazel action keys, Dagster code versions, DVC content hashes)::

    fingerprint(sequence) = H(sorted (relative path, content hash) of its input files)
    key(sequence, stage)  = H(stage, stage code version, the config slice the stage reads,
                              fingerprint for the first stage / upstream keys after it)

Content hashes are memoised per sequence in ``OUT/.cache/sequences/<seq>.json`` by (size,
mtime_ns, inode); that file also keeps a *stat signature* of every entry of the sequence's layout
folders (name, size, mtime_ns, inode, type). While the signature is unchanged, planning takes the
fingerprint from the memo and reads no byte of the sequence (not even its calibration): a file
rewritten in place with the same size within the file system's mtime resolution, or restored with
its old mtime by a tool, is not noticed. ``--verify`` (``FingerprintCache(verify=True)``) reads
and hashes every file instead.
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import os
import shutil
import socket
import stat
import threading
import time
import uuid
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from storage.atomic import atomic_write_bytes, named
from storage.files import InputError, open_regular
from storage.layout import TMP_PREFIX, shown

MANIFEST = "manifest.json"
JOURNAL = "manifest.journal"
MANIFEST_VERSION = 1


def _hash_bytes(*parts: bytes) -> str:
    h = hashlib.sha256()
    for part in parts:
        h.update(len(part).to_bytes(8, "little"))
        h.update(part)
    return h.hexdigest()


def canonical_json(value: Any) -> bytes:
    return json.dumps(value, sort_keys=True, separators=(",", ":"), default=str).encode()


class FileHasher:
    """sha256 of file contents, memoised by (size, mtime_ns, inode).

    memo: relative path -> [size, mtime_ns, inode, sha256] (a sequence's part of the fingerprint
    cache); verify: read and hash every file whatever the memo says. Files with the same
    (device, inode, size, mtime) are hashed once per hasher (hard links). Only regular files are
    read (storage.files); anything else is an InputError naming the file. ``bytes_hashed`` and
    ``seconds`` say what hashing cost.
    """

    def __init__(self, memo: dict | None = None, verify: bool = False):
        self.memo: dict[str, list] = memo if memo is not None else {}
        self.verify = verify
        self._by_inode: dict[tuple, str] = {}
        self.used: set[str] = set()  # memo keys asked for (what the memo keeps)
        self.hashed = 0
        self.bytes_hashed = 0
        self.seconds = 0.0

    def __call__(self, path: Path, rel: str | None = None) -> str:
        path = Path(path)
        key = rel if rel is not None else os.path.abspath(path)
        self.used.add(key)
        t0 = time.perf_counter()
        with open_regular(path, None, "input file") as fh:
            st = os.fstat(fh.fileno())
            stamp = [st.st_size, st.st_mtime_ns, st.st_ino]
            hit = self.memo.get(key)
            if not self.verify and hit is not None and hit[:3] == stamp:
                return hit[3]
            ident = (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)
            digest = self._by_inode.get(ident)
            if digest is None:
                h = hashlib.sha256()
                try:
                    for block in iter(lambda: fh.read(1 << 20), b""):
                        h.update(block)
                except OSError as exc:
                    raise InputError(
                        f"{path}: cannot read the input file: {exc.strerror or exc}", path
                    ) from None
                digest = h.hexdigest()
                self._by_inode[ident] = digest
                self.hashed += 1
                self.bytes_hashed += st.st_size
                self.seconds += time.perf_counter() - t0
        self.memo[key] = stamp + [digest]
        return digest

    def share_inodes(self, other: FileHasher) -> FileHasher:
        """Use ``other``'s (device, inode) table and counters' home: one table per plan."""
        self._by_inode = other._by_inode
        return self


def _relative(root: str, path: Path) -> str:
    ap = os.path.abspath(path)
    return ap[len(root) + 1 :] if ap.startswith(root + os.sep) else ap


def sequence_fingerprint(root: Path, files: Iterable[Path], hasher: FileHasher) -> str:
    """Content fingerprint of a sequence's input files (paths relative to the dataset root; the
    paths are not resolved, so the same files at another place give the same fingerprint)."""
    root_s = os.path.abspath(root)
    entries = []
    for p in sorted(os.path.abspath(f) for f in files):
        rel = _relative(root_s, Path(p))
        entries.append([rel, hasher(Path(p), rel)])
    return _hash_bytes(canonical_json(entries))[:32]


def _stat_line(name: str, st: os.stat_result) -> bytes:
    return (
        f"{name}\0{st.st_size}\0{st.st_mtime_ns}\0{st.st_ino}\0{stat.S_IFMT(st.st_mode)}\n".encode()
    )


def layout_signature(root: Path | str, entries: Iterable[tuple[Path | str, bool]]) -> str:
    """A hash of the stat facts (size, mtime_ns, inode, type) of every path and, for folders, of
    every entry in them (symlinks followed; an entry that cannot be stat'ed counts by its error).
    Paths count relative to ``root`` (the same files reached from another place, e.g. hard links,
    sign the same). No file is opened: equal signatures mean nothing was added, removed, replaced
    or rewritten (up to the mtime resolution). About one ``stat`` per file."""
    root_s = os.path.abspath(root) + os.sep
    h = hashlib.sha256()
    for path, is_folder in entries:
        p = os.fspath(path)
        rel = p[len(root_s) :] if p.startswith(root_s) else p
        try:
            st = os.stat(p)
        except OSError as exc:
            h.update(f"{rel}\0!{exc.errno}\n".encode())
            continue
        if not is_folder or not stat.S_ISDIR(st.st_mode):
            h.update(_stat_line(rel, st))
            continue
        h.update(
            f"{rel}\0folder\n".encode()
        )  # its entries say what changed; its own mtime adds nothing
        try:
            with os.scandir(p) as it:
                children = sorted(it, key=lambda e: e.name)
        except OSError as exc:
            h.update(f"{rel}\0!list {exc.errno}\n".encode())
            continue
        for entry in children:
            try:
                h.update(_stat_line(entry.name, entry.stat()))
            except OSError as exc:
                h.update(f"{entry.name}\0!{exc.errno}\n".encode())
    return h.hexdigest()[:32]


class FingerprintCache:
    """``OUT/.cache/sequences/<seq>.json``: per sequence, what planning learnt from its files
    (``reader``: how it was read, ``signature``: :func:`layout_signature`, ``fingerprint``,
    ``num_frames``, ``warnings``, ``files``: the content-hash memo). One small file per sequence,
    written only when it changes. ``folder=None`` keeps nothing (every plan reads everything);
    ``verify`` ignores what is kept."""

    def __init__(self, folder: Path | None, verify: bool = False):
        self.folder = None if folder is None else Path(folder)
        self.verify = verify
        self.hasher = FileHasher(verify=verify)  # the plan's (device, inode) table and counters
        self.errors: list[str] = []  # memo files that could not be written (a full disk)

    def load(self, sequence: str) -> dict:
        if self.folder is None:
            return {}
        try:
            memo = json.loads((self.folder / f"{sequence}.json").read_bytes())
        except (OSError, ValueError):
            return {}  # a missing or damaged memo only costs reading the sequence again
        # verified before use: a memo that is not the object this class writes is not used
        if not isinstance(memo, dict) or not isinstance(memo.get("files", {}), dict):
            return {}
        return memo

    def hit(self, memo: dict, reader: Any, signature: str) -> bool:
        return (
            not self.verify
            and memo.get("reader") == reader
            and memo.get("signature") == signature
            and "fingerprint" in memo
        )

    def file_hasher(self, memo: dict) -> FileHasher:
        h = FileHasher(dict(memo.get("files") or {}), self.verify).share_inodes(self.hasher)
        return h

    def add_costs(self, hasher: FileHasher) -> None:
        self.hasher.hashed += hasher.hashed
        self.hasher.bytes_hashed += hasher.bytes_hashed
        self.hasher.seconds += hasher.seconds

    def save(self, sequence: str, entry: dict) -> None:
        if self.folder is None:
            return
        try:
            atomic_write_bytes(self.folder / f"{sequence}.json", canonical_json(entry))
        except OSError as exc:  # the run goes on; the next plan reads the sequence again
            self.errors.append(f"{exc.filename}: {exc.strerror}")


def stage_key(stage: str, code_version: str, inputs_hash: str, upstream: dict[str, str]) -> str:
    """Key of one (sequence, stage): what must change for the stage to run again (its code
    version, the hash of its inputs object, the fingerprint or its upstream keys)."""
    return _hash_bytes(
        stage.encode(), code_version.encode(), inputs_hash.encode(), canonical_json(upstream)
    )[:24]


def _flatten(value: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(value, dict):
        out: dict[str, Any] = {}
        for k, v in value.items():
            if k != "type" or not isinstance(v, str):
                out.update(_flatten(v, f"{prefix}.{k}" if prefix else str(k)))
            else:
                out[f"{prefix}.type" if prefix else "type"] = v
        return out
    return {prefix: value}


@dataclass
class StageRecord:
    sequence: str
    stage: str
    key: str
    status: str  # done | failed
    location: str = ""  # relative to the output root
    error: str = ""
    seconds: float = 0.0
    finished_at: float = 0.0
    summary: dict = field(default_factory=dict)
    #: the key's ingredients (code version, inputs hash, fingerprint / upstream keys) to explain
    #: staleness
    parts: dict = field(default_factory=dict)


class Manifest:
    """The rows of ``OUT/manifest.json`` and of the journal beside it.

    :meth:`record` appends one row to the journal (O(1), fsynced); :meth:`save` compacts
    everything into ``manifest.json`` (atomic) and removes the journal; :meth:`load` reads both.
    """

    def __init__(
        self,
        root: Path,
        rows: dict[tuple[str, str], StageRecord] | None = None,
        meta: dict | None = None,
    ):
        self.root = Path(root)
        self.rows = rows or {}
        self.meta = meta or {}
        self.journal_lines = (
            0  # rows read from a journal (a killed run) or appended since the last save
        )

    @classmethod
    def load(cls, root: Path) -> Manifest:
        path = Path(root) / MANIFEST
        manifest = cls(root)
        if path.exists():
            try:
                data = json.loads(path.read_text())
            except json.JSONDecodeError as exc:
                raise OutputError(
                    f"{path}: manifest is not valid JSON ({exc}); move it aside to rebuild"
                ) from None
            if data.get("version") != MANIFEST_VERSION:
                raise OutputError(
                    f"{path}: manifest version {data.get('version')!r}, expected {MANIFEST_VERSION}"
                )
            for row in data["rows"]:
                manifest.put(StageRecord(**row))
            manifest.meta = data.get("meta", {})
        manifest._replay(Path(root) / JOURNAL)
        return manifest

    def _replay(self, path: Path) -> None:
        try:
            lines = path.read_bytes().splitlines()
        except FileNotFoundError:
            return
        for line in lines:
            try:
                self.put(StageRecord(**json.loads(line)))
            except (ValueError, TypeError):  # a line cut by a kill or a full disk: the unit reruns
                continue
            self.journal_lines += 1

    def get(self, sequence: str, stage: str) -> StageRecord | None:
        return self.rows.get((sequence, stage))

    def put(self, record: StageRecord) -> None:
        loc = record.location
        if loc and (
            loc != f"stages/{record.stage}/{record.sequence}/{record.key}"
            or ".." in loc.split("/")
            or not loc.isprintable()
        ):
            # nothing recorded in OUT is trusted to name a path: a row naming any folder but its
            # own key-named one (a crafted or foreign manifest) names none, so the unit runs again
            record = replace(
                record,
                location="",
                status="failed",
                error=f"its recorded output location {shown(repr(loc))} was refused",
            )
        self.rows[(record.sequence, record.stage)] = record

    def record(self, record: StageRecord) -> None:
        """Put a row and append it to the journal at once (a disk error names the journal; the
        row stays in memory for the next :meth:`save`)."""
        self.put(record)
        path = self.root / JOURNAL
        line = json.dumps(asdict(record), sort_keys=True, separators=(",", ":")).encode() + b"\n"
        try:
            with open(path, "ab") as fh:
                fh.write(line)
                fh.flush()
                os.fsync(fh.fileno())
        except OSError as exc:
            raise named(exc, path) from None
        self.journal_lines += 1

    def save(self) -> None:
        """Compact: every row and the meta into ``manifest.json`` (atomic), then drop the journal."""
        used = {(r.stage, (r.parts or {}).get("config")) for r in self.rows.values()}
        for stage, table in self.meta.get("inputs", {}).items():
            keep = {h for s, h in used if s == stage} | set(list(table)[-1:])
            for digest in [h for h in table if h not in keep]:
                del table[digest]
        rows = [asdict(self.rows[k]) for k in sorted(self.rows)]
        atomic_write_bytes(
            self.root / MANIFEST,
            json.dumps(
                {"version": MANIFEST_VERSION, "meta": self.meta, "rows": rows},
                indent=1,
                sort_keys=True,
            ).encode(),
            sync_folder=True,
        )
        (self.root / JOURNAL).unlink(missing_ok=True)
        self.journal_lines = 0

    def drop_sequence(self, sequence: str) -> None:
        """Forget every row of a sequence (its input is gone; kept by the next :meth:`save`)."""
        for key in [k for k in self.rows if k[0] == sequence]:
            del self.rows[key]

    def remember_inputs(self, inputs: dict[str, tuple[str, Any]]) -> None:
        """Keep each stage's inputs (hash -> JSON) so a later plan can say which setting changed;
        kept for the hashes some row still refers to (pruned on save)."""
        table = self.meta.setdefault("inputs", {})
        for stage, (digest, value) in inputs.items():
            table.setdefault(stage, {})[digest] = value

    def inputs_diff(self, stage: str, old: str | None, new: str, limit: int = 3) -> str:
        """The settings that differ between two inputs hashes of a stage ("" if unknown)."""
        table = self.meta.get("inputs", {}).get(stage, {})
        if old not in table or new not in table:
            return ""
        a, b = _flatten(table[old]), _flatten(table[new])
        diffs = [
            f"{k} {a.get(k)!r} -> {b.get(k)!r}"
            for k in sorted(set(a) | set(b))
            if a.get(k) != b.get(k)
        ]
        more = f" (+{len(diffs) - limit} more)" if len(diffs) > limit else ""
        return ", ".join(diffs[:limit]) + more


#: manifest meta key: the absolute raw data root the dataset was last built from
DATA_ROOT_KEY = "data_root"


def record_data_root(manifest: Manifest, data_root: Path | str) -> None:
    """Remember where the dataset is built from (absolute, symlinks resolved): what the frames
    table's relative source paths are relative to, wherever the next command runs from."""
    manifest.meta[DATA_ROOT_KEY] = str(Path(data_root).resolve())


def recorded_data_root(out_root: Path | str) -> Path | None:
    """The raw data root recorded in ``OUT/manifest.json`` (None: none recorded). Manifests
    written before the record existed: the run's ``dataset.root``, relative to this directory."""
    meta = Manifest.load(Path(out_root)).meta
    root = meta.get(DATA_ROOT_KEY) or ((meta.get("config") or {}).get("dataset") or {}).get("root")
    return Path(root) if root else None


def data_root_for(out_root: Path | str, given: Path | str | None = None) -> Path:
    """The raw data root of the dataset at ``out_root``: ``given`` (``--data``) when set, else the
    one recorded by the run that built it. InputError naming both paths when the root to use is
    not a folder (a moved data root), or when none is known."""
    out = Path(out_root)
    if given is not None and Path(given).is_dir():
        return Path(given)
    recorded = recorded_data_root(out)
    if given is not None:
        built = f"; the dataset was built from {recorded}" if recorded else ""
        raise InputError(f"data root {given} (--data) is not a folder{built}", Path(given))
    if recorded is None:
        raise InputError(
            f"{out / MANIFEST}: no raw data root recorded (no pipeline run wrote it); pass --data",
            out / MANIFEST,
        )
    if not recorded.is_dir():
        raise InputError(
            f"the dataset {out} was built from the raw data root {recorded} (recorded in "
            f"{out / MANIFEST}), which is not a folder any more; if the raw data moved, pass "
            "--data NEW_ROOT",
            recorded,
        )
    return recorded


def stage_dir(root: Path, stage: str, sequence: str, key: str) -> Path:
    """Key-named output location of one (sequence, stage)."""
    return Path(root) / "stages" / stage / sequence / key


#: where runs leave temporary files, relative to OUT (a killed run, a full disk): stage outputs
#: being written, publication staging, table partitions, the manifest and memo files, exports
TEMPORARY_PATTERNS = (
    f"{TMP_PREFIX}*",
    f".cache/{TMP_PREFIX}*",
    f".cache/*/{TMP_PREFIX}*",
    f"stages/*/*/{TMP_PREFIX}*",
    f"occupancy/*/{TMP_PREFIX}*",
    f"tables/*/*/{TMP_PREFIX}*",
    f"exports/{TMP_PREFIX}*",
    f"exports/*/{TMP_PREFIX}*",
    f"exports/*/*/{TMP_PREFIX}*",
)


def sweep_temporaries(root: Path) -> int:
    """Remove the ``.tmp-*`` leftovers of killed or failed runs (``TEMPORARY_PATTERNS``); returns
    how many. Call it only while holding :func:`run_lock` (no other run is writing)."""
    n = 0
    for pattern in TEMPORARY_PATTERNS:
        for tmp in Path(root).glob(pattern):
            if tmp.is_dir() and not tmp.is_symlink():
                shutil.rmtree(tmp, ignore_errors=True)
            else:
                tmp.unlink(missing_ok=True)
            n += 1
    return n


#: the store's cache products under ``OUT/.cache`` (all remade on demand from the inputs):
#: the procedural body model and prior, the log indexes, the odometry, the planning memos
PROCEDURAL_MODEL = "procedural_smpl_v1.npz"
PROCEDURAL_PRIOR = "procedural_gmm_08_v1.pkl"
CACHE_PRODUCTS = (
    PROCEDURAL_MODEL,
    PROCEDURAL_PRIOR,
    "log-index",
    "odometry",
    "sequences",
)


def remove_caches(root: Path) -> int:
    """Remove every cache product (``rebuild --force``: each is made again from the inputs, so a
    damaged one that passed its check cannot outlive a forced run); returns how many. Call it
    only while holding :func:`run_lock`."""
    n = 0
    for name in CACHE_PRODUCTS:
        path = Path(root) / ".cache" / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
            n += 1
        elif os.path.lexists(path):
            path.unlink(missing_ok=True)
            n += 1
    return n


def remove_stale_versions(root: Path, stage: str, sequence: str, keep: str) -> None:
    """Delete the outputs of a (sequence, stage) other than the key ``keep``."""
    folder = Path(root) / "stages" / stage / sequence
    if folder.is_dir():
        for child in folder.iterdir():
            if child.name != keep and not child.name.startswith(TMP_PREFIX):
                shutil.rmtree(child, ignore_errors=True)


class StoreLockedError(RuntimeError):
    """Another run holds the output store's lock."""


class OutputError(ValueError):
    """The output store cannot be written (checked before any work starts)."""


def check_writable(root: Path) -> None:
    """``root`` is (or can be made) a folder this process can write; OutputError naming it and the
    reason otherwise (a file, a read-only place, a full disk)."""
    root = Path(root)
    if root.exists() and not root.is_dir():
        raise OutputError(f"output store {root} is not a folder")
    probe = root / f"{TMP_PREFIX}writable-{uuid.uuid4().hex[:8]}"
    try:
        root.mkdir(parents=True, exist_ok=True)
        with open(probe, "wb") as fh:
            fh.write(b"0")
    except OSError as exc:
        raise OutputError(
            f"output store {root} is not writable ({exc.strerror or exc}"
            f"{': ' + str(exc.filename) if exc.filename and str(exc.filename) != str(probe) else ''})"
        ) from None
    finally:
        try:
            probe.unlink()
        except OSError:
            pass


#: what an output store holds at its top (anything else in a store without a manifest is not ours)
STORE_ENTRIES = frozenset(
    {MANIFEST, JOURNAL, ".lock", ".cache", ".publishing", "stages", "occupancy", "tables",
     "exports", "report"}
)  # fmt: skip


def check_store_place(out: Path, data: Path) -> None:
    """The output store is neither the data root nor a folder holding it, and a store without a
    manifest holds nothing but a store's entries (``STORE_ENTRIES``, temporaries): else an
    OutputError naming both, before any work (the store's sweep and publication must never touch
    the user's files)."""
    out_r, data_r = os.path.realpath(out), os.path.realpath(data)
    if out_r == data_r:
        raise OutputError(
            f"output store {out} is the data root {data}: the store would mix with the data; "
            "choose another folder for --out"
        )
    if data_r.startswith(out_r.rstrip(os.sep) + os.sep):
        raise OutputError(
            f"output store {out} holds the data root {data}; choose another folder for --out"
        )
    out = Path(out)
    if not out.is_dir() or (out / MANIFEST).exists() or (out / JOURNAL).exists():
        return
    foreign = sorted(
        p.name
        for p in out.iterdir()
        if p.name not in STORE_ENTRIES and not p.name.startswith(TMP_PREFIX)
    )
    if foreign:
        more = f" and {len(foreign) - 3} more" if len(foreign) > 3 else ""
        raise OutputError(
            f"output store {out} holds files that are not a mobileocc store's "
            f"({', '.join(repr(f) for f in foreign[:3])}{more}); choose a new or empty folder "
            "for --out"
        )


#: the output stores whose lock this process holds (a caller holding it may hand the run to code
#: that would take it again: :func:`holding_lock`)
_HELD: set[str] = set()
_HELD_GUARD = threading.Lock()
LOCK_FILE = ".lock"


@contextmanager
def run_lock(root: Path) -> Iterator[None]:
    """One run at a time per output store: a second run is refused with :class:`StoreLockedError`
    (a second one in the same process too).

    The lock is a kernel file lock (``flock``) on ``OUT/.lock``, so it is released when its process
    ends however it ends: a lock "left" by a killed run is no lock, and the next run takes it. The
    file's content (host, pid, start time) is only for the refusal's message; a failed write of it
    (a full disk) leaves the lock held and the file empty, never a wedged store. The holder
    unlinks the file before unlocking, and a process that locked a file which is no longer the one
    at ``OUT/.lock`` tries again, so two processes can never both hold it (tests race many).
    """
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    path = root / LOCK_FILE
    key = os.path.abspath(path)
    with _HELD_GUARD:
        if key in _HELD:
            raise StoreLockedError(
                f"{root} is in use by another run (in this process, pid {os.getpid()})"
            )
        _HELD.add(key)
    try:
        fd = _acquire(path)
    except BaseException:
        with _HELD_GUARD:
            _HELD.discard(key)
        raise
    try:
        yield
    finally:
        try:
            os.unlink(path)
        except OSError:
            pass
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)
        with _HELD_GUARD:
            _HELD.discard(key)


@contextmanager
def read_lock(root: Path) -> Iterator[None]:
    """Readers of the published store (``mobileocc export``, ``evaluate``): many at once, never
    while a run holds :func:`run_lock` (refused with :class:`StoreLockedError`), and a run is
    refused while they read. A shared ``flock`` on the same ``OUT/.lock``; a reader neither writes
    the file nor unlinks it (other readers may hold it), so a store only ever read keeps an empty
    lock file, which the next run takes and removes."""
    root = Path(root)
    if not root.is_dir():
        raise OutputError(f"output store {root} does not exist")
    path = root / LOCK_FILE
    with _HELD_GUARD:
        if os.path.abspath(path) in _HELD:  # this process runs: it sees its own writes
            held = True
        else:
            held = False
    if held:
        yield
        return
    if not writable_store(root):
        # a read-only store (a finished dataset on a read-only mount): no run can write it, so
        # none can race this reader; the lock file may not be creatable, and is not needed
        yield
        return
    fd = _acquire(path, exclusive=False)
    try:
        yield
    finally:
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)


def writable_store(root: Path) -> bool:
    """Whether ``root`` can be written: its lock file opened for writing (created where missing,
    as a reader's shared lock does anyway). False on a read-only file system (EROFS) or a folder
    this user may not write (EACCES / EPERM)."""
    try:
        fd = os.open(root / LOCK_FILE, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o644)
    except OSError as exc:
        if exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
            return False
        raise
    os.close(fd)
    return True


def read_only_error(root: Path, exc: OSError, doing: str) -> OutputError | None:
    """The one line for a write refused by a read-only store (EROFS, EACCES, EPERM) while
    ``doing``; None for any other error."""
    if exc.errno not in (errno.EROFS, errno.EACCES, errno.EPERM):
        return None
    why = "is on a read-only file system" if exc.errno == errno.EROFS else "is not writable here"
    return OutputError(
        f"output store {root} {why} ({exc.filename or root}: {exc.strerror}); {doing} needs to "
        "write into it (reading it works: status, evaluate --report, export --to, view)"
    )


@contextmanager
def holding_lock(root: Path) -> Iterator[None]:
    """For code run on behalf of a caller that holds :func:`run_lock` of ``root`` (the CLI takes it
    before starting Prefect, then runs the flow): checks that this process holds it."""
    with _HELD_GUARD:
        held = os.path.abspath(Path(root) / LOCK_FILE) in _HELD
    if not held:
        raise StoreLockedError(
            f"{root}: the run was told the lock is held, but this process does not hold it"
        )
    yield


def _acquire(path: Path, exclusive: bool = True) -> int:
    me = {"host": socket.gethostname(), "pid": os.getpid(), "started": time.time()}
    for _ in range(100):
        fd = os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o644)
        try:
            fcntl.flock(fd, (fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH) | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd)
            os.close(fd)
            raise StoreLockedError(_in_use(path.parent, holder, exclusive)) from None
        except OSError as exc:
            os.close(fd)
            raise StoreLockedError(
                f"{path}: cannot lock the output store ({exc.strerror}); its file system "
                "does not support flock"
            ) from None
        try:
            same = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if not same:  # locked a file its holder unlinked on release: take the current one
            fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)
            continue
        if not exclusive:
            return fd
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, json.dumps(me).encode(), 0)
        except OSError:
            pass  # the kernel lock is held; only the refusal message of another run loses host / pid
        return fd
    raise StoreLockedError(f"{path}: the lock changed hands 100 times while taking it; try again")


def _in_use(root: Path, holder: dict, exclusive: bool) -> str:
    """Why the lock was refused: a run (it writes its host, pid and start into the file) or
    readers (they write nothing; the file may still name a run of this host that was killed
    before it could remove it: a pid no longer alive, so readers hold it)."""
    if not holder or _dead_here(holder):
        holders = lock_holders(root / LOCK_FILE)
        if holders:  # the kernel says who (Linux /proc/locks): name them, not a guess
            named = "; ".join(
                f"{'exclusive' if excl else 'shared'} lock of pid {pid} on {socket.gethostname()}"
                f" ({cmd})"
                for excl, pid, cmd in holders[:3]
            )
            if not any(excl for excl, _, _ in holders):
                return f"{root} is being read ({named}); wait for it to finish"
            return f"{root} is locked by another process ({named}); wait for it to finish"
        return (
            f"{root} is being read (e.g. by `mobileocc export` or `evaluate`); wait for it to finish"
            if exclusive
            else f"{root} is in use by a run; wait for it to finish"
        )
    when = (
        time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(holder["started"]))
        if isinstance(holder.get("started"), (int, float))
        else "?"
    )
    return (
        f"{root} is in use by {'another' if exclusive else 'a'} run (host "
        f"{holder.get('host', '?')}, pid {holder.get('pid', '?')}, started {when}); wait for it "
        "to finish"
    )


def lock_holders(path: Path) -> list[tuple[bool, int, str]]:
    """(exclusive, pid, command line) of each process of this host holding a ``flock`` on
    ``path``, from Linux's ``/proc/locks`` (empty where it cannot be read: another system, or a
    lock held from another host over a network file system). This process is left out."""
    try:
        st = os.stat(path)
        lines = Path("/proc/locks").read_text().splitlines()
    except OSError:
        return []
    inode = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    found = []
    for line in lines:
        parts = line.split()
        if len(parts) < 6 or parts[1] != "FLOCK" or parts[5] != inode:
            continue
        try:
            pid = int(parts[4])
        except ValueError:
            continue
        if pid == os.getpid():
            continue
        try:
            raw = Path(f"/proc/{pid}/cmdline").read_bytes()
            cmd = shown(" ".join(raw.decode("utf-8", "replace").split("\0")).strip()[:120])
        except OSError:
            cmd = "?"
        found.append((parts[3] == "WRITE", pid, cmd or "?"))
    return found


def _dead_here(holder: dict) -> bool:
    """Whether ``holder`` names a process of this host that no longer exists."""
    pid = holder.get("pid")
    if holder.get("host") != socket.gethostname() or not isinstance(pid, int) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:  # alive, another user's
        return False
    return False


def _holder(fd: int) -> dict:
    try:
        data = os.pread(fd, 4096, 0)
        holder = json.loads(data) if data else {}
    except (OSError, ValueError):
        holder = {}
    return holder if isinstance(holder, dict) else {}
