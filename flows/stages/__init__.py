"""The six stages of a sequence: read through storage, call kernels, write through storage.

Each stage function takes a :class:`StageContext` and writes its outputs into ``ctx.out_dir``
(a hidden staging directory that is published by rename when the function returns), and returns a
small JSON-able summary. ``implemented: False`` in a summary says plainly that the stage does not
compute its product yet; nothing pretends.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from configs.schema import Config
from flows.parallel import fan_out
from flows.plan import open_sequence


@dataclass(frozen=True)
class StageContext:
    config: Config
    sequence: str
    out_root: Path
    out_dir: Path
    upstream: dict[str, Path] = field(default_factory=dict)

    def upstream_summary(self, stage: str) -> dict:
        return json.loads((self.upstream[stage] / "summary.json").read_text())


def _read_frame_chunk(config: Config, sequence: str, positions: list[int]) -> list[dict]:
    seq = open_sequence(config, sequence)
    out = []
    for i in positions:
        frame = seq.frame(i)
        out.append({"frame": frame.index, "points": int(frame.points_lidar.shape[0]),
                    "boxes": len(frame.boxes)})
    return out


def chunks(n: int, size: int) -> list[list[int]]:
    return [list(range(a, min(a + size, n))) for a in range(0, n, size)]


def run_detect(ctx: StageContext) -> dict:
    seq = open_sequence(ctx.config, ctx.sequence)
    per_chunk = fan_out(_read_frame_chunk, [(ctx.config, ctx.sequence, c) for c in chunks(len(seq), 8)])
    rows = [r for chunk in per_chunk for r in chunk]
    (ctx.out_dir / "frames.json").write_text(json.dumps(rows))
    return {"implemented": False, "note": "frames read and validated; no perception provider wired yet",
            "frames": len(rows), "points": sum(r["points"] for r in rows)}


def _not_implemented(stage: str) -> Callable[[StageContext], dict]:
    def run(ctx: StageContext) -> dict:
        return {"implemented": False, "note": f"{stage} is not implemented yet: passes nothing through"}
    run.__name__ = f"run_{stage}"
    return run


STAGE_FUNCTIONS: dict[str, Callable[[StageContext], dict]] = {
    "detect": run_detect,
    "track": _not_implemented("track"),
    "fit": _not_implemented("fit"),
    "map": _not_implemented("map"),
    "fuse": _not_implemented("fuse"),
    "export": _not_implemented("export"),
}
