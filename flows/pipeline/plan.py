"""Planning a run: which (sequence, stage) units are fresh, which must run, and why.

The plan is computed in the flow process: keys depend only on input fingerprints, code versions,
stage inputs (flows/pipeline/inputs.py) and upstream keys, never on outputs. Sequences are planned
one by one (:func:`iter_plans`) so a run can submit a sequence's work while the next one is being
fingerprinted. Each sequence is isolated: any error while listing, opening, validating or hashing
its files fails that sequence alone (``SequencePlan.error``, with the file named), never the plan.

Fingerprints come from the per-sequence memo of storage.manifest.FingerprintCache when the stat
signature of the sequence's layout folders is unchanged (no file of the sequence is opened);
otherwise the sequence is opened (validated) and its changed files hashed.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

from configs.schema import Config
from flows.pipeline.dag import CODE_VERSIONS, STAGES
from flows.pipeline.inputs import (
    SequenceRef,
    StageInputs,
    inputs_hash,
    sequence_ref,
    source,
    stage_inputs,
    to_jsonable,
)
from flows.pipeline.outcome import Status
from storage.coda import READER_VERSION, frame_number, sequence_ids, sequence_layout
from storage.files import InputError, regular_stat
from storage.manifest import (
    FileHasher,
    FingerprintCache,
    Manifest,
    layout_signature,
    sequence_fingerprint,
    stage_key,
)


@dataclass
class UnitPlan:
    sequence: str
    stage: str
    key: str
    parts: dict
    fresh: bool
    reason: str  # why it runs ("" when fresh)
    #: the stage's inputs object (the only settings the stage reads)
    inputs: StageInputs
    #: the sequence: where it is, what the config says about it alone
    ref: SequenceRef


@dataclass
class SequencePlan:
    sequence: str
    fingerprint: str = ""
    num_frames: int = 0
    error: str = ""  # the sequence could not even be opened
    warnings: tuple[str, ...] = ()  # the reader's (defaults used, values ignored)
    units: dict[str, UnitPlan] = field(default_factory=dict)
    #: the fingerprint came from the memo (no file of the sequence was read)
    memo_hit: bool = False


@dataclass
class PlanCosts:
    """What planning cost: seconds, sequences read vs taken from the memo, bytes hashed."""

    seconds: float = 0.0
    sequences: int = 0
    memo_hits: int = 0
    files_hashed: int = 0
    bytes_hashed: int = 0
    hash_seconds: float = 0.0

    @property
    def hash_mb_per_s(self) -> float | None:
        return self.bytes_hashed / 1e6 / self.hash_seconds if self.hash_seconds > 0 else None

    def line(self) -> str:
        text = (
            f"planned {self.sequences} sequence(s) in {self.seconds:.1f} s "
            f"({self.memo_hits} unchanged by size / mtime / inode"
        )
        if self.files_hashed:
            text += (
                f"; hashed {self.files_hashed} file(s), {self.bytes_hashed / 1e6:.1f} MB in "
                f"{self.hash_seconds:.1f} s = {self.hash_mb_per_s or 0:.0f} MB/s"
            )
        return text + ")"


def selected_sequences(config: Config) -> list[str]:
    """The sequences a run takes: ``dataset.sequences``, or with "all" every sequence that has any
    layout file (storage.coda.sequence_ids: one missing its timestamps file is still listed, so it
    is reported, not left out)."""
    if config.dataset.sequences == "all":
        return sequence_ids(config.dataset.root)
    return [str(s) for s in config.dataset.sequences]


def unit_keys(
    inputs: dict[str, Any], fingerprint: str, hashes: dict[str, str] | None = None
) -> dict[str, tuple[str, dict]]:
    """(key, parts) of every stage of a sequence: parts are the key's ingredients (code version,
    inputs hash, fingerprint or upstream keys), kept in the manifest to explain staleness.
    ``hashes``: the inputs hashes, when already computed (they are the same for every sequence)."""
    hashes = hashes or {stage: inputs_hash(obj) for stage, obj in inputs.items()}
    keys: dict[str, tuple[str, dict]] = {}
    for stage, upstream in STAGES.items():
        ups = {u: keys[u][0] for u in upstream} or {"fingerprint": fingerprint}
        parts = {"code": CODE_VERSIONS[stage], "config": hashes[stage], "inputs": ups}
        keys[stage] = (stage_key(stage, CODE_VERSIONS[stage], parts["config"], ups), parts)
    return keys


def _as_cache(cache: FingerprintCache | FileHasher | None) -> FingerprintCache:
    if isinstance(cache, FingerprintCache):
        return cache
    return FingerprintCache(None, verify=bool(getattr(cache, "verify", False)))


def _message(exc: BaseException) -> str:
    """An error as a plan records it: bad input speaks for itself (it names the file), anything
    else with its type."""
    return str(exc) if isinstance(exc, (InputError, OSError)) else f"{type(exc).__name__}: {exc}"


class NeedsHashing(Exception):
    """Planning without hashing met a sequence whose files changed since its memo."""


def sequence_facts(
    config: Config,
    ref: SequenceRef,
    cache: FingerprintCache,
    hashing: bool = True,
    src: Any = None,
    reader: Any = None,
) -> tuple[str, int, tuple, bool]:
    """(files fingerprint, frames, reader warnings, taken from the memo) of one sequence.

    The stat signature is taken before anything is read, so a file changing meanwhile only makes
    the next plan read the sequence again. ``hashing=False``: NeedsHashing instead of hashing
    (after opening the sequence, so bad input is still found). ``src`` / ``reader``: the
    config's Source and its JSON, when the caller has them."""
    src = src or source(config)
    signature = layout_signature(
        ref.root, sequence_layout(ref.root, ref.sequence, src.lidar_source, src.image_source)
    )
    reader = {
        "version": READER_VERSION,
        "source": reader or to_jsonable(src),
        "lighting": ref.lighting,
    }
    memo = cache.load(ref.sequence)
    if cache.hit(memo, reader, signature):
        return memo["fingerprint"], int(memo["num_frames"]), tuple(memo["warnings"]), True
    info = src.open(ref).info  # every sequence-level check of the reader
    for path in info.files:  # a FIFO, device, folder or link loop among them fails here, unread
        regular_stat(path, frame_number(path), "input file")
    if not hashing:
        raise NeedsHashing(ref.sequence)
    hasher = cache.file_hasher(memo)
    try:
        fingerprint = sequence_fingerprint(ref.root, info.files, hasher)
    finally:
        cache.add_costs(hasher)
    cache.save(
        ref.sequence,
        {
            "reader": reader,
            "signature": signature,
            "fingerprint": fingerprint,
            "num_frames": info.num_frames,
            "warnings": list(info.warnings),
            "files": {k: hasher.memo[k] for k in sorted(hasher.used)},
        },
    )
    return fingerprint, info.num_frames, info.warnings, False


def iter_plans(
    config: Config,
    manifest: Manifest,
    cache: FingerprintCache | FileHasher | None = None,
    force: bool = False,
    sequences: list[str] | None = None,
    costs: PlanCosts | None = None,
    hashing: bool = True,
) -> Iterator[SequencePlan]:
    """Plan the selected sequences one at a time: fingerprint, per-stage keys, freshness with a
    reason. A sequence that cannot be listed, opened or hashed gets ``error`` and no units."""
    cache, costs = _as_cache(cache), costs if costs is not None else PlanCosts()
    inputs, src = stage_inputs(config), source(config)
    hashes, reader = {stage: inputs_hash(obj) for stage, obj in inputs.items()}, to_jsonable(src)
    manifest.remember_inputs(
        {stage: (hashes[stage], to_jsonable(obj)) for stage, obj in inputs.items()}
    )
    for seq in sequences if sequences is not None else selected_sequences(config):
        t0, plan = time.perf_counter(), SequencePlan(str(seq))
        ref = sequence_ref(config, str(seq))
        try:
            files_fp, plan.num_frames, plan.warnings, plan.memo_hit = sequence_facts(
                config, ref, cache, hashing, src, reader
            )
        except NeedsHashing:
            raise
        except Exception as exc:  # noqa: BLE001 - whatever breaks on one sequence fails that sequence
            plan.error = _message(exc)
        else:
            plan.fingerprint = ref.fingerprint(files_fp)
            runs: set[str] = set()
            for stage, (key, parts) in unit_keys(inputs, plan.fingerprint, hashes).items():
                reason = _stale_reason(
                    manifest, plan.sequence, stage, key, parts, STAGES[stage], runs, force
                )
                if reason:
                    runs.add(stage)
                plan.units[stage] = UnitPlan(
                    plan.sequence,
                    stage,
                    key,
                    parts,
                    fresh=not reason,
                    reason=reason,
                    inputs=inputs[stage],
                    ref=ref,
                )
        costs.sequences += 1
        costs.memo_hits += plan.memo_hit
        costs.seconds += time.perf_counter() - t0
        costs.files_hashed, costs.bytes_hashed = cache.hasher.hashed, cache.hasher.bytes_hashed
        costs.hash_seconds = cache.hasher.seconds
        yield plan


def plan_without_hashing(
    config: Config,
    manifest: Manifest,
    cache: FingerprintCache,
    force: bool = False,
    sequences: list[str] | None = None,
    costs: PlanCosts | None = None,
) -> list[SequencePlan] | None:
    """The plans when no sequence needs hashing (each is unchanged since its memo, or cannot be
    read at all); None as soon as one does. A run whose plans have no stale unit needs no task
    runner (the CLI then starts no Prefect server)."""
    if force or cache.verify:
        return None
    try:
        return list(iter_plans(config, manifest, cache, force, sequences, costs, hashing=False))
    except NeedsHashing:
        return None


def plan_run(
    config: Config,
    manifest: Manifest,
    cache: FingerprintCache | FileHasher | None = None,
    force: bool = False,
    sequences: list[str] | None = None,
    costs: PlanCosts | None = None,
) -> list[SequencePlan]:
    """Plan every selected sequence (:func:`iter_plans`, all at once)."""
    return list(iter_plans(config, manifest, cache, force, sequences, costs))


def _stale_reason(
    manifest: Manifest,
    seq: str,
    stage: str,
    key: str,
    parts: dict,
    upstream: tuple[str, ...],
    runs: set[str],
    force: bool,
) -> str:
    if force:
        return "forced (--force)"
    rec = manifest.get(seq, stage)
    if rec is None:
        return "never ran"
    if rec.status != Status.DONE:
        what = "was skipped" if rec.status == Status.SKIPPED else "failed"
        return f"last run {what}: {rec.error.splitlines()[0][:120] if rec.error else rec.status}"
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
