"""``mobileocc bench``: what a (re)build costs on this machine, measured in one run.

``bench(quick, json_path, workers)`` makes a small synthetic dataset (flows/commands/simulate.py), runs the
six stages through ``flows.pipeline.run.execute_unit`` without Prefect (``run_local``) and times each
stage, then calls the other benchmark functions of the project in the same run:

- frames/s per stage and end to end (simulation excluded), at 0.2 m and, for fuse, at 0.05 m;
- peak RSS: ``resource.getrusage(RUSAGE_SELF).ru_maxrss`` of a fresh spawned process per measured
  stage run (stage runs each in their own process, so a peak is that stage's own, not the parent's);
  the fan-out figures also report ``RUSAGE_CHILDREN`` of the Dask worker processes' parent;
- person-fits/s of the fit stage (CPU; and CUDA when ``torch.cuda.is_available()``);
- free-space insertion vs octomap-python (flows/bench/occupancy.py ``bench_freespace``);
- store throughput vs raw numpy writes (flows/bench/storage.py ``bench_store``);
- the fuse stage's frame fan-out on a Dask LocalCluster with 1 vs ``workers`` worker processes
  (same frames, same output), speed-up computed here.

Ratios are computed inside the run. CPU counts, model name, memory and library versions go in the
JSON's ``machine``. Run: ``mobileocc bench [--quick] [--json FILE]``.
"""

from __future__ import annotations

import json
import os
import platform
import resource
import shutil
import tempfile
import time
from pathlib import Path

STAGE_ORDER = ("detect", "track", "fit", "map", "fuse", "export")


# ---- running the stages without Prefect ----------------------------------------------------------

def make_config(data_root: Path, out_root: Path, overrides: dict | None = None):
    """The default config pointed at ``data_root`` / ``out_root`` with dotted ``overrides``."""
    from configs.schema import load_config

    return load_config(overrides={"dataset.root": str(data_root), "output.root": str(out_root),
                                  **{k: v for k, v in (overrides or {}).items()}})


def run_local(config, stages=STAGE_ORDER, sequences: list[str] | None = None) -> dict:
    """Plan and run ``stages`` of every sequence in this process (no Prefect), recording each
    outcome and the resolved config in ``OUT/manifest.json`` as a flow run does. Stages left out
    are absent upstream (fuse with ``body_source: ground-truth`` needs no fit). Returns
    {(sequence, stage): outcome} with ``seconds`` per unit; raises on a failed unit."""
    from configs.schema import config_hash
    from flows.pipeline.dag import STAGES
    from flows.pipeline.inputs import runtime
    from flows.pipeline.plan import plan_run
    from flows.pipeline.run import _record, execute_unit
    from storage.manifest import FileHasher, Manifest

    out = Path(config.output.root)
    out.mkdir(parents=True, exist_ok=True)
    manifest = Manifest.load(out)
    manifest.meta.update({"config_hash": config_hash(config), "config": config.model_dump(mode="json")})
    outcomes: dict = {}
    for plan in plan_run(config, manifest, FileHasher(None), sequences=sequences):
        if plan.error:
            raise RuntimeError(f"sequence {plan.sequence}: {plan.error}")
        done: dict[str, dict] = {}
        for stage in STAGES:
            if stage not in stages:
                continue
            ups = {u: done[u] for u in STAGES[stage] if u in done}
            outcome = execute_unit(plan.units[stage], out, ups, plan.fingerprint, runtime(config))
            _record(manifest, outcome)
            if outcome["status"] != "done":
                raise RuntimeError(f"sequence {plan.sequence} stage {stage} {outcome['status']}: "
                                   f"{outcome.get('error')}\n{outcome.get('traceback', '')}")
            done[stage] = outcome
            outcomes[(plan.sequence, stage)] = outcome
    manifest.save()
    return outcomes


# ---- machine description -----------------------------------------------------------------------

def machine() -> dict:
    import numpy as np

    model = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem_gb = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                mem_gb = round(int(line.split()[1]) / 1024 ** 2, 1)
    except OSError:
        pass
    try:
        import torch

        torch_v, cuda = torch.__version__, torch.cuda.is_available()
        gpu = torch.cuda.get_device_name(0) if cuda else None
    except ImportError:  # pragma: no cover
        torch_v, cuda, gpu = None, False, None
    return {"cpu_count": os.cpu_count(), "cpu_affinity": len(os.sched_getaffinity(0)),
            "cpu_model": model, "memory_gb": mem_gb, "load_avg_1m": os.getloadavg()[0],
            "platform": platform.platform(), "python": platform.python_version(),
            "numpy": np.__version__, "torch": torch_v, "cuda": cuda, "gpu": gpu}


# ---- measurements ------------------------------------------------------------------------------

def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _spawned(fn, *args):
    """``fn(*args)`` in a fresh spawned process: its peak RSS is its own."""
    import multiprocessing as mp

    with mp.get_context("spawn").Pool(1) as pool:
        return pool.apply(fn, args)


def _stage_in_process(data_root: str, out_root: str, overrides: dict, stages: tuple) -> dict:
    """Run some stages in this (fresh) process; per stage wall / CPU seconds, peak RSS after it."""
    cfg = make_config(Path(data_root), Path(out_root), overrides)
    res = {}
    for stage in stages:
        c0, t0 = time.process_time(), time.perf_counter()
        outcomes = run_local(cfg, stages=_with_upstream(stage))
        res[stage] = {"wall_s": sum(o["seconds"] for (s, st), o in outcomes.items() if st == stage),
                      "cpu_s": time.process_time() - c0, "total_wall_s": time.perf_counter() - t0,
                      "peak_rss_mb": _peak_rss_mb()}
    return res


def _with_upstream(stage: str) -> tuple:
    """``stage`` and everything before it in STAGE_ORDER (earlier ones are cached in the manifest:
    execute_unit returns a finished key folder at once)."""
    return STAGE_ORDER[: STAGE_ORDER.index(stage) + 1]


def _fuse_fanout(data_root: str, out_root: str, overrides: dict, n_workers: int) -> dict:
    """The fuse stage with its frame chunks on a LocalCluster of ``n_workers`` processes."""
    from distributed import Client, LocalCluster

    from flows.pipeline.inputs import fuse_inputs, sequence_ref
    from flows.stages.common import StageContext
    from flows.stages.fuse import run_fuse
    from storage.manifest import Manifest

    cfg = make_config(Path(data_root), Path(out_root), overrides)
    inputs = fuse_inputs(cfg)
    man = Manifest.load(Path(out_root))
    seq = cfg.dataset.sequences[0] if isinstance(cfg.dataset.sequences, list) else "0"
    ups = {s: Path(out_root) / man.get(seq, s).location for s in ("detect", "map")}
    with LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True, dashboard_address=None) as cl, \
            Client(cl) as client:
        def unit():
            work = Path(tempfile.mkdtemp(dir=out_root))
            try:
                run_fuse(StageContext(sequence_ref(cfg, seq), inputs, Path(out_root), work, ups, key="bench"))
            finally:
                shutil.rmtree(work, ignore_errors=True)
        client.run(lambda: __import__("flows.stages.fuse"))  # imports on every worker, outside the timing
        t0 = time.perf_counter()
        client.submit(unit, pure=False).result()
        wall = time.perf_counter() - t0
        rss = client.run(lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)
    return {"workers": n_workers, "wall_s": wall, "worker_peak_rss_mb": max(rss.values())}


def _fit_rate(data_root: str, out_root: str, overrides: dict, device: str) -> dict:
    """Person-fits/s of the fit kernel on the track product's rows (one batch, after a warm-up)."""
    import numpy as np

    from flows.pipeline.inputs import fit_inputs, sequence_ref
    from flows.stages.fit import fit_batch
    from storage.manifest import Manifest
    from storage.products import Tracks

    cfg = make_config(Path(data_root), Path(out_root), {**overrides, "fit.device": device})
    inputs, man, seq = fit_inputs(cfg), Manifest.load(Path(out_root)), "0"
    tracks_dir = Path(out_root) / man.get(seq, "track").location
    rows = np.flatnonzero(Tracks.read(tracks_dir).gt_index >= 0).tolist()
    if not rows:
        return {"device": device, "persons": 0, "note": "no tracked person to fit"}
    args = (sequence_ref(cfg, seq), inputs, Path(out_root), tracks_dir)
    fit_batch(*args, rows[:1])  # warm-up
    t0 = time.perf_counter()
    fit_batch(*args, rows)
    wall = time.perf_counter() - t0
    return {"device": device, "persons": len(rows), "iterations": cfg.fit.iterations, "wall_s": wall,
            "fits_per_s": len(rows) / wall, "peak_rss_mb": _peak_rss_mb()}


def bench(quick: bool, json_path: Path | None, workers: int = 2, work_dir: Path | None = None) -> dict:
    """Measure everything listed in the module docstring; print a table; write JSON when asked.
    ``quick``: 1 sequence of 12 raw frames (6 at 5 Hz), few fit iterations; else 1 x 40 frames."""
    import torch

    from flows.bench.occupancy import bench_freespace
    from flows.bench.storage import bench_store
    from flows.commands.simulate import simulate

    raw_frames = 12 if quick else 40
    fit_iters = 30 if quick else 150
    work = Path(tempfile.mkdtemp(prefix="mobileocc-bench-", dir=work_dir))
    started = time.perf_counter()
    result: dict = {"quick": quick, "machine": machine(),
                    "how_measured": {
                        "frames_per_s": "frames at 5 Hz / wall seconds of the stage's execute_unit (one "
                                        "process, frame fan-out inline); CPU seconds beside it",
                        "peak_rss_mb": "resource.getrusage(RUSAGE_SELF).ru_maxrss of a fresh spawned process "
                                       "that ran the stage (and its cached upstream) only",
                        "speedup": "wall of the fuse stage with frame chunks on a LocalCluster of 1 vs N "
                                   "worker processes (1 thread each), after a warm-up run"}}
    try:
        data = work / "data"
        t0 = time.perf_counter()
        simulate(data, sequences=1, frames=raw_frames, seed=11, pedestrians=3, crowd="uncrowded", progress=False)
        result["simulate_s"] = time.perf_counter() - t0
        frames = raw_frames // 2
        over = {"fit.iterations": fit_iters, "output.frames_per_chunk": 2}
        stages: dict = {}
        out02 = work / "out-0.2"
        per = _spawned(_stage_in_process, str(data), str(out02), over, STAGE_ORDER)
        for st, v in per.items():
            stages[st] = {**v, "frames": frames, "frames_per_s": frames / v["wall_s"] if v["wall_s"] else None}
        total = sum(v["wall_s"] for v in per.values())
        result["stages_0.2m"] = stages
        result["end_to_end_0.2m"] = {"frames": frames, "wall_s": total, "frames_per_s": frames / total}
        # fuse at 0.05 m (map and earlier are the same stage keys -> reused from the 0.2 m run)
        out005 = work / "out-0.05"
        shutil.copytree(out02, out005, ignore=shutil.ignore_patterns("fuse", "export", "occupancy", "tables"))
        (out005 / "manifest.json").unlink(missing_ok=True)
        fine = {**over, "fuse.grid.voxel_size_m": 0.05}
        per_fine = _spawned(_stage_in_process, str(data), str(out005), fine, ("fuse",))
        f = per_fine["fuse"]
        result["fuse_0.05m"] = {**f, "frames": frames, "frames_per_s": frames / f["wall_s"],
                                "note": "includes detect/track/fit/map rerun in the same process when their "
                                        "keys were not found (see total_wall_s); wall_s is fuse alone"}
        # person fits
        fitted = json.loads(next((out02 / "stages" / "fit").glob("*/*/summary.json")).read_text()).get("fitted", 0)
        fits = {"cpu": {"device": "cpu", "persons": fitted, "iterations": fit_iters, "wall_s": per["fit"]["wall_s"],
                        "fits_per_s": fitted / per["fit"]["wall_s"], "source": "the fit stage run above"}}
        if torch.cuda.is_available():
            fits["cuda"] = _spawned(_fit_rate, str(data), str(out02), over, "cuda")
            fits["cuda_over_cpu"] = fits["cuda"]["fits_per_s"] / fits["cpu"]["fits_per_s"]
        result["person_fits"] = fits
        # fan-out speed-up of fuse
        one = _fuse_fanout(str(data), str(out02), over, 1)
        many = _fuse_fanout(str(data), str(out02), over, workers)
        result["fuse_fanout"] = {"1": one, str(workers): many, "speedup": one["wall_s"] / many["wall_s"],
                                 "frames": frames, "chunks": -(-frames // 2)}
        result["freespace_vs_octomap"] = _spawned(bench_freespace, quick)
        result["store_vs_numpy"] = _spawned(bench_store, quick)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    result["bench_wall_s"] = time.perf_counter() - started
    print(format_table(result))
    if json_path is not None:
        from flows.commands.report import to_jsonable

        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
        Path(json_path).write_text(json.dumps(to_jsonable(result), indent=1) + "\n")
    return result


def format_table(r: dict) -> str:
    """The headline figures as an aligned text table."""
    m = r["machine"]
    lines = [f"machine: {m['cpu_model']} x{m['cpu_count']} cpus, {m['memory_gb']} GB, python {m['python']}, "
             f"numpy {m['numpy']}, torch {m['torch']} (cuda {m['cuda']}), load {m['load_avg_1m']:.1f}",
             f"{'measure':<34}{'value':>14}  {'detail'}"]

    def row(name, value, detail=""):
        v = "n/a" if value is None else (f"{value:.3g}" if isinstance(value, float) else str(value))
        lines.append(f"{name:<34}{v:>14}  {detail}")

    for st, v in r.get("stages_0.2m", {}).items():
        row(f"{st} frames/s (0.2 m)", v["frames_per_s"], f"wall {v['wall_s']:.1f} s, peak RSS {v['peak_rss_mb']:.0f} MB")
    if "end_to_end_0.2m" in r:
        row("end to end frames/s (0.2 m)", r["end_to_end_0.2m"]["frames_per_s"], f"{r['end_to_end_0.2m']['frames']} frames")
    if "fuse_0.05m" in r:
        row("fuse frames/s (0.05 m)", r["fuse_0.05m"]["frames_per_s"], f"peak RSS {r['fuse_0.05m']['peak_rss_mb']:.0f} MB")
    for dev, v in r.get("person_fits", {}).items():
        if isinstance(v, dict):
            row(f"person fits/s ({dev})", v.get("fits_per_s"), f"{v.get('persons')} persons, {v.get('iterations')} iterations")
    if "fuse_fanout" in r:
        fo = r["fuse_fanout"]
        row("fuse fan-out speed-up 1 -> N", fo["speedup"], f"{fo['1']['wall_s']:.1f} s -> "
            f"{[v for k, v in fo.items() if k not in ('1', 'speedup', 'frames', 'chunks')][0]['wall_s']:.1f} s")
    fs = r.get("freespace_vs_octomap") or {}
    for k, v in fs.items():
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            row(f"freespace {k}", float(v))
    st = r.get("store_vs_numpy") or {}
    for part, d in st.items():
        if isinstance(d, dict):
            for k, v in d.items():
                if isinstance(v, (int, float)) and not isinstance(v, bool) and ("ratio" in k or "per_s" in k or "speed" in k):
                    row(f"store {part} {k}", float(v))
    row("bench wall s", r.get("bench_wall_s"))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:  # pragma: no cover - the CLI calls bench()
    import argparse

    p = argparse.ArgumentParser(prog="mobileocc bench", description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--workers", type=int, default=2)
    a = p.parse_args(argv)
    bench(a.quick, a.json, a.workers)

