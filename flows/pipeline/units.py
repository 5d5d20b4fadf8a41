"""Running a dataset's units: plan, submit, record, withdraw, export (Prefect-free).

:func:`run_units` is the body of the Prefect flows of flows/pipeline/run.py, which hand it a
submitter that turns each (sequence, stage) unit into a Prefect task; without one it runs every
unit here, in order (``inline``: tests, benchmarks, and the CLI when nothing needs to run, which
then imports neither Prefect nor the stages).

Units whose key is fresh in the manifest are not submitted; a unit whose upstream failed is
skipped (and recorded as such). Sequences are planned one by one and each one's detect unit is
submitted as soon as it is planned, so fingerprinting the next sequences overlaps with work; the
later stages are submitted stage-major once planning is done. The flow process appends every
finished unit to the manifest's journal at once, so a killed run resumes where it stopped.

Nothing disappears: a sequence that cannot be read, or any of whose units failed or was skipped,
is in the report (``RunReport.exit_code`` 1) and the manifest, and its earlier published data are
withdrawn (storage.publish.withdraw_sequence: the sequences table marks it failed) and so left
out of the dataset-level exports.
"""

from __future__ import annotations

import time
import traceback
from collections.abc import Callable, Collection
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from configs.schema import Config, config_hash
from flows.pipeline.dag import CODE_VERSIONS, DATASET_EXPORTS_VERSION, STAGES
from flows.pipeline.inputs import (
    DatasetExportInputs,
    Runtime,
    dataset_export_inputs,
    export_inputs,
    inputs_hash,
    runtime,
)
from flows.pipeline.outcome import Status, UnitOutcome
from flows.pipeline.plan import (
    PlanCosts,
    SequencePlan,
    UnitPlan,
    iter_plans,
    selected_sequences,
)
from storage.atomic import staged_folder
from storage.coda import check_dataset_root
from storage.manifest import (
    FingerprintCache,
    Manifest,
    StageRecord,
    check_writable,
    data_root_for,
    holding_lock,
    record_data_root,
    remove_stale_versions,
    run_lock,
    stage_dir,
    sweep_temporaries,
)
from storage.products import SUMMARY, read_summary, write_summary
from storage.publish import withdraw_sequence


def _error_text(exc: BaseException, where: Path) -> str:
    """A stage error as recorded: a disk error without a file name gets the unit's output folder."""
    if isinstance(exc, OSError) and not exc.filename:
        return f"{type(exc).__name__}: {exc} (writing under {where})"
    return f"{type(exc).__name__}: {exc}"


def execute_unit(
    unit: UnitPlan,
    out_root: Path,
    upstream: dict[str, UnitOutcome],
    fingerprint: str = "",
    runtime: Runtime = Runtime(),
) -> UnitOutcome:
    """Run one (sequence, stage); never raises for a stage error (the outcome is failed)."""

    def outcome(status: Status, **more) -> UnitOutcome:
        return UnitOutcome(unit.sequence, unit.stage, unit.key, unit.parts, status, **more)

    blocked = [s for s, o in upstream.items() if not o.finished]
    if blocked:
        return outcome(Status.SKIPPED, error=f"upstream {', '.join(blocked)} did not finish")
    final = stage_dir(out_root, unit.stage, unit.sequence, unit.key)
    location = str(final.relative_to(out_root))
    if (final / SUMMARY).exists():  # finished by a run that was killed before recording it
        summary = read_summary(final)
        return outcome(Status.DONE, location=location, summary=summary)
    from flows.pipeline.parallel import limit_threads
    from flows.stages import (  # the kernels: only where a unit runs
        STAGE_FUNCTIONS,
        StageContext,
    )

    started = time.perf_counter()
    limit_threads(runtime.threads)
    try:
        with staged_folder(final, replace=False) as tmp:
            ctx = StageContext(
                unit.ref,
                unit.inputs,
                Path(out_root),
                tmp,
                {s: Path(out_root) / o.location for s, o in upstream.items()},
                key=unit.key,
                fingerprint=fingerprint,
                runtime=runtime,
            )
            summary = STAGE_FUNCTIONS[unit.stage](ctx)
            write_summary(tmp, summary)
    except Exception as exc:  # noqa: BLE001 - one bad sequence fails alone, with its error
        return outcome(
            Status.FAILED,
            seconds=time.perf_counter() - started,
            error=_error_text(exc, final.parent),
            traceback=traceback.format_exc(limit=8),
        )
    return outcome(
        Status.DONE, location=location, summary=summary, seconds=time.perf_counter() - started
    )


@dataclass
class RunReport:
    out_root: Path
    plans: list[SequencePlan]
    outcomes: dict[tuple[str, str], UnitOutcome] = field(default_factory=dict)
    seconds: float = 0.0
    #: format -> "done" or "failed: <error>" for the dataset-level exports made in this run
    dataset_exports: dict[str, str] = field(default_factory=dict)
    #: what planning cost (sequences read, bytes hashed, MB/s)
    costs: PlanCosts = field(default_factory=PlanCosts)
    #: sequences whose earlier published data this run withdrew (their last run failed)
    withdrawn: list[str] = field(default_factory=list)
    #: manifest / memo files that could not be written (a full disk), with the error
    write_errors: list[str] = field(default_factory=list)

    @property
    def failed(self) -> list[UnitOutcome]:
        return [o for o in self.outcomes.values() if o.status == Status.FAILED]

    @property
    def skipped(self) -> list[UnitOutcome]:
        return [o for o in self.outcomes.values() if o.status == Status.SKIPPED]

    def failed_frames(self) -> dict[str, list[dict]]:
        """sequence -> the frames detect left out for bad input (run now or cached)."""
        out = {}
        for (seq, stage), o in sorted(self.outcomes.items()):
            bad = o.summary.get("failed_frames") if stage == "detect" else None
            if bad and o.finished:
                out[seq] = bad
        return out

    @property
    def exit_code(self) -> int:
        """0 when every sequence and frame went through and everything was written; 1 otherwise."""
        bad_export = any(v != "done" for v in self.dataset_exports.values())
        return int(
            bool(
                self.failed
                or self.skipped
                or self.failed_frames()
                or bad_export
                or self.write_errors
            )
        )

    def ran(self, stage: str | None = None) -> list[tuple[str, str]]:
        return sorted(
            k for k, o in self.outcomes.items() if o.ran and (stage is None or k[1] == stage)
        )


def _record(manifest: Manifest, outcome: UnitOutcome, report: RunReport | None = None) -> None:
    """Journal a unit's outcome (done, failed or skipped); a disk error is reported, not raised:
    the row stays in memory for the final save and the run goes on."""
    if outcome.status == Status.CACHED:
        return
    rec = StageRecord(
        sequence=outcome.sequence,
        stage=outcome.stage,
        key=outcome.key,
        status=outcome.status.value,
        location=outcome.location,
        error=outcome.error,
        seconds=round(outcome.seconds, 3),
        finished_at=time.time(),
        summary=outcome.summary,
        parts=outcome.parts,
    )
    try:
        manifest.record(rec)
    except OSError as exc:
        if report is None:
            raise
        report.write_errors.append(f"manifest journal {exc.filename}: {exc.strerror}")
    if outcome.status == Status.DONE:
        remove_stale_versions(manifest.root, outcome.stage, outcome.sequence, outcome.key)


def _save(manifest: Manifest, report: RunReport) -> None:
    try:
        manifest.save()
    except OSError as exc:
        report.write_errors.append(f"manifest {exc.filename}: {exc.strerror}")


def check_run_paths(config: Config, sequences: list[str] | None = None) -> list[str]:
    """Before any work: the output store is writable and the dataset root holds sequences;
    returns the sequences to run. Raises storage.manifest.OutputError / storage.coda's
    CodaFormatError with one clear line."""
    check_writable(Path(config.output.root))
    if sequences is not None:
        return [str(s) for s in sequences]
    check_dataset_root(Path(config.dataset.root))
    return selected_sequences(config)


class Submitter:
    """How units run. This one: here, at once (``submit`` returns the outcome). The Prefect flows
    use one that returns futures and yields outcomes as they complete (flows/pipeline/run.py)."""

    def submit(self, stage: str, *args) -> UnitOutcome | Any:
        return execute_unit(*args)

    def completed(self, futures: list) -> Any:
        return iter(())


class _Units:
    """Submits units and records their outcomes."""

    def __init__(
        self,
        config: Config,
        manifest: Manifest,
        report: RunReport,
        submitter: Submitter,
        stages: tuple[str, ...],
    ):
        self.config, self.manifest, self.report = config, manifest, report
        self.submitter, self.stages = submitter, stages
        #: sequence -> stage -> its outcome, or a future of it
        self.results: dict[str, dict[str, Any]] = {}
        self.futures: list = []
        self.on_done: Callable[[UnitOutcome], None] = lambda outcome: None

    def fail_plan(self, plan: SequencePlan) -> None:
        self.finish(UnitOutcome(plan.sequence, "detect", "", {}, Status.FAILED, error=plan.error))

    def finish(self, outcome: UnitOutcome) -> None:
        self.report.outcomes[(outcome.sequence, outcome.stage)] = outcome
        _record(self.manifest, outcome, self.report)
        self.on_done(outcome)

    def submit(self, plan: SequencePlan, stage: str) -> None:
        mine, unit = self.results.setdefault(plan.sequence, {}), plan.units[stage]
        if unit.fresh:
            rec = self.manifest.get(plan.sequence, stage)
            assert rec is not None  # fresh: recorded done
            mine[stage] = UnitOutcome(
                plan.sequence,
                stage,
                unit.key,
                unit.parts,
                Status.CACHED,
                location=rec.location,
                summary=rec.summary,
            )
            self.report.outcomes[(plan.sequence, stage)] = mine[stage]
            return
        mine[stage] = self.submitter.submit(
            stage,
            unit,
            self.report.out_root,
            {u: mine[u] for u in STAGES[stage] if u in mine},  # all but in a stage-level run
            plan.fingerprint,
            runtime(self.config),
        )
        if isinstance(mine[stage], UnitOutcome):  # ran here
            self.finish(mine[stage])
        else:
            self.futures.append(mine[stage])

    def wait(self) -> None:
        for outcome in self.submitter.completed(self.futures):
            self.finish(outcome)


def run_units(
    config: Config,
    force: bool = False,
    sequences: list[str] | None = None,
    progress: bool = True,
    verify: bool = False,
    plans: list[SequencePlan] | None = None,
    lock_held: bool = False,
    submitter: Submitter | None = None,
    stages: Collection[str] | None = None,
) -> RunReport:
    """Plan and run; the body of both flows (which pass a Prefect ``submitter``). Without one
    (``inline``) every unit runs here, in order. ``verify``: hash every input file.
    ``plans``: already made under this run's lock (flows.pipeline.plan.plan_without_hashing).
    ``lock_held``: the caller holds the output store's lock (checked) and keeps it.
    ``stages``: a stage-level run of these stages only (benchmarks, tests): the others neither run
    nor count as anyone's upstream (fuse with ``body_source: ground-truth`` needs no fit), and
    the run publishes nothing dataset-level (no dataset export made, no sequence withdrawn)."""
    out_root, started = Path(config.output.root), time.perf_counter()
    ids = check_run_paths(config, sequences)
    run = tuple(s for s in STAGES if stages is None or s in stages)
    if not run or set(stages or ()) - set(run):
        raise ValueError(f"stages {sorted(stages or ())}: expected some of {list(STAGES)}")
    with holding_lock(out_root) if lock_held else run_lock(out_root):
        report = RunReport(out_root, [])
        sweep_temporaries(out_root)  # leftovers of earlier (killed) runs
        manifest = Manifest.load(out_root)
        manifest.meta.update(
            {"config_hash": config_hash(config), "config": config.model_dump(mode="json")}
        )
        record_data_root(manifest, config.dataset.root)  # export / evaluate default to it
        units = _Units(config, manifest, report, submitter or Submitter(), run)
        cache = FingerprintCache(out_root / ".cache" / "sequences", verify)
        with _Progress(report, units, progress, len(ids)) as bars:
            for plan in (
                plans
                if plans is not None
                else iter_plans(config, manifest, cache, force, ids, report.costs)
            ):
                report.plans.append(plan)
                bars.planned()
                if plan.error:
                    units.fail_plan(plan)
                else:
                    units.submit(plan, run[0])  # now: the next sequences are hashed meanwhile
            report.write_errors += cache.errors
            _save(manifest, report)  # the meta (config, inputs) with the rows so far
            bars.start(units)
            # stage-major order: a thread pool runs tasks in submission order and a task waiting on
            # its upstream holds a thread, so every sequence's track goes first, then every fit, ...
            for stage in run[1:]:
                for plan in report.plans:
                    if not plan.error:
                        units.submit(plan, stage)
            units.wait()
        if stages is None:
            _withdraw_failed(config, report)
            _dataset_exports(config, manifest, report)
        _save(manifest, report)
    report.seconds = time.perf_counter() - started
    return report


def _first_problem(report: RunReport, plan: SequencePlan) -> str | None:
    """Why a sequence is not published by this run (None when its export is done or cached)."""
    if plan.error:
        return plan.error
    export = report.outcomes.get((plan.sequence, "export"))
    if export is not None and export.finished:
        return None
    for stage in STAGES:
        o = report.outcomes.get((plan.sequence, stage))
        if o is not None and o.status == Status.FAILED:
            return f"{stage}: {o.error}"
    return "export did not run"


def _withdraw_failed(config: Config, report: RunReport) -> None:
    """Withdraw the published data of every sequence this run could not publish (and mark it
    failed in the sequences table), so the dataset never shows outputs the manifest calls failed."""
    ex = export_inputs(config)
    for plan in report.plans:
        problem = _first_problem(report, plan)
        if problem is None:
            continue
        row = {
            "fingerprint": plan.fingerprint,
            "config_hash": ex.content_hash,
            "code_version": CODE_VERSIONS["export"],
        }
        try:
            if withdraw_sequence(report.out_root, plan.sequence, problem, row):
                report.withdrawn.append(plan.sequence)
        except (OSError, ValueError) as exc:  # e.g. a sequence id that is no valid partition name
            report.write_errors.append(f"withdrawing sequence {plan.sequence}: {exc}")


def _dataset_exports(config: Config, manifest: Manifest, report: RunReport) -> None:
    """The Occ3D / nuScenes exports of the whole dataset (``export.formats``), made again when a
    sequence was (re)published or withdrawn, or their settings changed. Each is written aside and
    swapped in, so a failed or killed export leaves the previous one. A failure is reported, not
    raised: the sequences are published."""
    ex = dataset_export_inputs(config)
    published = report.withdrawn or any(
        st == "export" and o.status == Status.DONE for (_, st), o in report.outcomes.items()
    )
    key = f"{inputs_hash(ex)}-v{DATASET_EXPORTS_VERSION}"
    done = manifest.meta.setdefault("dataset_exports", {})
    for fmt in ex.formats:
        if not (published or done.get(fmt) != key):
            continue
        final = Path(config.output.root) / "exports" / fmt
        try:
            with staged_folder(final) as tmp:
                export_dataset(
                    ex, Path(config.output.root), Path(config.dataset.root), fmt, target=tmp
                )
            done[fmt] = key
            report.dataset_exports[fmt] = "done"
        except Exception as exc:  # noqa: BLE001 - the sequences stay published
            done.pop(fmt, None)
            report.dataset_exports[fmt] = f"failed: {type(exc).__name__}: {exc}"


class _Progress:
    """One progress line for planning, then one per stage (never one per sequence)."""

    def __init__(self, report: RunReport, units: _Units, enabled: bool, sequences: int):
        self.report, self.enabled, self.plan_bar = report, enabled, None
        self.bars: dict[str, Any] = {}
        if enabled and sequences > 1:
            from tqdm import tqdm

            self.plan_bar = tqdm(total=sequences, desc="  plan", unit="seq", leave=True)

    def __enter__(self) -> _Progress:
        return self

    def planned(self) -> None:
        if self.plan_bar is not None:
            self.plan_bar.update(1)

    def start(self, units: _Units) -> None:
        if self.plan_bar is not None:
            self.plan_bar.close()
        todo = {
            s: sum(1 for p in self.report.plans if not p.error and not p.units[s].fresh)
            for s in units.stages
        }
        if not self.enabled or not any(todo.values()):
            return
        from tqdm import tqdm

        self.bars = {
            s: tqdm(total=todo[s], desc=f"{s:>6}", unit="seq", position=i, leave=True)
            for i, s in enumerate(units.stages)
        }
        units.on_done = lambda o: self.bars[o.stage].update(1) if o.stage in self.bars else None

    def __exit__(self, *exc) -> None:
        for bar in [*self.bars.values(), *([self.plan_bar] if self.plan_bar is not None else [])]:
            bar.close()


def export_dataset(
    ex: DatasetExportInputs,
    out_root: Path,
    data_root: Path | None,
    fmt: str,
    target: Path | None = None,
    gt: bool = False,
) -> Path:
    """Export the published dataset (every sequence) for occupancy trainers; ``gt``: Occ3D labels
    from the synthetic ground truth under ``data_root`` instead of the pipeline's. ``data_root``
    None: the raw data root recorded by the run that built the dataset."""
    from storage.export.nuscenes import export_nuscenes
    from storage.export.occ3d import export_occ3d

    target = Path(target) if target is not None else Path(out_root) / "exports" / fmt
    if gt and fmt != "occ3d":
        raise ValueError(f"--gt exports Occ3D labels; it does not apply to --format {fmt}")
    if fmt == "occ3d":
        export_occ3d(
            out_root,
            target,
            scene_prefix=ex.scene_prefix,
            val_sequences=ex.val_sequences,
            gt_root=data_root_for(out_root, data_root) if gt else None,
        )
    else:
        export_nuscenes(
            out_root,
            target,
            version=ex.nuscenes_version,
            scene_prefix=ex.scene_prefix,
            source_root=data_root_for(out_root, data_root),
            min_range_m=ex.min_range_m,
            val_sequences=ex.val_sequences,
            **({"infos_data_root": ex.infos_data_root} if ex.infos_data_root else {}),
        )
    return target


def _first_line(text: str) -> str:
    return text.splitlines()[0] if text else ""


def summary_table(report: RunReport) -> str:
    """Time per stage, cached vs run; then every sequence that failed, was skipped, lost frames
    or was withdrawn, each with its reason (one line each), and what planning cost."""
    lines = []
    header = f"{'stage':<8}{'ran':>5}{'cached':>8}{'failed':>8}{'skipped':>9}{'seconds':>10}"
    lines.append(header)
    lines.append("-" * len(header))
    for stage in STAGES:
        outs = [o for (s, st), o in report.outcomes.items() if st == stage]
        ran, cached, failed, skipped = (
            sum(o.status == status for o in outs)
            for status in (Status.DONE, Status.CACHED, Status.FAILED, Status.SKIPPED)
        )
        secs = sum(o.seconds for o in outs)
        lines.append(f"{stage:<8}{ran:>5}{cached:>8}{failed:>8}{skipped:>9}{secs:>10.1f}")
    frames = sum(p.num_frames for p in report.plans)
    lines.append(
        f"{len(report.plans)} sequence(s), {frames} frame(s), {report.seconds:.1f} s wall; "
        f"{report.costs.line()}"
    )
    not_impl = sorted(
        {st for (s, st), o in report.outcomes.items() if o.summary.get("implemented") is False}
    )
    if not_impl:
        lines.append(f"not implemented yet (placeholders): {', '.join(not_impl)}")
    for o in report.failed:
        lines.append(f"FAILED {o.sequence}/{o.stage}: {_first_line(o.error)}")
    skipped_stages: dict[str, list[str]] = {}
    for o in report.skipped:
        skipped_stages.setdefault(o.sequence, []).append(o.stage)
    for seq, stages in sorted(skipped_stages.items()):
        lines.append(f"SKIPPED {seq}/{', '.join(stages)}: an upstream stage did not finish")
    for seq, bad in report.failed_frames().items():
        more = f" (+{len(bad) - 3} more)" if len(bad) > 3 else ""
        lines += [
            f"FRAME FAILED {seq}/frame {b['frame']}: {_first_line(b['error'])}" for b in bad[:3]
        ]
        lines += [f"FRAME FAILED {seq}: {len(bad)} frame(s) left out{more}"] if more else []
    if report.withdrawn:
        lines.append(
            f"WITHDRAWN {', '.join(report.withdrawn)}: earlier published data removed (the sequences "
            "table marks them failed)"
        )
    for fmt, state in sorted(report.dataset_exports.items()):
        lines.append(f"{fmt} export: {state}")
    lines += [f"WRITE FAILED {e}" for e in report.write_errors]
    lines += [f"WARNING {p.sequence}: {w}" for p in report.plans for w in p.warnings]
    return "\n".join(lines)
