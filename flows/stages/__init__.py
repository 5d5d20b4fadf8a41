"""The six stages of a sequence: read through storage, call kernels, write through storage.

Each stage function takes a :class:`StageContext` and writes its outputs into ``ctx.out_dir``
(a hidden staging directory published by rename when the function returns) and returns a small
JSON-able summary (``implemented`` says whether the stage computes its product; every stage does
now, the flag stays so a future placeholder says so plainly).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from flows.stages.common import StageContext, chunks
from flows.stages.detect import run_detect
from flows.stages.export import run_export
from flows.stages.fit import run_fit
from flows.stages.fuse import run_fuse
from flows.stages.map import run_map
from flows.stages.track import run_track

STAGE_FUNCTIONS: dict[str, Callable[[StageContext[Any]], dict]] = {
    "detect": run_detect,
    "track": run_track,
    "fit": run_fit,
    "map": run_map,
    "fuse": run_fuse,
    "export": run_export,
}

__all__ = ["STAGE_FUNCTIONS", "StageContext", "chunks"]
