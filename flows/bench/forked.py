"""Units in forked children: what a stage costs in memory on its own, through the pipeline's
runner (``mobileocc bench scale``: flows/bench/scale.py)."""

from __future__ import annotations

import dataclasses
import json
import os
import resource
import time

from flows.pipeline.outcome import Status, UnitOutcome
from flows.pipeline.units import Submitter, execute_unit


def _rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


class ForkedUnits(Submitter):
    """Runs each unit in a forked child of this runner (which imported every stage and planned):
    per stage the child's wall / CPU seconds, its peak RSS and the runner's RSS when it forked
    (the baseline), in ``measured``."""

    def __init__(self):
        self.measured: dict[str, dict] = {}

    def submit(self, stage: str, *args) -> UnitOutcome:
        r, w = os.pipe()
        pid = os.fork()
        if pid == 0:  # the child: one stage, then report and leave without cleanup handlers
            code = 0
            try:
                os.close(r)
                start_rss = _rss_mb()  # what the fork maps of the runner (its anonymous pages)
                c0, t0 = time.process_time(), time.perf_counter()
                outcome = execute_unit(*args)
                msg = {
                    "outcome": dataclasses.asdict(outcome),
                    "wall_s": time.perf_counter() - t0,
                    "cpu_s": time.process_time() - c0,
                    "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
                    "start_rss_mb": start_rss,
                }
            except BaseException as exc:  # noqa: BLE001 - reported to the runner
                msg, code = {"error": f"{type(exc).__name__}: {exc}"}, 1
            finally:
                with os.fdopen(w, "w") as fh:
                    fh.write(json.dumps(msg))
                os._exit(code)
        os.close(w)
        with os.fdopen(r, "rb") as fh:
            data = fh.read()
        os.waitpid(pid, 0)
        msg = json.loads(data.decode() or '{"error": "the stage process died"}')
        if "error" in msg:
            raise RuntimeError(f"stage {stage}: {msg['error']}")
        self.measured[stage] = msg
        return UnitOutcome(**{**msg["outcome"], "status": Status(msg["outcome"]["status"])})
