"""``mobileocc bench scale``: what a 116k-frame rebuild costs, measured in one run of minutes.

Parts (``parts``), each in its own spawned process where it matters:

- ``simulator``: default vs ``--fast`` simulator on a long sequence (flows/bench/simulator.py).
- ``long``: one long sequence (``simulate --fast``, every 2nd raw frame: the 5 Hz frames the
  pipeline keeps) cut by hard links into sequences of ``frames`` 5 Hz frames (same scene, same
  density); each through the six stages, every stage in a process forked from a runner that has
  imported everything: ``peak_rss_mb`` is the stage process's peak (ru_maxrss), ``baseline_rss_mb``
  its RSS when it starts (the runner's pages the fork maps), ``stage_rss_mb`` = peak - baseline,
  what the stage itself holds; wall and CPU seconds per frame.
  ``fit.iterations`` is LONG_FIT_ITERATIONS here (the fit's memory is per batch and its time per
  person-frame: its default cost comes from the ``cost`` part).
- ``cost``: the shortest of those sequences through the six stages with the default settings:
  CPU and wall seconds per frame per stage, the figures the projection multiplies.
- ``memory``: peak RSS of the map and fuse stages at MEMORY_FRAMES frames on a synthetic strip
  of constant density (flows/bench/memory.py ``bench_memory``; ``mobileocc bench memory --untiled``
  adds the whole-sequence map for comparison):
  the tiled map's bound on memory at real sequence lengths (the ``long`` part cannot reach them:
  it runs every stage, the fit included).
- ``planning``: plan / status / dry-run seconds and hashing MB/s vs sequences
  (flows/bench/planning.py ``bench_planning``).
- ``cluster``: ``mobileocc rebuild --address`` against a real ``dask scheduler`` + ``dask worker
  --nworkers N --nthreads 1`` on loopback, N in ``cluster_workers``, on CLUSTER_SEQUENCES copies
  of a CLUSTER_FRAMES-frame sequence: wall speed-up T(1) / T(N) (bounded by the machine's free
  cores) and, from the scheduler's task stream, ``busy`` = compute seconds / (N x wall), the
  share of N worker threads the run kept busy; ``speedup_dedicated`` = N busy(N) / busy(1) is the
  speed-up on N cores of their own (what the projection uses).
- ``projection``: wall time of DATASET_FRAMES frames on N workers = frames x (the ``cost`` part's
  CPU seconds per frame) / S(N), S(N) = ``speedup_dedicated`` measured for N <= the machine's
  cores and extrapolated beyond with Amdahl's law fitted to those points; never less than the critical
  path of one sequence of SEQUENCE_FRAMES frames through its serial stages (track and map are one
  task per sequence), at the per-frame cost of the longest ``long`` run.

"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from flows.bench.common import machine, make_config, run_stages, spawned
from flows.bench.planning import (
    SOURCE_ID,  # the simulated long sequence's id (a number no copy takes)
)
from flows.pipeline.dag import STAGES
from storage.atomic import atomic_write_text

DEFAULT_FRAMES = (10, 20, 40)
DEFAULT_SEQUENCES = (10, 100, 1000)
DEFAULT_CLUSTER_WORKERS = (1, 2, 4)
PROJECT_WORKERS = (1, 8, 32, 128)
#: the paper's dataset, and the mean length of its sequences (CODa: 23 sequences)
DATASET_FRAMES = 116_000
SEQUENCE_FRAMES = 5_000
LONG_FIT_ITERATIONS = 10
CLUSTER_SEQUENCES = 4
CLUSTER_FRAMES = 6
PARTS = ("simulator", "long", "cost", "memory", "planning", "cluster")
#: sequence lengths (5 Hz frames) of the ``memory`` part
MEMORY_FRAMES = (200, 1000, 2000)
SERIAL_STAGES = ("track", "map")


# ---- datasets made of hard links -------------------------------------------------------------------


def link_sequence(
    src_root: Path, src_id: int, dst_root: Path, dst_id: int, raw_frames: int | None = None
) -> int:
    """Hard-link sequence ``src_id`` of ``src_root`` into ``dst_root`` as ``dst_id``; with
    ``raw_frames``, only the frame files below that raw frame, and the timestamps / poses cut
    there. Text files (timestamps, poses, metadata) are written, not linked. Returns the files."""
    from storage.coda import frame_number

    sid, n = str(src_id), 0
    for p in sorted(Path(src_root).rglob("*")):
        rel = str(p.relative_to(src_root))
        if not p.is_file() or sid not in rel:
            continue
        frame = (
            frame_number(p)
            if p.parent.name == sid and p.parent.parent.name != "calibrations"
            else None
        )
        if p.parent.name == sid and p.parent.parent.name == "gt" and p.name.startswith("gt_"):
            frame = int(p.stem.rsplit("_", 1)[1])
        if raw_frames is not None and frame is not None and frame >= raw_frames:
            continue
        target = Path(dst_root) / rel.replace(f"/{sid}/", f"/{dst_id}/").replace(
            f"_{sid}_", f"_{dst_id}_"
        ).replace(f"/{sid}.", f"/{dst_id}.")
        target.parent.mkdir(parents=True, exist_ok=True)
        if p.parent.name in ("timestamps", "dense_global"):
            lines = p.read_text().splitlines(keepends=True)
            atomic_write_text(
                target, "".join(lines[:raw_frames] if raw_frames is not None else lines)
            )
        elif p.parent.name == "metadata":
            atomic_write_text(
                target,
                p.read_text().replace(f"/{sid}/", f"/{dst_id}/").replace(f"_{sid}_", f"_{dst_id}_"),
            )
        else:
            os.link(p, target)
        n += 1
    return n


# ---- stages with per-stage peak RSS ----------------------------------------------------------------


def _run_stages_forked(data_root: str, out_root: str, overrides: dict) -> dict:
    """In a fresh (spawned) runner: import everything, then run the one sequence through the
    pipeline's runner, each stage in a forked child (flows/bench/forked.py); per stage wall / CPU
    seconds, the child's peak RSS and the runner's baseline."""
    import flows.stages  # noqa: F401  (every stage module and its kernels, before the forks)
    from flows.bench.forked import ForkedUnits

    forked = ForkedUnits()
    report = run_stages(
        make_config(Path(data_root), Path(out_root), overrides), tuple(STAGES), forked
    )
    (plan,) = report.plans
    res: dict = {"frames": plan.num_frames}
    n = max(1, plan.num_frames)
    for stage, msg in forked.measured.items():
        res[stage] = {
            "wall_s": msg["wall_s"],
            "cpu_s": msg["cpu_s"],
            "wall_s_per_frame": msg["wall_s"] / n,
            "cpu_s_per_frame": msg["cpu_s"] / n,
            "peak_rss_mb": msg["peak_rss_mb"],
            "baseline_rss_mb": msg["start_rss_mb"],
            "stage_rss_mb": msg["peak_rss_mb"] - msg["start_rss_mb"],
        }
    return res


# ---- the loopback Dask cluster -------------------------------------------------------------------


def _dask_cli() -> list[str]:
    exe = Path(sys.executable).parent / "dask"
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "dask"]


@contextlib.contextmanager
def loopback_cluster(n_workers: int, work: Path, memory_limit: str = "3GiB", threads: int = 1):
    """A ``dask scheduler`` and ``dask worker --nworkers n --nthreads threads`` on 127.0.0.1;
    yields the scheduler address once every worker has joined."""
    from distributed import Client

    work.mkdir(parents=True, exist_ok=True)
    sched_file = work / f"scheduler-{n_workers}.json"
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(
            [str(Path(__file__).resolve().parents[2]), os.environ.get("PYTHONPATH", "")]
        ).rstrip(os.pathsep),
    }
    log = open(work / f"cluster-{n_workers}.log", "w")
    procs = [
        subprocess.Popen(
            [
                *_dask_cli(),
                "scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                "0",
                "--no-dashboard",
                "--scheduler-file",
                str(sched_file),
            ],
            stdout=log,
            stderr=subprocess.STDOUT,
            env=env,
        )
    ]
    try:
        for _ in range(600):
            if sched_file.exists() and sched_file.stat().st_size:
                break
            time.sleep(0.1)
        address = json.loads(sched_file.read_text())["address"]
        procs.append(
            subprocess.Popen(
                [
                    *_dask_cli(),
                    "worker",
                    address,
                    "--nworkers",
                    str(n_workers),
                    "--nthreads",
                    str(threads),
                    "--memory-limit",
                    memory_limit,
                    "--no-dashboard",
                    "--local-directory",
                    str(work / "dask-worker-space"),
                ],
                stdout=log,
                stderr=subprocess.STDOUT,
                env=env,
            )
        )
        with Client(address, timeout=120) as client:
            client.wait_for_workers(n_workers, timeout=300)
        yield address
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in reversed(procs):
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
        log.close()


def _rebuild_on(data_root: str, out_root: str, address: str, overrides: dict) -> dict:
    """``rebuild`` of a dataset on the cluster at ``address`` (in a fresh process)."""
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
    from flows.pipeline.run import rebuild_dataset
    from flows.pipeline.runtime import prefect_api

    cfg = make_config(
        Path(data_root),
        Path(out_root),
        {**overrides, "dask.address": address, "dask.runner": "dask"},
    )
    with prefect_api():
        t0 = time.perf_counter()
        report = rebuild_dataset(cfg, progress=False)
        wall = time.perf_counter() - t0
    if report.failed:
        raise RuntimeError(f"cluster rebuild failed: {report.failed[0].error}")
    return {
        "wall_s": wall,
        "units_s": report.seconds,
        "frames": sum(p.num_frames for p in report.plans),
        "sequences": len(report.plans),
    }


def _rebuild_with_task_stream(address: str, slots: int, data: str, out: str, over: dict) -> dict:
    """The rebuild on the cluster, and from the scheduler's task stream the seconds its worker
    threads computed: ``busy`` = compute seconds / (slots x wall of the units), the share of the
    cluster the run kept busy (its parallelism, whatever else loads the machine)."""
    from distributed import Client

    with Client(address, timeout=120) as client:
        client.get_task_stream(start=time.time())  # installs the scheduler's task-stream plugin
        t0 = time.time()
        run = spawned(_rebuild_on, data, out, address, over)
        stream = client.get_task_stream(start=t0)
    compute = sum(
        ss["stop"] - ss["start"]
        for t in stream
        for ss in t.get("startstops", ())
        if ss.get("action") == "compute"
    )
    run.update(compute_s=compute, tasks=len(stream), busy=compute / (slots * run["units_s"]))
    return run


def bench_cluster(
    src_root: Path,
    src_id: int,
    work: Path,
    workers=DEFAULT_CLUSTER_WORKERS,
    sequences: int = CLUSTER_SEQUENCES,
    frames: int = CLUSTER_FRAMES,
    threads_check: bool = True,
) -> dict:
    """Rebuild ``sequences`` copies of a ``frames``-frame sequence on loopback clusters of each
    worker count (one thread each); speed-up and efficiency against one worker. ``threads_check``:
    also one worker of 2 threads (``threads_1x2``), against 2 workers of 1 thread."""
    data = work / "cluster-data"
    shutil.rmtree(data, ignore_errors=True)
    for k in range(sequences):
        link_sequence(src_root, src_id, data, k, raw_frames=2 * frames)
    over = {"fit.iterations": LONG_FIT_ITERATIONS}
    runs = {}
    for n in workers:
        with loopback_cluster(n, work / "cluster") as address:
            runs[n] = _rebuild_with_task_stream(
                address, n, str(data), str(work / f"cluster-out-{n}"), over
            )
        runs[n]["load_avg_1m"] = os.getloadavg()[0]
    t1 = runs[min(workers)]["units_s"] * min(workers)
    for n, r in runs.items():
        r["speedup"] = t1 / r["units_s"]
        r["efficiency"] = r["speedup"] / n
        # on dedicated cores a worker computes at one worker's speed: speed-up = N x busy / busy(1)
        r["speedup_dedicated"] = n * r["busy"] / runs[min(workers)]["busy"]
    res = {
        "sequences": sequences,
        "frames_per_sequence": frames,
        "fit.iterations": LONG_FIT_ITERATIONS,
        "cores": os.cpu_count(),
        "runs": runs,
    }
    if threads_check:
        with loopback_cluster(1, work / "cluster", threads=2) as address:
            r = _rebuild_with_task_stream(
                address, 2, str(data), str(work / "cluster-out-1x2"), over
            )
        r["load_avg_1m"] = os.getloadavg()[0]
        r["speedup"] = t1 / r["units_s"]
        res["threads_1x2"] = r
    return res


# ---- the projection ------------------------------------------------------------------------------


def amdahl_serial_fraction(points: dict[int, float]) -> float:
    """Least-squares serial fraction f of speed-ups {N: S(N)} under S(N) = 1 / (f + (1 - f) / N)
    (1 / S is linear in 1 / N); clipped to [0, 1]."""
    import numpy as np

    ns = np.array([n for n in points if n > 1], float)
    if not len(ns):
        return 0.0
    y = np.array([1.0 / points[int(n)] for n in ns]) - 1.0 / ns  # = f (1 - 1/N)
    x = 1.0 - 1.0 / ns
    return float(np.clip((x @ y) / (x @ x), 0.0, 1.0))


def project(
    cost: dict,
    long: dict,
    cluster: dict | None,
    frames: int = DATASET_FRAMES,
    sequence_frames: int = SEQUENCE_FRAMES,
    workers=PROJECT_WORKERS,
) -> dict:
    """Projected wall hours of ``frames`` frames on N workers (see the module docstring)."""

    cpu_per_frame = sum(cost[s]["cpu_s_per_frame"] for s in STAGES)
    wall_per_frame = sum(cost[s]["wall_s_per_frame"] for s in STAGES)
    # a worker is one process of one thread on a core of its own: its wall time per frame is the
    # CPU time measured here (the wall time on a shared, loaded machine is not)
    per_frame = cpu_per_frame
    cores = os.cpu_count() or 1
    # the speed-ups a cluster of dedicated cores would give: N x the busy share the run kept
    # (measured on this machine's cluster whatever its load), for N up to its cores
    measured = {int(n): r["speedup_dedicated"] for n, r in (cluster or {}).get("runs", {}).items()}
    fit_points = {n: s for n, s in measured.items() if n <= cores}
    f = amdahl_serial_fraction(fit_points) if fit_points else 0.0
    longest = max(long, key=int) if long else None
    serial = (
        sum(long[longest][s]["wall_s_per_frame"] for s in SERIAL_STAGES)
        if longest
        else sum(cost[s]["wall_s_per_frame"] for s in SERIAL_STAGES)
    )
    critical_h = sequence_frames * serial / 3600
    rows = {}
    for n in workers:
        speedup = measured[n] if n in fit_points else 1.0 / (f + (1 - f) / n)
        hours = frames * per_frame / speedup / 3600
        rows[n] = {
            "speedup": speedup,
            "efficiency": speedup / n,
            "hours": max(hours, critical_h),
            "bound": "critical path" if critical_h > hours else "throughput",
            "speedup_source": "measured" if n in fit_points else f"Amdahl f={f:.3f}",
        }
    return {
        "frames": frames,
        "sequence_frames": sequence_frames,
        "s_per_frame": per_frame,
        "cpu_s_per_frame": cpu_per_frame,
        "wall_s_per_frame": wall_per_frame,
        "serial_fraction": f,
        "critical_path_hours": critical_h,
        "serial_s_per_frame": serial,
        "workers": rows,
    }


# ---- the benchmark ---------------------------------------------------------------------------------


def bench_scale(
    frames=DEFAULT_FRAMES,
    sequences=DEFAULT_SEQUENCES,
    cluster_workers=DEFAULT_CLUSTER_WORKERS,
    parts=PARTS,
    json_path: Path | None = None,
    work_dir: Path | None = None,
    sim_long_frames: int = 2000,
    sim_sample: int = 6,
    sim_workers: int = 2,
    memory_frames=MEMORY_FRAMES,
) -> dict:
    """Run the parts listed in the module docstring; print a table; write JSON when asked."""
    from flows.bench.planning import bench_planning
    from flows.bench.simulator import bench_simulator
    from flows.commands.simulate import simulate

    work = Path(tempfile.mkdtemp(prefix="mobileocc-scale-", dir=work_dir))
    started = time.perf_counter()
    frames = sorted(int(f) for f in frames)
    result: dict = {
        "machine": machine(),
        "frames": frames,
        "sequences": list(sequences),
        "cluster_workers": list(cluster_workers),
        "parts": list(parts),
    }
    try:
        if "simulator" in parts:
            result["simulator"] = spawned(
                bench_simulator,
                sim_long_frames,
                sim_sample,
                sim_workers,
                ("uncrowded", "crowded"),
                str(work),
            )
        src = work / "long-source"
        if {"long", "cost", "cluster"} & set(parts):
            t0 = time.perf_counter()
            raw = 2 * max(frames + [CLUSTER_FRAMES])
            simulate(
                src,
                sequences=1,
                frames=raw,
                seed=7,
                progress=False,
                first_id=SOURCE_ID,
                fast=True,
                workers=2,
                frame_step=2,
            )
            result["long_simulate"] = {
                "raw_frames": raw,
                "files_for": raw // 2,
                "wall_s": time.perf_counter() - t0,
            }
        if "long" in parts:
            result["long"] = {}
            for n in frames:
                data = work / f"long-{n}"
                link_sequence(src, SOURCE_ID, data, 0, raw_frames=2 * n)
                result["long"][n] = spawned(
                    _run_stages_forked,
                    str(data),
                    str(work / f"long-out-{n}"),
                    {"fit.iterations": LONG_FIT_ITERATIONS},
                )
                shutil.rmtree(work / f"long-out-{n}", ignore_errors=True)
        if "cost" in parts:
            data = work / "cost-data"
            link_sequence(src, SOURCE_ID, data, 0, raw_frames=2 * frames[0])
            result["cost"] = spawned(_run_stages_forked, str(data), str(work / "cost-out"), {})
        if "memory" in parts:
            from flows.bench.memory import bench_memory

            result["memory"] = bench_memory(list(memory_frames), work / "memory")
        if "planning" in parts:
            result["planning"] = spawned(bench_planning, list(sequences), str(work))
        if "cluster" in parts:
            result["cluster"] = bench_cluster(src, SOURCE_ID, work, tuple(cluster_workers))
        if "cost" in result:
            result["projection"] = project(
                result["cost"], result.get("long", {}), result.get("cluster")
            )
    finally:
        shutil.rmtree(work, ignore_errors=True)
    result["bench_wall_s"] = time.perf_counter() - started
    print(format_scale(result))
    if json_path is not None:
        from flows.commands.report import write_json

        write_json(json_path, result)
    return result


def format_scale(r: dict) -> str:
    """The scale figures as aligned text tables (what docs/scale.md shows)."""
    from flows.bench.simulator import format_simulator

    m = r["machine"]
    lines = [
        f"machine: {m['cpu_model']} x{m['cpu_count']} cpus, {m['memory_gb']} GB, load {m['load_avg_1m']:.1f}"
    ]
    if "simulator" in r:
        lines += format_simulator(r["simulator"])
    if "long" in r:
        lines.append(
            "peak RSS per stage, MB (stage's own = peak - runner baseline), vs 5 Hz frames of one sequence:"
        )
        lines.append(f"  {'stage':<8}" + "".join(f"{n:>22}" for n in r["long"]))
        for st in STAGES:
            lines.append(
                f"  {st:<8}"
                + "".join(
                    f"{v[st]['peak_rss_mb']:>13.0f} ({v[st]['stage_rss_mb']:>+5.0f})"
                    for v in r["long"].values()
                )
            )
        lines.append(
            f"wall s per frame per stage vs frames (fit at {LONG_FIT_ITERATIONS} iterations here):"
        )
        for st in STAGES:
            lines.append(
                f"  {st:<8}"
                + "".join(f"{v[st]['wall_s_per_frame']:>22.3f}" for v in r["long"].values())
            )
    if "cost" in r:
        c = r["cost"]
        lines.append(
            f"per-frame cost, default settings ({c['frames']} frames): "
            + ", ".join(
                f"{st} {c[st]['cpu_s_per_frame']:.2f} CPU / {c[st]['wall_s_per_frame']:.2f} wall s"
                for st in STAGES
            )
        )
    if "memory" in r:
        from flows.bench.memory import format_table as format_memory

        lines.append("peak RSS of map and fuse vs frames (flows/bench/memory.py):")
        lines.extend("  " + line for line in format_memory(r["memory"]).splitlines())
    if "planning" in r:
        from flows.bench.planning import format_table

        lines.append("planning vs sequences (flows/bench/planning.py):")
        lines.extend("  " + line for line in format_table(r["planning"]).splitlines())
    if "cluster" in r:
        cl = r["cluster"]
        lines.append(
            f"loopback dask cluster ({cl['sequences']} x {cl['frames_per_sequence']} frames, "
            f"{cl['cores']} cores): "
            + ", ".join(
                f"{n} worker(s) {v['units_s']:.0f} s (wall x{v['speedup']:.2f}, busy {v['busy']:.2f}, "
                f"dedicated-core x{v['speedup_dedicated']:.2f})"
                for n, v in cl["runs"].items()
            )
        )
        if "threads_1x2" in cl:
            lines.append(
                f"  1 worker x 2 threads: {cl['threads_1x2']['units_s']:.0f} s (x{cl['threads_1x2']['speedup']:.2f})"
            )
    if "projection" in r:
        p = r["projection"]
        lines.append(
            f"projected wall for {p['frames']} frames ({p['s_per_frame']:.2f} s/frame on one worker; "
            f"critical path of a {p['sequence_frames']}-frame sequence {p['critical_path_hours']:.1f} h):"
        )
        for n, v in p["workers"].items():
            lines.append(
                f"  N={n:<4} {v['hours']:>8.1f} h  (speed-up {v['speedup']:.2f}, {v['speedup_source']}, "
                f"{v['bound']}-bound)"
            )
    lines.append(f"bench wall {r.get('bench_wall_s', 0):.0f} s")
    return "\n".join(lines)
