"""Planning a run: which (sequence, stage) units are fresh, which must run, and why.

The plan is computed in the flow process before anything is submitted: keys depend only on input
fingerprints, code versions, stage inputs (flows/pipeline/inputs.py) and upstream keys, never on
outputs.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from configs.schema import Config
from flows.pipeline.dag import CODE_VERSIONS, STAGES
from flows.pipeline.inputs import SequenceRef, inputs_hash, sequence_ref, source, stage_inputs, to_jsonable
from storage.coda import list_sequences
from storage.manifest import FileHasher, Manifest, sequence_fingerprint, stage_key


@dataclass
class UnitPlan:
    sequence: str
    stage: str
    key: str
    parts: dict
    fresh: bool
    reason: str  # why it runs ("" when fresh)
    #: the stage's inputs object (the only settings the stage reads)
    inputs: Any = None
    #: the sequence: where it is, what the config says about it alone
    ref: SequenceRef | None = None


@dataclass
class SequencePlan:
    sequence: str
    fingerprint: str = ""
    num_frames: int = 0
    error: str = ""  # the sequence could not even be opened
    warnings: tuple[str, ...] = ()  # the reader's (defaults used, values ignored)
    units: dict[str, UnitPlan] = field(default_factory=dict)


def selected_sequences(config: Config) -> list[str]:
    available = list_sequences(config.dataset.root)
    if config.dataset.sequences == "all":
        return available
    return [str(s) for s in config.dataset.sequences]


def unit_keys(inputs: dict[str, Any], fingerprint: str) -> dict[str, tuple[str, dict]]:
    """(key, parts) of every stage of a sequence: parts are the key's ingredients (code version,
    inputs hash, fingerprint or upstream keys), kept in the manifest to explain staleness."""
    keys: dict[str, tuple[str, dict]] = {}
    for stage, upstream in STAGES.items():
        ups = {u: keys[u][0] for u in upstream} or {"fingerprint": fingerprint}
        parts = {"code": CODE_VERSIONS[stage], "config": inputs_hash(inputs[stage]), "inputs": ups}
        keys[stage] = (stage_key(stage, CODE_VERSIONS[stage], parts["config"], ups), parts)
    return keys


def plan_run(config: Config, manifest: Manifest, hasher: FileHasher, force: bool = False,
             sequences: list[str] | None = None) -> list[SequencePlan]:
    """Plan every selected sequence: fingerprint, per-stage keys, freshness with a reason."""
    inputs = stage_inputs(config)
    manifest.remember_inputs({stage: (inputs_hash(obj), to_jsonable(obj)) for stage, obj in inputs.items()})
    plans = []
    for seq in sequences if sequences is not None else selected_sequences(config):
        plan = SequencePlan(seq)
        plans.append(plan)
        ref = sequence_ref(config, seq)
        try:
            info = source(config).open(ref).info
            plan.fingerprint = ref.fingerprint(sequence_fingerprint(config.dataset.root, info.files, hasher))
            plan.num_frames = info.num_frames
            plan.warnings = info.warnings
        except (ValueError, OSError) as exc:
            plan.error = str(exc)
            continue
        runs: set[str] = set()
        for stage, (key, parts) in unit_keys(inputs, plan.fingerprint).items():
            reason = _stale_reason(manifest, seq, stage, key, parts, STAGES[stage], runs, force)
            if reason:
                runs.add(stage)
            plan.units[stage] = UnitPlan(seq, stage, key, parts, fresh=not reason, reason=reason,
                                         inputs=inputs[stage], ref=ref)
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
        changed = manifest.inputs_diff(stage, old.get("config"), parts["config"])
        return f"settings changed: {changed}" if changed else "settings changed"
    if "fingerprint" in parts["inputs"] and old.get("inputs") != parts["inputs"]:
        return "input files changed"
    return "key changed"
