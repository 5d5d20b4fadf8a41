"""Planning a run: which (sequence, stage) units are fresh, which must run, and why.

The plan is computed in the flow process before anything is submitted: keys depend only on input
fingerprints, code versions, config slices and upstream keys, never on outputs.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

from configs.schema import Config
from storage.coda import CodaSequence, list_sequences
from storage.manifest import FileHasher, Manifest, canonical_json, sequence_fingerprint, stage_key

#: The DAG of DESIGN.md: stage -> upstream stages. Order is a topological order.
STAGES: dict[str, tuple[str, ...]] = {
    "detect": (),
    "track": ("detect",),
    "fit": ("track",),
    "map": ("detect",),
    "fuse": ("fit", "map"),
    "export": ("fuse", "track", "fit"),  # tables take tracks and body fits too
}

#: Explicit code versions: bump a stage's version when its output for the same input changes.
#: (A key from code versions, not from source hashes: refactors do not invalidate datasets.)
CODE_VERSIONS: dict[str, str] = {
    "detect": "2",  # 2: the oracle's miss curve calibrated on the paper's detection table
    "track": "4",  # 2: offline back-fill and stitching; 3: world-position check; 4: person points past the image side
    "fit": "3",  # 2: L_3D caps the vertex -> point distances (fit.chamfer_vertex_max_m); 100 iterations;
    #             3: detections with fewer than fit.min_points LiDAR points are not fitted, fits
    #                that moved more than fit.max_shift_m from their estimate are dropped
    "map": "2",  # 2: the out-of-view fallback keeps ground and raised points apart, strips along the path
    "fuse": "1",
    "export": "2",  # 2: instances carry the fitted bodies, 3D boxes and velocities
}


@dataclass
class UnitPlan:
    sequence: str
    stage: str
    key: str
    parts: dict
    fresh: bool
    reason: str  # why it runs ("" when fresh)


@dataclass
class SequencePlan:
    sequence: str
    fingerprint: str = ""
    num_frames: int = 0
    error: str = ""  # the sequence could not even be opened
    warnings: tuple[str, ...] = ()  # the reader's (defaults used, values ignored)
    units: dict[str, UnitPlan] = field(default_factory=dict)

    @property
    def to_run(self) -> list[str]:
        return [s for s, u in self.units.items() if not u.fresh]


def open_sequence(config: Config, sequence: str) -> CodaSequence:
    ds = config.dataset
    return CodaSequence(ds.root, sequence, frame_stride=ds.frame_stride,
                        lidar_source=ds.lidar_source, image_source=ds.image_source,
                        min_range_m=ds.min_range_m, max_range_m=ds.max_range_m, frames=ds.frames,
                        lighting=ds.lighting.get(str(sequence)), lidar_height_m=ds.lidar_height_m)


def selected_sequences(config: Config) -> list[str]:
    available = list_sequences(config.dataset.root)
    if config.dataset.sequences == "all":
        return available
    return [str(s) for s in config.dataset.sequences]


def _short(value) -> str:
    return hashlib.sha256(canonical_json(value)).hexdigest()[:12]


def plan_run(config: Config, manifest: Manifest, hasher: FileHasher, force: bool = False,
             sequences: list[str] | None = None) -> list[SequencePlan]:
    """Plan every selected sequence: fingerprint, per-stage keys, freshness with a reason."""
    plans = []
    for seq in sequences if sequences is not None else selected_sequences(config):
        plan = SequencePlan(seq)
        plans.append(plan)
        try:
            info = open_sequence(config, seq).info
            plan.fingerprint = sequence_fingerprint(config.dataset.root, info.files, hasher)
            plan.num_frames = info.num_frames
            plan.warnings = info.warnings
        except (ValueError, OSError) as exc:
            plan.error = str(exc)
            continue
        keys: dict[str, str] = {}
        runs: set[str] = set()
        for stage, upstream in STAGES.items():
            inputs = {u: keys[u] for u in upstream} or {"fingerprint": plan.fingerprint}
            parts = {"code": CODE_VERSIONS[stage], "config": _short(config.stage_slice(stage)),
                     "inputs": inputs}
            key = stage_key(stage, CODE_VERSIONS[stage], config.stage_slice(stage), inputs)
            keys[stage] = key
            reason = _stale_reason(manifest, seq, stage, key, parts, upstream, runs, force)
            if reason:
                runs.add(stage)
            plan.units[stage] = UnitPlan(seq, stage, key, parts, fresh=not reason, reason=reason)
    return plans


def _stale_reason(manifest: Manifest, seq: str, stage: str, key: str, parts: dict,
                  upstream: tuple[str, ...], runs: set[str], force: bool) -> str:
    if force:
        return "forced (--force)"
    rec = manifest.get(seq, stage)
    if rec is None:
        return "never ran"
    if rec.status != "done":
        return f"last run failed: {rec.error.splitlines()[0][:120] if rec.error else rec.status}"
    rerun_up = [u for u in upstream if u in runs]
    if rerun_up:  # also when keys match: the upstream output it was built from is being rebuilt
        return f"upstream {', '.join(rerun_up)} runs"
    if rec.key == key:
        return "" if manifest.output_exists(rec) else f"output missing ({rec.location})"
    old = rec.parts or {}
    if old.get("code") != parts["code"]:
        return f"code version {old.get('code')} -> {parts['code']}"
    if old.get("config") != parts["config"]:
        return "config changed"
    if "fingerprint" in parts["inputs"] and old.get("inputs") != parts["inputs"]:
        return "input files changed"
    return "key changed"
