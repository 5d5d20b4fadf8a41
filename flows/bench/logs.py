"""Robot-log decoding: speed on one core, and peak memory against the log's length (issue 27).

``bench_logs(sweeps, work)`` writes one ROS 2 MCAP log per length with the simulator's log writer
(storage.sources.log.writer): organised OS1-128 sweeps in the Ouster driver's 48-byte layout
(ranges of a smooth random scene, 10 % no-returns, so every sweep differs), a small rectified
JPEG camera with its CameraInfo, /tf_static and /tf poses at 10 Hz. Then, per log, a fresh
spawned process pinned to one core (``sched_setaffinity``, BLAS / OpenMP pools at one thread)
opens it as a sequence (storage.sources.log.reader.LogSequence: the index pass over the whole log, no
cache) and reads every sweep in stamp order (``frame(i)``: the message fetched through the index,
its PointCloud2 decoded, no-returns dropped), and reports:

- ``index_s``: seconds of the index pass; ``read_s`` / ``read_cpu_s``: wall / CPU seconds of
  reading every sweep; ``sweeps_per_s`` = sweeps / read_s (target >= 20 on one core);
- ``peak_rss_mb``: ``resource.getrusage(RUSAGE_SELF).ru_maxrss`` of the process, and
  ``baseline_rss_mb`` (the peak after imports, before the log is opened).

The summary's ``rss_ratio`` is the longest log's peak over the shortest's (target <= 1.2 for
1,000 vs 100 sweeps: memory flat in the log's length).

Run: ``mobileocc bench logs --work DIR [--sweeps 100 1000] [--json FILE] [--keep]`` (flows/cli.py).
"""

from __future__ import annotations

import os
import resource
import shutil
import time
from pathlib import Path

import numpy as np

ROWS, COLS = 128, 1024
START_NS = 1_700_000_000_000_000_000
PERIOD_NS = 100_000_000


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _sweep(rng: np.random.Generator, scene: np.ndarray, k: int):
    """An organised sweep of the scene's range image shifted by k columns, with noise."""
    el = np.repeat(np.linspace(np.radians(-22.5), np.radians(22.5), ROWS), COLS)
    az = np.tile(np.linspace(0, 2 * np.pi, COLS, endpoint=False), ROWS)
    rng_m = np.roll(scene, k, axis=1).reshape(-1) + rng.normal(0, 0.02, ROWS * COLS)
    rng_m[rng.random(ROWS * COLS) < 0.1] = 0.0  # no returns
    pts = np.c_[np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)] * rng_m[:, None]
    intensity = rng.uniform(0, 255, ROWS * COLS).astype(np.float32)
    t_ns = np.tile(np.arange(COLS, dtype=np.uint32) * (PERIOD_NS // COLS), ROWS)
    return pts.astype(np.float32), intensity, t_ns


def write_bench_log(path: Path, sweeps: int, seed: int = 0) -> Path:
    """A synthetic MCAP log of ``sweeps`` sweeps (module doc)."""
    from io import BytesIO

    from PIL import Image

    from storage.sources.log.writer import LogCamera, LogWriter

    rng = np.random.default_rng(seed)
    coarse = rng.uniform(3.0, 60.0, (ROWS // 16, COLS // 32))
    scene = np.kron(coarse, np.ones((16, 32)))  # a blocky scene of walls at 3..60 m
    K = np.array([[80.0, 0, 63.5], [0, 80.0, 47.5], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]
    cam = LogCamera("cam0", 128, 96, K, np.zeros(5), np.eye(3), np.c_[K, np.zeros(3)], T)
    T_base = np.eye(4)
    T_base[2, 3] = 0.9
    buf = BytesIO()
    Image.fromarray(np.full((96, 128, 3), 90, np.uint8)).save(buf, format="JPEG")
    with LogWriter(path, "mcap", [cam], T_base, poses="tf") as w:
        w.write_static(START_NS)
        for k in range(sweeps):
            stamp = START_NS + k * PERIOD_NS
            w.write_pose(stamp, np.array([0.1 * k, 0.0, 0.0]), np.array([1.0, 0, 0, 0]))
            w.write_sweep(stamp, *_sweep(rng, scene, k))
            w.write_image(stamp, "cam0", buf.getvalue())
    return path


def _read_log(path: str, queue) -> None:
    """In a spawned process on one core: open the log, read every sweep, report."""
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    from threadpoolctl import threadpool_limits

    from storage.sources.log.reader import LogSequence

    with threadpool_limits(1):
        baseline = _peak_mb()
        t0 = time.perf_counter()
        seq = LogSequence(Path(path), frame_stride=1, cameras=("cam0",), max_range_m=120.0)
        index_s = time.perf_counter() - t0
        t0, c0, points = time.perf_counter(), time.process_time(), 0
        for i in range(len(seq)):
            points += len(seq.frame(i).points_lidar)
        read_s, read_cpu_s = time.perf_counter() - t0, time.process_time() - c0
    queue.put(
        {
            "sweeps": len(seq),
            "points": points,
            "index_s": index_s,
            "read_s": read_s,
            "read_cpu_s": read_cpu_s,
            "sweeps_per_s": len(seq) / read_s,
            "sweeps_per_cpu_s": len(seq) / read_cpu_s,
            "baseline_rss_mb": baseline,
            "peak_rss_mb": _peak_mb(),
        }
    )


def measure(path: Path) -> dict:
    """Read one log in a fresh spawned process (module doc)."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=_read_log, args=(str(path), queue))
    proc.start()
    result = queue.get()
    proc.join()
    return {**result, "log_mb": path.stat().st_size / 1e6}


def bench_logs(sweeps: list[int], work: Path, keep: bool = False) -> dict:
    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    runs = []
    for n in sorted(sweeps):
        path = work / f"bench_{n}.mcap"
        t0 = time.perf_counter()
        if not path.exists():
            write_bench_log(path, n)
        write_s = time.perf_counter() - t0
        runs.append({**measure(path), "write_s": write_s})
        if not keep:
            path.unlink()
    if not keep:
        shutil.rmtree(work / "cache", ignore_errors=True)
    first, last = runs[0], runs[-1]
    return {
        "runs": runs,
        "sweeps_per_s": min(r["sweeps_per_s"] for r in runs),
        "rss_ratio": last["peak_rss_mb"] / first["peak_rss_mb"],
        "cpus": os.cpu_count(),
        "load_average": os.getloadavg(),
    }


def format_table(r: dict) -> str:
    lines = [
        f"{'sweeps':>7} {'log MB':>8} {'index s':>8} {'read s':>7} {'sweeps/s':>9} "
        f"{'(cpu)':>7} {'baseline MB':>12} {'peak RSS MB':>12}"
    ]
    for x in r["runs"]:
        lines.append(
            f"{x['sweeps']:>7} {x['log_mb']:>8.0f} {x['index_s']:>8.1f} {x['read_s']:>7.1f} "
            f"{x['sweeps_per_s']:>9.1f} {x['sweeps_per_cpu_s']:>7.1f} "
            f"{x['baseline_rss_mb']:>12.0f} {x['peak_rss_mb']:>12.0f}"
        )
    lines.append(
        f"decoding: {r['sweeps_per_s']:.1f} sweeps/s on one core (target >= 20); peak RSS "
        f"{r['runs'][-1]['sweeps']} vs {r['runs'][0]['sweeps']} sweeps: {r['rss_ratio']:.2f}x "
        f"(target <= 1.2); load average {r['load_average'][0]:.1f} on {r['cpus']} CPUs"
    )
    return "\n".join(lines)
