"""The simulator's speed: where a frame's time goes, default vs ``--fast``, one process vs workers.

``bench_simulator(long_frames, sample, workers)`` builds the Simulator of one long sequence
(``long_frames`` raw frames: the scene spans the whole drive) for each mode and crowd, and
simulates + writes ``sample`` frames spread over it:

- ``cpu_s_per_frame`` and its parts (process CPU time on one thread: LiDAR = BVH build + cast,
  the two cameras, ground-truth occupancy, people's ground truth, posing, writing the files);
- ``frames_per_s_wall``: the same frames made by ``workers`` frame worker processes (as
  ``simulate --workers``), after a warm-up, wall clock; on an idle machine with ``workers``
  cores it approaches ``workers / cpu_s_per_frame`` (``frames_per_s_cpu``); on a loaded one it
  is lower (``load_avg_1m`` is recorded).
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from pathlib import Path

#: the parts a frame's CPU time is split into: (name, owner, attribute)
_PARTS = (
    ("lidar (BVH build + cast)", "frame", "cast_lidar"),
    ("cameras", "frame", "render_camera"),
    ("gt occupancy", "Simulator", "_occupancy"),
    ("gt people", "Simulator", "_people_gt"),
    ("posing", "Simulator", "_pose_people"),
)


def _profiled_frames(long_frames: int, crowd: str, fast: bool, sample: int, out: Path) -> dict:
    """CPU seconds per frame and per part over ``sample`` frames of a long sequence (this process)."""
    import torch

    import tasks.sim.frame as F
    from flows.commands.simulate import make_simulator, write_frame
    from tasks.sim import SimOptions

    torch.set_num_threads(1)
    spent: dict[str, float] = {}
    saved = []

    def timed(name, fn):
        def wrapper(*a, **k):
            t0 = time.process_time()
            try:
                return fn(*a, **k)
            finally:
                spent[name] = spent.get(name, 0.0) + time.process_time() - t0

        return wrapper

    for name, owner, attr in _PARTS:
        target = F if owner == "frame" else F.Simulator
        saved.append((target, attr, getattr(target, attr)))
        setattr(target, attr, timed(name, getattr(target, attr)))
    try:
        sim = make_simulator(SimOptions(seed=1, frames=long_frames, crowd=crowd), fast)
        sim.frame(0)
        spent.clear()
        idx = [int(i) for i in (1 + (long_frames - 2) * (k + 0.5) / sample for k in range(sample))]
        t0 = time.process_time()
        for i in idx:
            f = sim.frame(i)
            w0 = time.process_time()
            write_frame(out, 0, f, i)
            spent["writing files"] = spent.get("writing files", 0.0) + time.process_time() - w0
        total = time.process_time() - t0
    finally:
        for target, attr, fn in saved:
            setattr(target, attr, fn)
    return {
        "cpu_s_per_frame": total / len(idx),
        "pedestrians": sim.options.num_pedestrians,
        "parts_cpu_s": {k: v / len(idx) for k, v in sorted(spent.items(), key=lambda kv: -kv[1])},
        "triangles_static": int(len(sim._static["faces"])),
    }


def _pool_frames_per_s(
    long_frames: int, crowd: str, fast: bool, sample: int, workers: int, out: Path
) -> float:
    """Wall frames/s of ``workers`` frame worker processes on ``sample`` frames (after warm-up)."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    from flows.commands.simulate import _limit_threads, _write_frames
    from tasks.sim import SimOptions

    opts = SimOptions(seed=1, frames=long_frames, crowd=crowd)
    with ProcessPoolExecutor(
        workers, mp_context=mp.get_context("spawn"), initializer=_limit_threads
    ) as pool:
        warm = [
            pool.submit(_write_frames, str(out), 1, opts, fast, [i], [i], ".jpg")
            for i in range(workers)
        ]
        for f in warm:
            f.result()
        idx = [int(i) for i in (1 + (long_frames - 2) * (k + 0.5) / sample for k in range(sample))]
        t0 = time.perf_counter()
        futures = [
            pool.submit(_write_frames, str(out), 1, opts, fast, [i], [i], ".jpg") for i in idx
        ]
        for f in futures:
            f.result()
        return len(idx) / (time.perf_counter() - t0)


def bench_simulator(
    long_frames: int = 2000,
    sample: int = 8,
    workers: int = 2,
    crowds: tuple[str, ...] = ("uncrowded", "crowded"),
    work_dir: str | None = None,
) -> dict:
    """Default vs fast simulator on a long sequence (see the module docstring)."""
    result: dict = {
        "long_frames": long_frames,
        "sample_frames": sample,
        "workers": workers,
        "modes": {},
    }
    work = Path(tempfile.mkdtemp(prefix="mobileocc-simbench-", dir=work_dir))
    try:
        for crowd in crowds:
            for fast in (False, True):
                name = f"{'fast' if fast else 'default'} {crowd}"
                row = _profiled_frames(
                    long_frames, crowd, fast, sample, work / name.replace(" ", "-")
                )
                row["frames_per_s_cpu"] = workers / row["cpu_s_per_frame"]
                row["load_avg_1m_before"] = os.getloadavg()[0]
                row["frames_per_s_wall"] = _pool_frames_per_s(
                    long_frames,
                    crowd,
                    fast,
                    sample,
                    workers,
                    work / f"pool-{name.replace(' ', '-')}",
                )
                row["load_avg_1m_after"] = os.getloadavg()[0]
                result["modes"][name] = row
        for crowd in crowds:
            d, f = result["modes"][f"default {crowd}"], result["modes"][f"fast {crowd}"]
            result[f"fast_over_default_cpu {crowd}"] = d["cpu_s_per_frame"] / f["cpu_s_per_frame"]
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return result


def format_simulator(r: dict) -> list[str]:
    lines = [
        f"simulator: {r['long_frames']}-raw-frame sequence, {r['sample_frames']} frames sampled, "
        f"{r['workers']} workers"
    ]
    for name, m in r["modes"].items():
        parts = ", ".join(f"{k} {1000 * v:.0f}" for k, v in m["parts_cpu_s"].items())
        lines.append(
            f"  {name:<18} {m['cpu_s_per_frame']:.3f} CPU s/frame -> {m['frames_per_s_cpu']:.1f} frames/s "
            f"on {r['workers']} idle cores; measured {m['frames_per_s_wall']:.2f} frames/s wall "
            f"(load {m['load_avg_1m_before']:.1f}); ms: {parts}"
        )
    return lines
