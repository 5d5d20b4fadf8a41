"""Prefect overhead per sequence: flow wall time minus the time inside stages, per sequence.

    mobileocc bench overhead [--sequences 8] [--frames 2]

One worker with one thread on both runners, so units run one after another and the subtraction is
meaningful. Each runner is warmed up first on one sequence (imports, JIT) in a separate store; the
Dask runner connects to a LocalCluster (one worker process) started beforehand, so cluster start-up
is not counted.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from flows.bench.common import make_config


def _measure(cfg_for, data: Path, work: Path, name: str, sequences: int) -> dict:
    from flows.pipeline.run import rebuild_dataset

    def run(out: Path, seqs: list[str]):
        cfg = cfg_for(data, out, seqs)
        started = time.perf_counter()
        report = rebuild_dataset(cfg, progress=False)  # picks its runner from cfg.dask
        return time.perf_counter() - started, report

    run(work / f"{name}-warm", ["0"])
    wall, report = run(work / f"{name}-run", [str(i) for i in range(sequences)])
    inside = sum(o.seconds for o in report.outcomes.values())
    units = sum(o.ran for o in report.outcomes.values())
    return {
        "flow_s": round(wall, 2),
        "inside_stages_s": round(inside, 2),
        "units": units,
        "failed_units": len(report.failed),
        "overhead_per_sequence_s": round((wall - inside) / sequences, 3),
        "overhead_per_unit_s": round((wall - inside) / max(units, 1), 3),
    }


def bench_overhead(sequences: int = 8, frames: int = 2) -> dict:
    """Overhead of the thread and Dask runners on ``sequences`` simulated sequences of ``frames``
    raw frames each (the module docstring); a dict of figures per runner."""
    from distributed import LocalCluster

    from flows.commands.simulate import simulate
    from flows.pipeline.runtime import prefect_api

    work = Path(tempfile.mkdtemp(prefix="mobileocc-bench-overhead-"))
    data = work / "data"
    simulate(
        data,
        sequences=sequences,
        frames=frames,
        seed=3,
        pedestrians=2,
        crowd="uncrowded",
        progress=False,
    )

    result: dict = {"sequences": sequences, "raw_frames": frames}
    with prefect_api():
        result["thread"] = _measure(
            lambda d, o, s: make_config(d, o, {"dataset.sequences": s, "dask.workers": 1}),
            data,
            work,
            "thread",
            sequences,
        )
        with LocalCluster(
            n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None
        ) as cluster:
            address = cluster.scheduler_address
            result["dask"] = _measure(
                lambda d, o, s: make_config(
                    d, o, {"dataset.sequences": s, "dask.runner": "dask", "dask.address": address}
                ),
                data,
                work,
                "dask",
                sequences,
            )
    return result
