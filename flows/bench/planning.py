"""Planning at dataset scale: what ``rebuild`` / ``reprocess --dry-run`` / ``status`` cost on
datasets of many sequences, and what the manifest costs (issue 17, item 3).

``bench_planning(sequences, work_dir)`` simulates one short sequence, replicates it under N ids
with hard links (same bytes, same inodes: a dataset of N sequences on the disk space of one) for
each N in ``sequences``, and measures, per N:

- ``first_plan_s``: the first plan (no fingerprint known): every sequence opened, validated and
  hashed; with ``hash_mb_per_s`` (bytes read and hashed / hashing seconds; hard links are hashed
  once per plan, so ``bytes_hashed`` is about one sequence's worth) and ``unique_mb``;
- ``status_s``, ``dry_run_s``, ``rebuild_s``: wall seconds of ``mobileocc status`` /
  ``reprocess --dry-run`` / ``rebuild`` as commands (a new Python process each: start-up and
  imports included; ``startup_s`` is ``mobileocc config show`` for comparison) once fingerprints
  are known, on a store whose manifest holds every unit as done (rows written here with the keys
  the plan computes and summaries shaped like a real run's: the pipeline itself is not run N
  times). A rebuild with nothing to run starts no task runner and no Prefect server;
- ``files_opened_in_plan``: input files opened by a no-change ``status`` (0: no frame bytes read);
- the manifest: ``manifest_mb``, ``manifest_load_s``, ``manifest_save_s`` (one compaction),
  ``journal_append_ms`` (one unit recorded), and ``full_rewrite_per_unit_run_s`` = units x one
  full save: what recording a whole run cost when the manifest was rewritten after every unit
  (measured save time x units, not run).

Run: ``mobileocc bench planning 10 100 1000`` (``mobileocc bench scale`` calls
:func:`bench_planning`).
"""

from __future__ import annotations

import contextlib
import io
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from storage.atomic import atomic_write_text

#: raw 10 Hz frames of the replicated sequence (10 frames at 5 Hz)
RAW_FRAMES = 20
#: the replicated sequence's own id: one that no replica's id or frame index can be mistaken for
SOURCE_ID = 987654


def replicate_sequence(src_root: Path, dst_root: Path, source_id: int, ids: list[int]) -> int:
    """Hard-link every file of sequence ``source_id`` under ``src_root`` into ``dst_root`` once
    per id of ``ids`` (the id replaced in directory and file names; the metadata's frame lists
    rewritten). Returns the number of links made."""
    sid = str(source_id)
    files = [
        p for p in Path(src_root).rglob("*") if p.is_file() and sid in str(p.relative_to(src_root))
    ]
    links = 0
    for new in ids:
        for p in files:
            rel = str(p.relative_to(src_root))
            target = Path(dst_root) / rel.replace(f"/{sid}/", f"/{new}/").replace(
                f"_{sid}_", f"_{new}_"
            ).replace(f"/{sid}.", f"/{new}.")
            target.parent.mkdir(parents=True, exist_ok=True)
            if p.parent.name == "metadata":
                text = p.read_text().replace(f"/{sid}/", f"/{new}/").replace(f"_{sid}_", f"_{new}_")
                atomic_write_text(target, text)
            else:
                os.link(p, target)
                links += 1
    return links


def _command(argv: list[str]) -> tuple[int, float, str]:
    """(exit code, wall seconds, stdout) of ``mobileocc <argv>`` as a new process (this checkout)."""
    root = Path(__file__).resolve().parents[2]
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")]),
    }
    t0 = time.perf_counter()
    run = subprocess.run(
        [sys.executable, "-m", "flows.cli", *argv],
        cwd=root,
        env=env,
        capture_output=True,
        text=True,
    )
    return run.returncode, time.perf_counter() - t0, run.stdout


def _summaries(frames: int) -> dict[str, dict]:
    """Stage summaries shaped like a real run's (their size is what the manifest carries)."""
    raws = list(range(0, 2 * frames, 2))
    return {
        "detect": {
            "implemented": True,
            "frames": raws,
            "failed_frames": [],
            "image_provider": "oracle",
            "lidar_provider": "lidar-clusters",
            "detections": 31,
            "lidar_boxes": 28,
        },
        "track": {
            "implemented": True,
            "tracks": 4,
            "tracked_detections": 29,
            "mean_person_points": 151.3,
        },
        "fit": {
            "implemented": True,
            "fitted": 25,
            "batches": 1,
            "skipped_without_estimate": 2,
            "skipped_few_points": 2,
            "dropped_far_from_estimate": 0,
            "device": "cpu",
            "preset": "3dpw",
        },
        "map": {
            "implemented": True,
            "static_voxels": 91234,
            "camera_labelled_voxels": 40211,
            "occupancy_voxels": 250119,
            "points_kept": 1200345,
            "points_removed": 2311,
            "ground_votes_rejected": 12,
        },
        "fuse": {
            "implemented": True,
            "frames": frames,
            "grid_shape": [48, 48, 24],
            "voxel_size_m": 0.2,
            "body_source": "fit",
            "pedestrian_meshes": 25,
        },
        "export": {
            "implemented": True,
            "frames": frames,
            "instances": 29,
            "occupancy_version": "x",
        },
    }


#: files of a unit's output folder beside summary.json and complete.json, as a real run of the
#: replicated sequence leaves them (detect: one per frame; map: tiles; fuse: the Zarr store), and
#: of a published sequence (arrays and the three partitions)
FILES_PER_UNIT = {
    "detect": RAW_FRAMES // 2,
    "track": 1,
    "fit": 1,
    "map": 9,
    "fuse": 12,
    "export": 0,
}
PUBLISHED_FILES = 14


def _fake_output(out: Path, folder: Path, stage: str, sequence: str, key: str) -> None:
    """An output folder of empty files with its completion record (what a plan stats), and for
    the export stage a published sequence whose current.json lists its files."""
    import json

    from storage.completion import describe, write_record

    for i in range(FILES_PER_UNIT[stage]):
        (folder / f"part_{i}.npz").touch()
    atomic_write_text(folder / "summary.json", "{}")
    write_record(folder, stage=stage, sequence=sequence, key=key)
    if stage == "export":
        store = out / "occupancy" / sequence / f"{key}.zarr"
        store.mkdir(parents=True, exist_ok=True)
        for i in range(PUBLISHED_FILES):
            (store / f"chunk_{i}").touch()
        current = {"version": key, "files": describe(out, sorted(store.iterdir()))}
        atomic_write_text(store.parent / "current.json", json.dumps(current))


def _complete_store(config, out: Path) -> int:
    """Record every unit of every sequence as done (with an output folder and its completion
    record, and a published sequence), as a finished run would leave the store; returns the
    number of rows."""
    from flows.pipeline.plan import plan_run
    from storage.manifest import FingerprintCache, Manifest, StageRecord, stage_dir

    manifest = Manifest.load(out)
    plans = plan_run(config, manifest, FingerprintCache(out / ".cache" / "sequences"))
    for plan in plans:
        summaries = _summaries(plan.num_frames)
        for stage, unit in plan.units.items():
            folder = stage_dir(out, stage, plan.sequence, unit.key)
            folder.mkdir(parents=True, exist_ok=True)
            _fake_output(out, folder, stage, plan.sequence, unit.key)
            manifest.put(
                StageRecord(
                    plan.sequence,
                    stage,
                    unit.key,
                    "done",
                    str(folder.relative_to(out)),
                    seconds=1.0,
                    finished_at=time.time(),
                    summary=summaries[stage],
                    parts=unit.parts,
                )
            )
    manifest.meta.update({"config": config.model_dump(mode="json"), "completion_records": 1})
    manifest.save()
    return len(manifest.rows)


def _manifest_costs(out: Path) -> dict:
    from storage.manifest import JOURNAL, MANIFEST, Manifest

    t0 = time.perf_counter()
    manifest = Manifest.load(out)
    load_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    manifest.save()
    save_s = time.perf_counter() - t0
    rows = list(manifest.rows.values())[:50]
    t0 = time.perf_counter()
    for rec in rows:
        manifest.record(rec)
    append_ms = (time.perf_counter() - t0) / len(rows) * 1e3
    (out / JOURNAL).unlink(missing_ok=True)
    return {
        "rows": len(manifest.rows),
        "manifest_mb": (out / MANIFEST).stat().st_size / 1e6,
        "manifest_load_s": load_s,
        "manifest_save_s": save_s,
        "journal_append_ms": append_ms,
        "full_rewrite_per_unit_run_s": save_s * len(manifest.rows),
        "journal_per_unit_run_s": append_ms / 1e3 * len(manifest.rows) + save_s,
    }


def _opened_during(fn, root: Path) -> tuple[int, object]:
    """How many files under ``root`` ``fn()`` opened (os.open and open), and its result."""
    import builtins

    root_s, count = os.path.abspath(root) + os.sep, [0]
    real_open, real_os_open = builtins.open, os.open

    def counting_open(file, *a, **kw):
        if isinstance(file, (str, os.PathLike)) and os.path.abspath(file).startswith(root_s):
            count[0] += 1
        return real_open(file, *a, **kw)

    def counting_os_open(path, *a, **kw):
        if os.path.abspath(path).startswith(root_s):
            count[0] += 1
        return real_os_open(path, *a, **kw)

    builtins.open, os.open = counting_open, counting_os_open
    try:
        result = fn()
    finally:
        builtins.open, os.open = real_open, real_os_open
    return count[0], result


def bench_planning(sequences: list[int], work_dir: Path | str) -> dict:
    """Planning figures for datasets of each size in ``sequences`` (see the module docstring).
    Returns {"machine", "raw_frames", "sizes": {N: figures}}."""
    from configs.schema import load_config
    from flows.bench.common import machine
    from flows.commands.simulate import simulate
    from flows.commands.status import print_plan
    from flows.pipeline.plan import PlanCosts, plan_run
    from storage.manifest import FingerprintCache, Manifest

    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    source = work / "source"
    if not (source / "timestamps").is_dir():
        simulate(
            source,
            sequences=1,
            frames=RAW_FRAMES,
            seed=3,
            pedestrians=2,
            crowd="uncrowded",
            progress=False,
            first_id=SOURCE_ID,
        )
    result: dict = {"machine": machine(), "raw_frames": RAW_FRAMES, "sizes": {}}
    for n in sequences:
        data, out = work / f"data-{n}", work / f"out-{n}"
        shutil.rmtree(out, ignore_errors=True)
        out.mkdir(parents=True)
        replicate_sequence(source, data, SOURCE_ID, list(range(n)))
        over = {"dataset.root": str(data), "output.root": str(out), "export.formats": []}
        config = load_config(None, over)
        args = ["--data", str(data), "--out", str(out), "--set", "export.formats=[]"]
        costs = PlanCosts()
        t0 = time.perf_counter()
        plans = plan_run(
            config, Manifest.load(out), FingerprintCache(out / ".cache" / "sequences"), costs=costs
        )
        first = time.perf_counter() - t0
        assert not any(p.error for p in plans), [p.error for p in plans if p.error][:3]
        rows = _complete_store(config, out)
        figures = {
            "sequences": n,
            "units": rows,
            "first_plan_s": first,
            "files_hashed": costs.files_hashed,
            "bytes_hashed": costs.bytes_hashed,
            "hash_mb_per_s": costs.hash_mb_per_s,
            "unique_mb": sum(f.stat().st_size for f in source.rglob("*") if f.is_file()) / 1e6,
        }
        figures["startup_s"] = _command(["config", "show"])[1]
        for name, argv in (
            ("status", ["status", *args]),
            ("dry_run", ["reprocess", "--dry-run", *args]),
            ("rebuild", ["rebuild", "--quiet", *args]),
        ):
            code, seconds, text = _command(argv)
            figures[f"{name}_s"], figures[f"{name}_exit"] = seconds, code
            figures[f"{name}_lines"] = len(text.splitlines())
        with contextlib.redirect_stdout(io.StringIO()):  # ``mobileocc status``, in this process
            opened, _ = _opened_during(lambda: print_plan(config), data)
        figures["files_opened_in_plan"] = opened
        figures.update(_manifest_costs(out))
        result["sizes"][n] = figures
    return result


def format_table(result: dict) -> str:
    m = result["machine"]
    lines = [
        f"machine: {m['cpu_model']} x{m['cpu_count']}, load {m['load_avg_1m']:.1f}; one sequence of "
        f"{result['raw_frames']} raw frames replicated by hard links",
        f"{'sequences':>9} {'first plan':>10} {'MB/s':>6} {'start-up':>8} {'status':>7} {'dry-run':>8} {'rebuild':>8} "
        f"{'opened':>6} {'manifest':>9} {'load':>6} {'save':>6} {'append':>7} {'rewrite/unit':>12}",
    ]
    for n, f in sorted(result["sizes"].items()):
        lines.append(
            f"{n:>9} {f['first_plan_s']:>9.1f}s {f['hash_mb_per_s'] or 0:>6.0f} {f['startup_s']:>7.1f}s "
            f"{f['status_s']:>6.1f}s "
            f"{f['dry_run_s']:>7.1f}s {f['rebuild_s']:>7.1f}s {f['files_opened_in_plan']:>6} "
            f"{f['manifest_mb']:>7.1f}MB {f['manifest_load_s']:>5.2f}s {f['manifest_save_s']:>5.2f}s "
            f"{f['journal_append_ms']:>5.2f}ms {f['full_rewrite_per_unit_run_s']:>11.0f}s"
        )
    return "\n".join(lines)
