"""The stage cache: content fingerprints, stage keys, key-named outputs, the manifest, the run lock.

The manifest (``OUT/manifest.json``) is the source of truth of what was processed: one row per
(sequence, stage) with the stage key, where the output is, the status and the error. It is
rewritten atomically (write aside, fsync, rename) after every stage that finishes, so a killed run
loses at most the stages in flight. A stage is fresh when its row is ``done``, its key equals the key
computed now, and its output still exists; otherwise it runs again (and so does everything
downstream, whose keys include the upstream keys).

Keys (prior art: Bazel action keys, Dagster code versions, DVC content hashes)::

    fingerprint(sequence) = H(sorted (relative path, content hash) of its input files)
    key(sequence, stage)  = H(stage, stage code version, the config slice the stage reads,
                              fingerprint for the first stage / upstream keys after it)

Content hashes are memoised by (size, mtime_ns, inode) in ``OUT/.cache/file-hashes.json``.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import socket
import time
import uuid
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator

MANIFEST = "manifest.json"
MANIFEST_VERSION = 1


def _hash_bytes(*parts: bytes) -> str:
    h = hashlib.sha256()
    for part in parts:
        h.update(len(part).to_bytes(8, "little"))
        h.update(part)
    return h.hexdigest()


def canonical_json(value: Any) -> bytes:
    return json.dumps(value, sort_keys=True, separators=(",", ":"), default=str).encode()


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so readers see the old or the new file, never a part."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".tmp-{path.name}-{uuid.uuid4().hex[:8]}")
    with open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


class FileHasher:
    """sha256 of file contents, memoised by (size, mtime_ns, inode) across runs."""

    def __init__(self, cache_path: Path | None = None):
        self.cache_path = cache_path
        self._memo: dict[str, list] = {}
        if cache_path is not None and cache_path.exists():
            try:
                self._memo = json.loads(cache_path.read_text())
            except (OSError, json.JSONDecodeError):
                self._memo = {}  # a damaged memo only costs rehashing
        self.hashed = 0

    def __call__(self, path: Path) -> str:
        st = os.stat(path)
        stamp = [st.st_size, st.st_mtime_ns, st.st_ino]
        key = str(Path(path).resolve())
        hit = self._memo.get(key)
        if hit is not None and hit[:3] == stamp:
            return hit[3]
        h = hashlib.sha256()
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
        digest = h.hexdigest()
        self._memo[key] = stamp + [digest]
        self.hashed += 1
        return digest

    def save(self) -> None:
        if self.cache_path is not None:
            atomic_write_bytes(self.cache_path, canonical_json(self._memo))


def sequence_fingerprint(root: Path, files: Iterable[Path], hasher: FileHasher) -> str:
    """Content fingerprint of a sequence's input files (paths relative to the dataset root)."""
    root = Path(root).resolve()
    entries = []
    for p in sorted(Path(f).resolve() for f in files):
        try:
            rel = str(p.relative_to(root))
        except ValueError:
            rel = str(p)
        entries.append([rel, hasher(p)])
    return _hash_bytes(canonical_json(entries))[:32]


def stage_key(stage: str, code_version: str, inputs_hash: str, upstream: dict[str, str]) -> str:
    """Key of one (sequence, stage): what must change for the stage to run again (its code
    version, the hash of its inputs object, the fingerprint or its upstream keys)."""
    return _hash_bytes(stage.encode(), code_version.encode(), inputs_hash.encode(),
                       canonical_json(upstream))[:24]


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
    """The rows of ``OUT/manifest.json``; write with :meth:`save` (atomic)."""

    def __init__(self, root: Path, rows: dict[tuple[str, str], StageRecord] | None = None,
                 meta: dict | None = None):
        self.root = Path(root)
        self.rows = rows or {}
        self.meta = meta or {}

    @classmethod
    def load(cls, root: Path) -> Manifest:
        path = Path(root) / MANIFEST
        if not path.exists():
            return cls(root)
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: manifest is not valid JSON ({exc}); move it aside to rebuild") from None
        if data.get("version") != MANIFEST_VERSION:
            raise ValueError(f"{path}: manifest version {data.get('version')!r}, expected {MANIFEST_VERSION}")
        rows = {}
        for row in data["rows"]:
            rec = StageRecord(**row)
            rows[(rec.sequence, rec.stage)] = rec
        return cls(root, rows, data.get("meta", {}))

    def get(self, sequence: str, stage: str) -> StageRecord | None:
        return self.rows.get((sequence, stage))

    def put(self, record: StageRecord) -> None:
        self.rows[(record.sequence, record.stage)] = record

    def save(self) -> None:
        used = {(r.stage, (r.parts or {}).get("config")) for r in self.rows.values()}
        for stage, table in self.meta.get("inputs", {}).items():
            keep = {h for s, h in used if s == stage} | set(list(table)[-1:])
            for digest in [h for h in table if h not in keep]:
                del table[digest]
        rows = [asdict(self.rows[k]) for k in sorted(self.rows)]
        atomic_write_bytes(self.root / MANIFEST, json.dumps(
            {"version": MANIFEST_VERSION, "meta": self.meta, "rows": rows}, indent=1,
            sort_keys=True).encode())

    def output_exists(self, record: StageRecord) -> bool:
        return bool(record.location) and (self.root / record.location).exists()

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
        diffs = [f"{k} {a.get(k)!r} -> {b.get(k)!r}" for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]
        more = f" (+{len(diffs) - limit} more)" if len(diffs) > limit else ""
        return ", ".join(diffs[:limit]) + more


def stage_dir(root: Path, stage: str, sequence: str, key: str) -> Path:
    """Key-named output location of one (sequence, stage)."""
    return Path(root) / "stages" / stage / sequence / key


@contextmanager
def staged_output(final: Path) -> Iterator[Path]:
    """Yield a hidden sibling directory to write into; publish it as ``final`` by rename on success.

    An exception (or a killed process) leaves ``final`` untouched: the temporary directory is removed
    (or, after a kill, ignored and swept by :func:`sweep_temporaries`).
    """
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = final.with_name(f".tmp-{final.name}-{uuid.uuid4().hex[:8]}")
    tmp.mkdir()
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if final.exists():  # same key = same content: keep the one already published
        shutil.rmtree(tmp, ignore_errors=True)
        return
    try:
        os.replace(tmp, final)
    except OSError:
        if not final.exists():
            raise
        shutil.rmtree(tmp, ignore_errors=True)  # another writer published the same key meanwhile


def sweep_temporaries(root: Path) -> int:
    """Remove ``.tmp-*`` leftovers of killed runs under ``root/stages``; returns how many."""
    n = 0
    for tmp in (Path(root) / "stages").glob("*/*/.tmp-*"):
        shutil.rmtree(tmp, ignore_errors=True)
        n += 1
    return n


def remove_stale_versions(root: Path, stage: str, sequence: str, keep: str) -> None:
    """Delete the outputs of a (sequence, stage) other than the key ``keep``."""
    folder = Path(root) / "stages" / stage / sequence
    if folder.is_dir():
        for child in folder.iterdir():
            if child.name != keep and not child.name.startswith(".tmp-"):
                shutil.rmtree(child, ignore_errors=True)


class StoreLockedError(RuntimeError):
    pass


@contextmanager
def run_lock(root: Path) -> Iterator[None]:
    """One run at a time per output store: a second run is refused with a clear message.

    The lock file holds host and pid; a lock left by a dead process on this host is taken over.
    """
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    path = root / ".lock"
    me = {"host": socket.gethostname(), "pid": os.getpid(), "started": time.time()}
    for _ in range(2):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            try:
                holder = json.loads(path.read_text())
            except (OSError, json.JSONDecodeError):
                holder = {}
            if holder.get("host") == me["host"] and not _pid_alive(int(holder.get("pid", -1))):
                path.unlink(missing_ok=True)  # stale: its process is gone
                continue
            raise StoreLockedError(
                f"{root} is in use by another run (host {holder.get('host', '?')}, pid "
                f"{holder.get('pid', '?')}); wait for it to finish, or remove {path} if that run is "
                "gone"
            ) from None
        with os.fdopen(fd, "w") as fh:
            json.dump(me, fh)
        break
    try:
        yield
    finally:
        path.unlink(missing_ok=True)


def _pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
