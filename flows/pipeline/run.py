"""Prefect flows: ``rebuild_dataset`` (many sequences) and ``process_sequence`` (one).

One Prefect task is one (sequence, stage) unit: the unit of caching, retry and failure. Units whose
key is fresh in the manifest are not submitted. A unit whose upstream failed is skipped. The flow
process records every finished unit in the manifest at once (atomic rewrite), so a killed run
resumes where it stopped.
"""

from __future__ import annotations

import contextlib
import json
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

from prefect import flow, task
from prefect.cache_policies import NO_CACHE
from prefect.futures import PrefectFuture, as_completed

from configs.schema import Config, config_hash
from flows.pipeline.dag import STAGES
from flows.pipeline.inputs import DatasetExportInputs, Runtime, dataset_export_inputs, inputs_hash, runtime
from flows.pipeline.plan import SequencePlan, UnitPlan, plan_run
from flows.stages import STAGE_FUNCTIONS, StageContext
from storage.manifest import (
    FileHasher,
    Manifest,
    StageRecord,
    remove_stale_versions,
    run_lock,
    stage_dir,
    staged_output,
    sweep_temporaries,
)


def execute_unit(unit: UnitPlan, out_root: Path, upstream: dict[str, dict],
                 fingerprint: str = "", runtime: Runtime = Runtime()) -> dict:
    """Run one (sequence, stage): returns an outcome dict; never raises for a stage error."""
    base = {"sequence": unit.sequence, "stage": unit.stage, "key": unit.key, "parts": unit.parts}
    blocked = [s for s, o in upstream.items() if o["status"] not in ("done", "cached")]
    if blocked:
        return {**base, "status": "skipped", "error": f"upstream {', '.join(blocked)} did not finish"}
    final = stage_dir(out_root, unit.stage, unit.sequence, unit.key)
    location = str(final.relative_to(out_root))
    if (final / "summary.json").exists():  # finished by a run that was killed before recording it
        summary = json.loads((final / "summary.json").read_text())
        return {**base, "status": "done", "location": location, "summary": summary, "seconds": 0.0}
    started = time.perf_counter()
    try:
        with staged_output(final) as tmp:
            ctx = StageContext(unit.ref, unit.inputs, Path(out_root), tmp,
                               {s: Path(out_root) / o["location"] for s, o in upstream.items()},
                               key=unit.key, fingerprint=fingerprint, runtime=runtime)
            summary = STAGE_FUNCTIONS[unit.stage](ctx)
            (tmp / "summary.json").write_text(json.dumps(summary, sort_keys=True, indent=1))
    except Exception as exc:  # noqa: BLE001 - one bad sequence fails alone, with its error
        return {**base, "status": "failed", "seconds": time.perf_counter() - started,
                "error": f"{type(exc).__name__}: {exc}",
                "traceback": traceback.format_exc(limit=8)}
    return {**base, "status": "done", "location": location, "summary": summary,
            "seconds": time.perf_counter() - started}


@task(name="stage", cache_policy=NO_CACHE, task_run_name="{unit.stage}-{unit.sequence}")
def stage_task(unit: UnitPlan, out_root: Path, upstream: dict[str, dict], fingerprint: str,
               runtime: Runtime) -> dict:
    return execute_unit(unit, out_root, upstream, fingerprint, runtime)


@dataclass
class RunReport:
    out_root: Path
    plans: list[SequencePlan]
    outcomes: dict[tuple[str, str], dict] = field(default_factory=dict)
    seconds: float = 0.0
    #: format -> "done" or "failed: <error>" for the dataset-level exports made in this run
    dataset_exports: dict[str, str] = field(default_factory=dict)

    @property
    def failed(self) -> list[dict]:
        return [o for o in self.outcomes.values() if o["status"] == "failed"]

    def ran(self, stage: str | None = None) -> list[tuple[str, str]]:
        return sorted(k for k, o in self.outcomes.items()
                      if o["status"] in ("done", "failed") and o.get("ran", True)
                      and (stage is None or k[1] == stage))


def _record(manifest: Manifest, outcome: dict) -> None:
    if outcome["status"] not in ("done", "failed"):
        return
    manifest.put(StageRecord(
        sequence=outcome["sequence"], stage=outcome["stage"], key=outcome["key"],
        status=outcome["status"], location=outcome.get("location", ""),
        error=outcome.get("error", ""), seconds=round(outcome.get("seconds", 0.0), 3),
        finished_at=time.time(), summary=outcome.get("summary", {}), parts=outcome["parts"]))
    manifest.save()
    if outcome["status"] == "done":
        remove_stale_versions(manifest.root, outcome["stage"], outcome["sequence"], outcome["key"])


def _gpu_annotation(config: Config, stage: str):
    if stage == "fit" and config.dask.gpu_fit and config.dask.runner == "dask":
        import dask

        return dask.annotate(resources={"GPU": 1})
    return contextlib.nullcontext()


def run_units(config: Config, force: bool = False, sequences: list[str] | None = None,
              progress: bool = True) -> RunReport:
    """Plan and run; the body of both flows. Must be called inside a flow (it submits tasks)."""
    out_root = Path(config.output.root)
    started = time.perf_counter()
    with run_lock(out_root):
        sweep_temporaries(out_root)
        manifest = Manifest.load(out_root)
        manifest.meta.update({"config_hash": config_hash(config),
                              "config": config.model_dump(mode="json")})
        hasher = FileHasher(out_root / ".cache" / "file-hashes.json")
        plans = plan_run(config, manifest, hasher, force=force, sequences=sequences)
        hasher.save()
        report = RunReport(out_root, plans)
        futures: list[PrefectFuture] = []
        results: dict[str, dict[str, object]] = {}
        for plan in plans:
            if plan.error:  # the sequence cannot be opened: it fails alone
                outcome = {"sequence": plan.sequence, "stage": "detect", "key": "", "parts": {},
                           "status": "failed", "error": plan.error}
                report.outcomes[(plan.sequence, "detect")] = outcome
                _record(manifest, outcome)
            else:
                results[plan.sequence] = {}
        # stage-major order: a thread pool runs tasks in submission order and a task waiting on its
        # upstream holds a thread, so every sequence's detect goes first, then every track, ...
        for stage, upstream in STAGES.items():
            for plan in plans:
                if plan.error:
                    continue
                mine = results[plan.sequence]
                unit = plan.units[stage]
                if unit.fresh:
                    rec = manifest.get(plan.sequence, stage)
                    outcome = {"sequence": plan.sequence, "stage": stage, "key": unit.key,
                               "parts": unit.parts, "status": "cached", "location": rec.location,
                               "summary": rec.summary, "seconds": 0.0, "ran": False}
                    report.outcomes[(plan.sequence, stage)] = outcome
                    mine[stage] = outcome
                    continue
                with _gpu_annotation(config, stage):
                    fut = stage_task.submit(unit, out_root, {u: mine[u] for u in upstream}, plan.fingerprint,
                                            runtime(config))
                futures.append(fut)
                mine[stage] = fut
        bars = _progress_bars(report, futures, progress)
        for fut in as_completed(futures):
            outcome = fut.result()
            report.outcomes[(outcome["sequence"], outcome["stage"])] = outcome
            _record(manifest, outcome)
            if bars:
                bars[outcome["stage"]].update(1)
        for bar in (bars or {}).values():
            bar.close()
        _dataset_exports(config, manifest, report)
    report.seconds = time.perf_counter() - started
    return report


def _dataset_exports(config: Config, manifest: Manifest, report: RunReport) -> None:
    """The Occ3D / nuScenes exports of the whole dataset (``export.formats``), made again when a
    sequence was (re)published or their settings changed. A failure is reported, not raised: the
    sequences are published."""
    ex = dataset_export_inputs(config)
    published = any(st == "export" and o["status"] == "done" and o.get("ran", True)
                    for (_, st), o in report.outcomes.items())
    key, done = inputs_hash(ex), manifest.meta.setdefault("dataset_exports", {})
    for fmt in ex.formats:
        if not (published or done.get(fmt) != key):
            continue
        try:
            export_dataset(ex, Path(config.output.root), Path(config.dataset.root), fmt)
            done[fmt] = key
            report.dataset_exports[fmt] = "done"
        except Exception as exc:  # noqa: BLE001 - the sequences stay published
            done.pop(fmt, None)
            report.dataset_exports[fmt] = f"failed: {type(exc).__name__}: {exc}"
    manifest.save()


def _progress_bars(report: RunReport, futures: list, progress: bool):
    if not progress or not futures:
        return None
    from tqdm import tqdm

    counts = {s: sum(1 for p in report.plans if not p.error and not p.units[s].fresh) for s in STAGES}
    return {s: tqdm(total=counts[s], desc=f"{s:>6}", unit="seq", position=i, leave=True)
            for i, s in enumerate(STAGES)}


def export_dataset(ex: DatasetExportInputs, out_root: Path, data_root: Path, fmt: str,
                   target: Path | None = None, gt: bool = False) -> Path:
    """Export the published dataset (every sequence) for occupancy trainers; ``gt``: Occ3D labels
    from the synthetic ground truth under ``data_root`` instead of the pipeline's."""
    from storage.export.nuscenes import export_nuscenes
    from storage.export.occ3d import export_occ3d

    target = Path(target) if target is not None else Path(out_root) / "exports" / fmt
    if gt and fmt != "occ3d":
        raise ValueError(f"--gt exports Occ3D labels; it does not apply to --format {fmt}")
    if fmt == "occ3d":
        export_occ3d(out_root, target, scene_prefix=ex.scene_prefix, val_sequences=ex.val_sequences,
                     gt_root=Path(data_root) if gt else None)
    else:
        export_nuscenes(out_root, target, version=ex.nuscenes_version, scene_prefix=ex.scene_prefix,
                        source_root=Path(data_root), min_range_m=ex.min_range_m, val_sequences=ex.val_sequences,
                        **({"infos_data_root": ex.infos_data_root} if ex.infos_data_root else {}))
    return target


@flow(name="run-units", log_prints=True)
def _run_units_flow(config: Config, force: bool, sequences: list[str] | None, progress: bool) -> RunReport:
    return run_units(config, force=force, sequences=sequences, progress=progress)


@flow(name="rebuild-dataset", log_prints=True)
def rebuild_dataset(config: Config, force: bool = False, sequences: list[str] | None = None,
                    progress: bool = True) -> RunReport:
    """Every selected sequence through detect -> track -> fit / map -> fuse -> export, then the
    dataset-level exports of ``export.formats`` when any sequence was (re)published or their
    settings changed.

    The units run in a subflow on the task runner ``config.dask`` asks for (threads, a Dask
    LocalCluster, or ``dask.address``), however this flow was started (CLI, deployment, test).
    """
    from flows.pipeline.runtime import task_runner

    inner = _run_units_flow.with_options(task_runner=task_runner(config))
    return inner(config, force, sequences, progress)


@flow(name="process-sequence", log_prints=True)
def process_sequence(config: Config, sequence: str, force: bool = False) -> RunReport:
    """One sequence through the six stages (on the task runner of ``config.dask``)."""
    return rebuild_dataset(config, force=force, sequences=[sequence], progress=False)


def summary_table(report: RunReport) -> str:
    """Sequences, frames, time per stage, cached vs run, failures."""
    lines = []
    header = f"{'stage':<8}{'ran':>5}{'cached':>8}{'failed':>8}{'skipped':>9}{'seconds':>10}"
    lines.append(header)
    lines.append("-" * len(header))
    for stage in STAGES:
        outs = [o for (s, st), o in report.outcomes.items() if st == stage]
        ran = sum(o["status"] == "done" for o in outs)
        cached = sum(o["status"] == "cached" for o in outs)
        failed = sum(o["status"] == "failed" for o in outs)
        skipped = sum(o["status"] == "skipped" for o in outs)
        secs = sum(o.get("seconds", 0.0) for o in outs)
        lines.append(f"{stage:<8}{ran:>5}{cached:>8}{failed:>8}{skipped:>9}{secs:>10.1f}")
    frames = sum(p.num_frames for p in report.plans)
    lines.append(f"{len(report.plans)} sequence(s), {frames} frame(s), {report.seconds:.1f} s wall")
    not_impl = sorted({st for (s, st), o in report.outcomes.items()
                       if o.get("summary", {}).get("implemented") is False})
    if not_impl:
        lines.append(f"not implemented yet (placeholders): {', '.join(not_impl)}")
    for o in report.failed:
        lines.append(f"FAILED {o['sequence']}/{o['stage']}: {o['error']}")
    for fmt, state in sorted(report.dataset_exports.items()):
        lines.append(f"{fmt} export: {state}")
    lines += [f"WARNING {p.sequence}: {w}" for p in report.plans for w in p.warnings]
    return "\n".join(lines)
