"""Planning at dataset scale: plan / status / dry-run seconds and hashing MB/s vs sequences.

``bench_planning(sequences, work_dir)`` simulates one short sequence (``simulate --fast``, 4 raw
frames), replicates it with hard links under ``n`` sequence ids for each ``n`` of ``sequences``
(the planner cannot tell: every path is hashed on its own), and measures, for each dataset, in
this process (imports already done):

- ``first_status_s``: ``mobileocc status`` on an empty output store: opens every sequence and
  hashes every input byte; ``hash_s``: the same plan once more (``status`` keeps no hash memo;
  a run saves it) for ``hashed_mb`` and ``hash_mb_per_s`` (the copies share their pages, so the
  bytes come from the page cache: sha256 speed, not disk speed);
- every unit is then recorded done in ``OUT/manifest.json`` (an empty key folder with a
  ``summary.json`` per unit, as a finished run leaves them; ``manifest_kb``);
- ``plan_s``: ``plan_run`` once fingerprints are known (the hash memo is loaded);
  ``status_s``: ``mobileocc status``; ``dry_run_s``: ``mobileocc reprocess --dry-run`` (both print
  to /dev/null; every unit is fresh).

This is the measurement the scale benchmark (flows/bench/scale.py) reports; the planner itself
is flows/pipeline/plan.py.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import time
from pathlib import Path

#: id of the simulated source sequence: a number no replica takes, replaced in paths by the
#: replica's id
_SOURCE_ID = 987654


def replicate_sequence(src_root: Path, dst_root: Path, source_id: int, ids: list[int]) -> int:
    """Hard-link every file of sequence ``source_id`` under ``src_root`` into ``dst_root`` once
    per id of ``ids`` (the id replaced in directory and file names; the metadata's frame lists
    rewritten). Returns the number of links made."""
    sid = str(source_id)
    files = [p for p in Path(src_root).rglob("*") if p.is_file() and sid in str(p.relative_to(src_root))]
    links = 0
    for new in ids:
        for p in files:
            rel = str(p.relative_to(src_root))
            target = Path(dst_root) / rel.replace(f"/{sid}/", f"/{new}/").replace(f"_{sid}_", f"_{new}_") \
                .replace(f"/{sid}.", f"/{new}.")
            target.parent.mkdir(parents=True, exist_ok=True)
            if p.parent.name == "metadata":
                text = p.read_text().replace(f"/{sid}/", f"/{new}/").replace(f"_{sid}_", f"_{new}_")
                target.write_text(text)
            else:
                os.link(p, target)
                links += 1
    return links


def _record_all_done(config, out: Path) -> None:
    """A manifest in which every unit of every sequence is done (empty outputs)."""
    from flows.pipeline.plan import plan_run
    from storage.manifest import FileHasher, Manifest, StageRecord, stage_dir

    manifest = Manifest.load(out)
    hasher = FileHasher(out / ".cache" / "file-hashes.json")
    for plan in plan_run(config, manifest, hasher):
        for stage, unit in plan.units.items():
            d = stage_dir(out, stage, plan.sequence, unit.key)
            d.mkdir(parents=True, exist_ok=True)
            (d / "summary.json").write_text("{}")
            manifest.put(StageRecord(plan.sequence, stage, unit.key, "done", str(d.relative_to(out)),
                                     finished_at=time.time(), parts=unit.parts))
    manifest.save()


def _cli_seconds(argv: list[str]) -> float:
    from flows.cli import main

    t0 = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):
        code = main(argv)
    if code:
        raise RuntimeError(f"mobileocc {' '.join(argv)} exited {code}")
    return time.perf_counter() - t0


def _plan_seconds(config, out: Path) -> float:
    from flows.pipeline.plan import plan_run
    from storage.manifest import FileHasher, Manifest

    t0 = time.perf_counter()
    plans = plan_run(config, Manifest.load(out), FileHasher(out / ".cache" / "file-hashes.json"))
    seconds = time.perf_counter() - t0
    stale = sum(not u.fresh for p in plans for u in p.units.values())
    if stale:
        raise RuntimeError(f"{out}: {stale} unit(s) stale after recording every unit done")
    return seconds


class _TimedHasher:
    """A FileHasher that adds up the seconds spent in it (hashing, and stat-ing the memo's hits)."""

    def __init__(self, hasher):
        self.hasher, self.seconds = hasher, 0.0

    def __call__(self, path):
        t0 = time.perf_counter()
        try:
            return self.hasher(path)
        finally:
            self.seconds += time.perf_counter() - t0

    def save(self) -> None:
        self.hasher.save()


def _prefill_memo(data: Path, out: Path, src: Path) -> None:
    """The hash memo a first plan would leave, without hashing: the copies are hard links of the
    source's files (same content); the rewritten metadata files are hashed."""
    from storage.manifest import FileHasher, atomic_write_bytes, canonical_json

    hasher = FileHasher(None)
    by_inode = {p.stat().st_ino: hasher(p) for p in src.rglob("*") if p.is_file()}
    memo = {}
    for p in data.rglob("*"):
        if p.is_file():
            st = p.stat()
            digest = by_inode.get(st.st_ino) or hasher(p)
            memo[str(p.resolve())] = [st.st_size, st.st_mtime_ns, st.st_ino, digest]
    atomic_write_bytes(out / ".cache" / "file-hashes.json", canonical_json(memo))


def bench_planning(sequences: list[int], work_dir, hash_up_to: int = 100) -> dict:
    """Plan / status / dry-run seconds and hashing MB/s for datasets of ``sequences`` sequences
    (see the module docstring). Datasets of more than ``hash_up_to`` sequences are not hashed
    (minutes on a loaded machine): their hash memo is filled from the source's digests (the copies
    are hard links) and their first plan is projected from the hashing MB/s measured on the
    largest hashed one (``first_status_s`` None, ``first_status_projected_s``). Returns
    {"source": {...}, "datasets": {n: {...}}}."""
    from flows.bench.pipeline import make_config
    from flows.commands.simulate import simulate
    from flows.pipeline.plan import plan_run
    from storage.manifest import FileHasher, Manifest

    work = Path(work_dir)
    src = work / "planning-source"
    if not (src / "metadata" / f"{_SOURCE_ID}.json").exists():
        simulate(src, sequences=1, frames=4, seed=3, pedestrians=2, progress=False, first_id=_SOURCE_ID,
                 fast=True)
    source_mb = sum(p.stat().st_size for p in src.rglob("*") if p.is_file() and "gt" not in p.parts) / 1e6
    result: dict = {"source": {"raw_frames": 4, "frames": 2, "input_mb": source_mb}, "datasets": {}}
    per_seq_mb = mb_per_s = None
    for n in sorted(sequences):
        if n > hash_up_to and per_seq_mb is None:
            raise ValueError(f"bench_planning: {n} sequences are not hashed; list a size <= {hash_up_to} too")
        data, out = work / f"planning-{n}" / "data", work / f"planning-{n}" / "out"
        shutil.rmtree(data.parent, ignore_errors=True)
        links = replicate_sequence(src, data, _SOURCE_ID, list(range(n)))
        cfg = make_config(data, out)
        args = ["--data", str(data), "--out", str(out)]
        if n <= hash_up_to:
            first = _cli_seconds(["status", *args])  # `status` hashes but keeps no memo: a run does
            hasher = _TimedHasher(FileHasher(out / ".cache" / "file-hashes.json"))
            plan_run(cfg, Manifest.load(out), hasher)
            hasher.save()
            hash_s = hasher.seconds
            hashed_mb = sum(v[0] for v in json.loads((out / ".cache" / "file-hashes.json").read_text()).values()) / 1e6
            per_seq_mb, mb_per_s = hashed_mb / n, hashed_mb / hash_s
        else:
            _prefill_memo(data, out, src)
            first, hash_s, hashed_mb = None, None, per_seq_mb * n
        _record_all_done(cfg, out)
        result["datasets"][n] = {
            "links": links, "first_status_s": first, "hashed_mb": hashed_mb, "hash_s": hash_s,
            "hash_mb_per_s": mb_per_s, "first_status_projected_s": hashed_mb / mb_per_s,
            "manifest_kb": (out / "manifest.json").stat().st_size / 1e3,
            "plan_s": _plan_seconds(cfg, out), "status_s": _cli_seconds(["status", *args]),
            "dry_run_s": _cli_seconds(["reprocess", "--dry-run", *args])}
        shutil.rmtree(data.parent, ignore_errors=True)
    return result
