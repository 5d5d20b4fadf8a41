"""``mobileocc bench``: what a (re)build costs on this machine, measured in one run.

``bench(quick, json_path, workers)`` makes a small synthetic dataset (flows/commands/simulate.py),
runs the six stages through the pipeline's runner without Prefect (flows.pipeline.units.run_units,
inline; flows/bench/common.py ``run_stages``) and times each stage, then calls the other benchmark
functions of the project in the same run:

- frames/s per stage and end to end (simulation excluded), at 0.2 m and, for fuse, at 0.05 m;
- peak RSS: ``resource.getrusage(RUSAGE_SELF).ru_maxrss`` of a fresh spawned process per measured
  stage run (stage runs each in their own process, so a peak is that stage's own, not the parent's);
  the fan-out figures also report ``RUSAGE_CHILDREN`` of the Dask worker processes' parent;
- person-fits/s of the fit stage (CPU; and CUDA when ``torch.cuda.is_available()``);
- free-space insertion vs octomap-python (flows/bench/occupancy.py ``bench_freespace``);
- store throughput vs raw numpy writes (flows/bench/storage.py ``bench_store``);
- the fuse stage's frame fan-out on a Dask LocalCluster with 1 vs ``workers`` worker processes
  (same frames, same output), speed-up computed here;
- map + fuse seconds per frame over octomap-python's ``insertPointCloud`` seconds per scan of the
  bench sequence's own sweeps (the speed issue's target: <= 0.2), and the top costs inside map
  and fuse (a cProfile rerun of each; library time charged to the calling function of ours).

Ratios are computed inside the run. CPU counts, model name, memory and library versions go in the
JSON's ``machine``. Run: ``mobileocc bench [--quick] [--json FILE]``; ``mobileocc bench scale``
runs the scale benchmark instead (flows/bench/scale.py).
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from pathlib import Path

from flows.bench.common import machine, make_config, peak_rss_mb, run_stages, spawned
from flows.pipeline.dag import STAGES

STAGE_ORDER = tuple(STAGES)


# ---- measurements ------------------------------------------------------------------------------


def _stage_in_process(data_root: str, out_root: str, overrides: dict, stages: tuple) -> dict:
    """Run some stages in this (fresh) process; per stage wall / CPU seconds, peak RSS after it."""
    cfg = make_config(Path(data_root), Path(out_root), overrides)
    res = {}
    for stage in stages:
        c0, t0 = time.process_time(), time.perf_counter()
        outcomes = run_stages(cfg, _with_upstream(stage)).outcomes
        res[stage] = {
            "wall_s": sum(o.seconds for (s, st), o in outcomes.items() if st == stage),
            "cpu_s": time.process_time() - c0,
            "total_wall_s": time.perf_counter() - t0,
            "peak_rss_mb": peak_rss_mb(),
        }
    return res


def _with_upstream(stage: str) -> tuple:
    """``stage`` and every stage before it (the earlier ones are fresh in the manifest: the runner
    takes them from the cache)."""
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
    with (
        LocalCluster(
            n_workers=n_workers, threads_per_worker=1, processes=True, dashboard_address=None
        ) as cl,
        Client(cl) as client,
    ):

        def unit():
            work = Path(tempfile.mkdtemp(dir=out_root))
            try:
                run_fuse(
                    StageContext(
                        sequence_ref(cfg, seq), inputs, Path(out_root), work, ups, key="bench"
                    )
                )
            finally:
                shutil.rmtree(work, ignore_errors=True)

        client.run(
            lambda: __import__("flows.stages.fuse")
        )  # imports on every worker, outside the timing
        t0 = time.perf_counter()
        client.submit(unit, pure=False).result()
        wall = time.perf_counter() - t0
        rss = client.run(peak_rss_mb)
    return {"workers": n_workers, "wall_s": wall, "worker_peak_rss_mb": max(rss.values())}


def _octomap_same_scans(data_root: str, out_root: str, overrides: dict) -> dict:
    """octomap-python's insertPointCloud on the bench sequence's own sweeps (world frame, from the
    LiDAR centre, the map stage's free-space voxel size and range): seconds per scan."""
    import numpy as np

    from flows.bench.occupancy import octomap_seconds_per_scan
    from flows.pipeline.inputs import open_sequence
    from tasks.geometry import transform_points

    cfg = make_config(Path(data_root), Path(out_root), overrides)
    seq = open_sequence(cfg, "0")
    scans = []
    for i in range(len(seq)):
        f = seq.frame(i)
        scans.append(
            (transform_points(f.T_world_from_lidar, f.points_lidar), f.T_world_from_lidar[:3, 3])
        )
    fs = cfg.map.freespace
    return {
        "scans": len(scans),
        "points_per_scan": float(np.mean([len(p) for p, _ in scans])),
        "voxel_size_m": fs.voxel_size_m,
        "max_range_m": fs.max_range_m,
        **octomap_seconds_per_scan(scans, fs.voxel_size_m, fs.max_range_m),
    }


#: code whose functions the stage breakdown names (time in libraries is charged to the caller)
_OWN_CODE = ("/tasks/", "/storage/", "/flows/stages/")


def _stage_costs(
    data_root: str, out_root: str, overrides: dict, stages=("map", "fuse"), top: int = 6
) -> dict:
    """Rerun stages (their upstream products reused) under cProfile timing process CPU: per stage
    the functions of our code with the most CPU, each charged with its own plus that of the
    library calls it makes (numpy, scipy, torch, zlib; a wait on its worker threads is charged
    the CPU those threads use meanwhile). CPU seconds per frame and share of the stage's CPU."""
    import cProfile
    import pstats

    from flows.pipeline.dag import STAGES
    from flows.pipeline.inputs import INPUTS, open_sequence, sequence_ref
    from flows.stages import STAGE_FUNCTIONS
    from flows.stages.common import StageContext
    from storage.manifest import Manifest

    cfg = make_config(Path(data_root), Path(out_root), overrides)
    man = Manifest.load(Path(out_root))
    seq = "0"
    frames = len(open_sequence(cfg, seq))
    result = {}
    for stage in stages:
        ups = {
            u: Path(out_root) / man.get(seq, u).location for u in STAGES[stage] if man.get(seq, u)
        }

        def context(work: Path, key: str) -> StageContext:
            return StageContext(
                sequence_ref(cfg, seq), INPUTS[stage](cfg), Path(out_root), work, ups, key=key
            )

        STAGE_FUNCTIONS[stage](
            context(Path(tempfile.mkdtemp(dir=out_root)), "warm-up")
        )  # JIT caches, imports
        work = Path(tempfile.mkdtemp(dir=out_root))
        prof = cProfile.Profile(time.process_time)
        t0, c0 = time.perf_counter(), time.process_time()
        prof.enable()
        STAGE_FUNCTIONS[stage](context(work, "profile"))
        prof.disable()
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        costs = _charge_to_own_code(pstats.Stats(prof))
        ranked = sorted(costs.items(), key=lambda kv: -kv[1])[:top]
        result[stage] = {
            "frames": frames,
            "profiled_wall_s": wall,
            "profiled_cpu_s": cpu,
            "top": [
                {"function": name, "cpu_s_per_frame": sec / frames, "share": sec / cpu}
                for name, sec in ranked
            ],
        }
    return result


def _charge_to_own_code(stats) -> dict[str, float]:
    """{'path:function': seconds}: every profiled function's own time, charged to our code: a
    function of ours keeps its own time; a library function's time is split over its callers in
    proportion to the time each call path spent in it, up to the first functions of ours."""
    table = stats.stats  # func -> (cc, nc, tottime, cumtime, callers {func: (cc, nc, tt, ct)})
    memo: dict = {}

    def own(func) -> bool:
        return any(part in func[0] for part in _OWN_CODE)

    def owners(func, stack=()) -> dict:
        if own(func):
            return {func: 1.0}
        if func in memo:
            return memo[func]
        callers = table.get(func, (0, 0, 0, 0, {}))[4]
        total = sum(v[3] for c, v in callers.items() if c not in stack)
        share: dict = {}
        if total > 0:
            for c, v in callers.items():
                if c in stack or v[3] <= 0:
                    continue
                for o, w in owners(c, stack + (func,)).items():
                    share[o] = share.get(o, 0.0) + w * v[3] / total
        memo[func] = share
        return share

    def name(func) -> str:
        path = func[0]
        for part in _OWN_CODE:
            if part in path:
                path = part.strip("/") + "/" + path.split(part, 1)[1]
        return f"{path}:{func[2]}"

    costs: dict[str, float] = {}
    for func, (_, _, tottime, _, _) in table.items():
        for o, w in owners(func).items():
            costs[name(o)] = costs.get(name(o), 0.0) + w * tottime
    return costs


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
    return {
        "device": device,
        "persons": len(rows),
        "iterations": cfg.fit.iterations,
        "wall_s": wall,
        "fits_per_s": len(rows) / wall,
        "peak_rss_mb": peak_rss_mb(),
    }


def bench(
    quick: bool, json_path: Path | None, workers: int = 2, work_dir: Path | None = None
) -> dict:
    """Measure everything listed in the module docstring; print a table; write JSON when asked.

    The pipeline runs with the default config (fit iterations and all) on a demo-like crowded
    sequence (8 pedestrians, as ``make demo``): ``quick`` 20 raw frames (10 at 5 Hz), else 60."""
    import torch

    from flows.bench.occupancy import bench_freespace
    from flows.bench.storage import bench_store
    from flows.commands.simulate import simulate

    raw_frames = 20 if quick else 60
    work = Path(tempfile.mkdtemp(prefix="mobileocc-bench-", dir=work_dir))
    started = time.perf_counter()
    result: dict = {
        "quick": quick,
        "machine": machine(),
        "how_measured": {
            "frames_per_s": "frames at 5 Hz / wall seconds of the stage's execute_unit (one "
            "process, frame fan-out inline); CPU seconds beside it",
            "peak_rss_mb": "resource.getrusage(RUSAGE_SELF).ru_maxrss of a fresh spawned process "
            "that ran the stage (and its cached upstream) only",
            "speedup": "wall of the fuse stage with frame chunks on a LocalCluster of 1 vs N "
            "worker processes (1 thread each), after a warm-up run",
        },
    }
    try:
        data = work / "data"
        t0 = time.perf_counter()
        simulate(
            data,
            sequences=1,
            frames=raw_frames,
            seed=11,
            pedestrians=8,
            crowd="crowded",
            progress=False,
        )
        result["simulate_s"] = time.perf_counter() - t0
        frames = raw_frames // 2
        over = {"output.frames_per_chunk": 2}  # several write units, for the fan-out figures
        stages: dict = {}
        out02 = work / "out-0.2"
        per = spawned(_stage_in_process, str(data), str(out02), over, STAGE_ORDER)
        for st, v in per.items():
            stages[st] = {
                **v,
                "frames": frames,
                "frames_per_s": frames / v["wall_s"] if v["wall_s"] else None,
            }
        total = sum(v["wall_s"] for v in per.values())
        result["stages_0.2m"] = stages
        result["end_to_end_0.2m"] = {
            "frames": frames,
            "wall_s": total,
            "frames_per_s": frames / total,
        }
        # fuse at 0.05 m (map and earlier are the same stage keys -> reused from the 0.2 m run)
        out005 = work / "out-0.05"
        shutil.copytree(
            out02, out005, ignore=shutil.ignore_patterns("fuse", "export", "occupancy", "tables")
        )
        (out005 / "manifest.json").unlink(missing_ok=True)
        fine = {**over, "fuse.grid.voxel_size_m": 0.05}
        per_fine = spawned(_stage_in_process, str(data), str(out005), fine, ("fuse",))
        f = per_fine["fuse"]
        result["fuse_0.05m"] = {
            **f,
            "frames": frames,
            "frames_per_s": frames / f["wall_s"],
            "note": "includes detect/track/fit/map rerun in the same process when their "
            "keys were not found (see total_wall_s); wall_s is fuse alone",
        }
        # person fits
        fitted = json.loads(
            next((out02 / "stages" / "fit").glob("*/*/summary.json")).read_text()
        ).get("fitted", 0)
        fits = {
            "cpu": {
                "device": "cpu",
                "persons": fitted,
                "iterations": make_config(data, out02).fit.iterations,
                "wall_s": per["fit"]["wall_s"],
                "fits_per_s": fitted / per["fit"]["wall_s"],
                "source": "the fit stage run above",
            }
        }
        if torch.cuda.is_available():
            fits["cuda"] = spawned(_fit_rate, str(data), str(out02), over, "cuda")
            fits["cuda_over_cpu"] = fits["cuda"]["fits_per_s"] / fits["cpu"]["fits_per_s"]
        result["person_fits"] = fits
        # fan-out speed-up of fuse
        one = _fuse_fanout(str(data), str(out02), over, 1)
        many = _fuse_fanout(str(data), str(out02), over, workers)
        result["fuse_fanout"] = {
            "1": one,
            str(workers): many,
            "speedup": one["wall_s"] / many["wall_s"],
            "frames": frames,
            "chunks": -(-frames // 2),
        }
        result["freespace_vs_octomap"] = spawned(bench_freespace, quick)
        # the target: map + fuse per frame <= 0.2 x octomap's insertPointCloud of the
        # same scan (the bench sequence's sweeps, same run): wall seconds on both sides, and
        # process CPU seconds (less sensitive to other load on the machine; ours counts all threads)
        octo = spawned(_octomap_same_scans, str(data), str(out02), over)
        map_fuse = (per["map"]["wall_s"] + per["fuse"]["wall_s"]) / frames
        map_fuse_cpu = (per["map"]["cpu_s"] + per["fuse"]["cpu_s"]) / frames
        result["map_fuse_vs_octomap"] = {
            "map_s_per_frame": per["map"]["wall_s"] / frames,
            "fuse_s_per_frame": per["fuse"]["wall_s"] / frames,
            "map_fuse_s_per_frame": map_fuse,
            "map_fuse_frames_per_s": 1.0 / map_fuse,
            "octomap_insert_s_per_scan": octo["wall_s"],
            "ratio": map_fuse / octo["wall_s"],
            "map_fuse_cpu_s_per_frame": map_fuse_cpu,
            "octomap_insert_cpu_s_per_scan": octo["cpu_s"],
            "ratio_cpu": map_fuse_cpu / octo["cpu_s"],
            "octomap": octo,
            "target_ratio": 0.2,
            "note": "stage seconds include the stage's fixed costs (process start-up of its kernels, "
            "sequence-level reads and writes) spread over the bench's few frames",
        }
        result["stage_costs"] = spawned(_stage_costs, str(data), str(out02), over)
        result["store_vs_numpy"] = spawned(bench_store, quick)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    result["bench_wall_s"] = time.perf_counter() - started
    print(format_table(result))
    if json_path is not None:
        from flows.commands.report import write_json

        write_json(json_path, result)
    return result


def format_table(r: dict) -> str:
    """The headline figures as an aligned text table."""
    m = r["machine"]
    lines = [
        f"machine: {m['cpu_model']} x{m['cpu_count']} cpus, {m['memory_gb']} GB, python {m['python']}, "
        f"numpy {m['numpy']}, torch {m['torch']} (cuda {m['cuda']}), load {m['load_avg_1m']:.1f}",
        f"{'measure':<34}{'value':>14}  {'detail'}",
    ]

    def row(name, value, detail=""):
        v = "n/a" if value is None else (f"{value:.3g}" if isinstance(value, float) else str(value))
        lines.append(f"{name:<34}{v:>14}  {detail}")

    for st, v in r.get("stages_0.2m", {}).items():
        row(
            f"{st} frames/s (0.2 m)",
            v["frames_per_s"],
            f"wall {v['wall_s']:.1f} s, peak RSS {v['peak_rss_mb']:.0f} MB",
        )
    if "end_to_end_0.2m" in r:
        row(
            "end to end frames/s (0.2 m)",
            r["end_to_end_0.2m"]["frames_per_s"],
            f"{r['end_to_end_0.2m']['frames']} frames",
        )
    if "fuse_0.05m" in r:
        row(
            "fuse frames/s (0.05 m)",
            r["fuse_0.05m"]["frames_per_s"],
            f"peak RSS {r['fuse_0.05m']['peak_rss_mb']:.0f} MB",
        )
    for dev, v in r.get("person_fits", {}).items():
        if isinstance(v, dict):
            row(
                f"person fits/s ({dev})",
                v.get("fits_per_s"),
                f"{v.get('persons')} persons, {v.get('iterations')} iterations",
            )
    mf = r.get("map_fuse_vs_octomap")
    if mf:
        row(
            "(map + fuse) / octomap scan, wall",
            mf["ratio"],
            f"{mf['map_fuse_s_per_frame']:.3f} s/frame vs octomap "
            f"{mf['octomap_insert_s_per_scan']:.3f} s/scan (target <= {mf['target_ratio']})",
        )
        row(
            "(map + fuse) / octomap scan, cpu",
            mf["ratio_cpu"],
            f"{mf['map_fuse_cpu_s_per_frame']:.3f} s/frame vs "
            f"octomap {mf['octomap_insert_cpu_s_per_scan']:.3f} s/scan",
        )
    for st, v in (r.get("stage_costs") or {}).items():
        for item in v["top"]:
            row(
                f"{st} cost cpu s/frame",
                item["cpu_s_per_frame"],
                f"{item['function']} ({100 * item['share']:.0f} %)",
            )
    if "fuse_fanout" in r:
        fo = r["fuse_fanout"]
        row(
            "fuse fan-out speed-up 1 -> N",
            fo["speedup"],
            f"{fo['1']['wall_s']:.1f} s -> "
            f"{[v for k, v in fo.items() if k not in ('1', 'speedup', 'frames', 'chunks')][0]['wall_s']:.1f} s",
        )
    fs = r.get("freespace_vs_octomap") or {}
    for k, v in fs.items():
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            row(f"freespace {k}", float(v))
    st = r.get("store_vs_numpy") or {}
    for part, d in st.items():
        if isinstance(d, dict):
            for k, v in d.items():
                if (
                    isinstance(v, (int, float))
                    and not isinstance(v, bool)
                    and ("ratio" in k or "per_s" in k or "speed" in k)
                ):
                    row(f"store {part} {k}", float(v))
    row("bench wall s", r.get("bench_wall_s"))
    return "\n".join(lines)
