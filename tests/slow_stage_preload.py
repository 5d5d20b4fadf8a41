"""Dask worker preload for tests/test_faults.py (``dask worker --preload tests/slow_stage_preload.py``).

While the file ``$MOBILEOCC_TEST_FAULTS/slow.json`` ({"stage": ..., "seconds": ...}) exists, that
stage sleeps before it runs and first leaves a marker ``started-<stage>-<sequence>-<pid>`` in the
same folder, so a test can kill the worker process while the stage is in flight. The stage's
output is unchanged (the real stage function runs after the sleep).
"""

from __future__ import annotations

import json
import os
import time
import uuid
from pathlib import Path


def _slowed(stage: str, run, control: Path):
    def slowed(ctx):
        switch = control / "slow.json"
        if switch.exists():
            cfg = json.loads(switch.read_text())
            if cfg["stage"] == stage:
                marker = (
                    control / f"started-{stage}-{ctx.sequence}-{os.getpid()}-{uuid.uuid4().hex[:6]}"
                )
                marker.write_text(str(os.getpid()))
                time.sleep(float(cfg["seconds"]))
        return run(ctx)

    slowed.__name__ = getattr(run, "__name__", f"run_{stage}")
    return slowed


def dask_setup(worker) -> None:  # noqa: ARG001 - the preload hook's signature
    control = os.environ.get("MOBILEOCC_TEST_FAULTS")
    if not control:
        return
    from flows.stages import STAGE_FUNCTIONS

    for stage, run in list(STAGE_FUNCTIONS.items()):
        if not getattr(run, "_slow_wrapped", False):
            wrapped = _slowed(stage, run, Path(control))
            wrapped._slow_wrapped = True
            STAGE_FUNCTIONS[stage] = wrapped
