"""``mobileocc status`` and ``mobileocc reprocess --dry-run``: per sequence and stage, fresh,
stale (or would run) with the reason, or failed."""

from __future__ import annotations

from pathlib import Path

from configs.schema import Config
from flows.pipeline.inputs import source
from flows.pipeline.outcome import Status
from flows.pipeline.plan import PlanCosts, plan_run, selected_sequences
from flows.pipeline.units import DAMAGED_REASONS, store_problems, unclassified_share
from storage.layout import shown
from storage.manifest import FingerprintCache, Manifest, OutputError


def _unit_state(manifest, plan, stage: str, unit, dry_run: bool) -> list[str]:
    """Lines for one unit: nothing when fresh and whole; its reason, failure or lost frames."""
    rec = manifest.get(plan.sequence, stage)
    if unit.fresh:
        bad = (rec.summary or {}).get("failed_frames") or [] if rec is not None else []
        return [f"fresh, frame {b['frame']} left out: {b['error']}" for b in bad[:3]] + (
            [f"fresh, {len(bad)} frame(s) left out in all"] if len(bad) > 3 else []
        )
    if rec is not None and rec.status in (Status.FAILED, Status.SKIPPED) and not dry_run:
        return [f"{rec.status}: {rec.error.splitlines()[0] if rec.error else ''}"]
    return [f"{'would run' if dry_run else 'stale'}: {unit.reason}"]


def print_plan(cfg: Config, dry_run: bool, verify: bool = False) -> int:
    """Print per sequence and stage what is stale (or would run, ``dry_run``) and why, and what
    failed or is damaged, then what is wrong with the store as a whole (interrupted publications,
    sequences gone from the input, stale dataset exports); returns the number of sequences with
    failures (or that cannot be read) plus the number of store problems."""
    out, costs = Path(cfg.output.root), PlanCosts()
    if not out.is_dir():  # not "every unit stale": there is no store to describe
        raise OutputError(
            f"output store {shown(out)} "
            + ("is not a folder" if out.exists() else "does not exist")
            + " (`mobileocc rebuild` builds one there)"
        )
    if cfg.dataset.sequences == "all":
        source(cfg).check_root(cfg.dataset.root)
    manifest = Manifest.load(out)
    cache = FingerprintCache(out / ".cache" / "sequences" if out.is_dir() else None, verify)
    plans = plan_run(cfg, manifest, cache, sequences=selected_sequences(cfg), costs=costs)
    runs = problems = 0
    for plan in plans:
        if plan.error:
            print(shown(f"{plan.sequence:>6}  cannot be read: {plan.error}"))
            problems += 1
            continue
        lines = [
            (stage, line)
            for stage, unit in plan.units.items()
            for line in _unit_state(manifest, plan, stage, unit, dry_run)
        ]
        runs += sum(not u.fresh for u in plan.units.values())
        problems += any(
            line.startswith(("failed", "skipped", "fresh, "))
            or line.split(": ", 1)[-1].startswith(DAMAGED_REASONS)
            for _, line in lines
        )
        for stage, line in lines:
            print(shown(f"{plan.sequence:>6}  {stage:<7} {line}"))
        if not lines and not dry_run:
            print(shown(f"{plan.sequence:>6}  fresh ({len(plan.units)} stages)"))
        fused = manifest.get(plan.sequence, "fuse")
        share = unclassified_share(fused.summary or {}) if fused is not None else None
        if share is not None and not dry_run:
            print(
                shown(
                    f"{plan.sequence:>6}  labels  {100 * share:.1f} % of occupied voxels "
                    "unclassified"
                )
            )
    print(
        f"{len(plans)} sequence(s): {runs} unit(s) {'would run' if dry_run else 'stale or failed'}, "
        f"{problems} sequence(s) with failures; {costs.line()}"
    )
    store = store_problems(cfg, manifest, verify) if out.is_dir() else []
    for line in store:
        print(shown(line))
    return problems + len(store)
