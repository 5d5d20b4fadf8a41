"""Prefect overhead per sequence: flow wall time minus the time inside stages, per sequence.

    nice .venv/bin/python infra/bench_overhead.py --sequences 8 --frames 2

One worker with one thread on both runners, so units run one after another and the subtraction is
meaningful. Each runner is warmed up first on one sequence (imports, JIT) in a separate store; the
Dask runner connects to a LocalCluster (one worker process) started beforehand, so cluster start-up
is not counted. Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--sequences", type=int, default=8)
    parser.add_argument("--frames", type=int, default=2, help="raw frames per sequence")
    args = parser.parse_args(argv)

    from distributed import LocalCluster

    from configs.schema import load_config
    from flows.commands.simulate import simulate
    from flows.pipeline.runtime import prefect_api

    work = Path(tempfile.mkdtemp(prefix="mobileocc-bench-overhead-"))
    data = work / "data"
    simulate(
        data,
        sequences=args.sequences,
        frames=args.frames,
        seed=3,
        pedestrians=2,
        crowd="uncrowded",
        progress=False,
    )

    def base(data: Path, out: Path, seqs: list[str], **extra):
        return load_config(
            overrides={
                "dataset.root": str(data),
                "output.root": str(out),
                "dataset.sequences": seqs,
                **extra,
            }
        )

    result = {"sequences": args.sequences, "raw_frames": args.frames}
    with prefect_api():
        result["thread"] = _measure(
            lambda d, o, s: base(d, o, s, **{"dask.workers": 1}),
            data,
            work,
            "thread",
            args.sequences,
        )
        with LocalCluster(
            n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None
        ) as cluster:
            address = cluster.scheduler_address
            result["dask"] = _measure(
                lambda d, o, s: base(d, o, s, **{"dask.runner": "dask", "dask.address": address}),
                data,
                work,
                "dask",
                args.sequences,
            )
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
