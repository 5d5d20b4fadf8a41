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

import contextlib
import dataclasses
import errno
import os
import shutil
import threading
import time
import traceback
from collections.abc import Callable, Collection, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from configs.schema import Config, config_hash
from flows.pipeline.config_files import check_config_files
from flows.pipeline.dag import CODE_VERSIONS, DATASET_EXPORTS_VERSION, STAGES
from flows.pipeline.inputs import (
    DatasetExportInputs,
    Runtime,
    dataset_export_inputs,
    export_inputs,
    inputs_hash,
    map_inputs,
    runtime,
    source,
)
from flows.pipeline.outcome import Status, UnitOutcome
from flows.pipeline.plan import (
    PlanCosts,
    SequencePlan,
    UnitPlan,
    iter_plans,
    selected_sequences,
)
from storage.atomic import move_into_place, named, os_error_line, staged_folder, temporary_name
from storage.completion import (
    RECORD,
    RECORD_VERSION,
    check_files,
    check_record,
    read_record,
    write_record,
)
from storage.layout import shown
from storage.manifest import (
    FingerprintCache,
    Manifest,
    OutputError,
    StageRecord,
    check_store_place,
    check_writable,
    data_root_for,
    holding_lock,
    record_data_root,
    remove_caches,
    remove_stale_versions,
    run_lock,
    stage_dir,
    sweep_temporaries,
)
from storage.products import read_summary, write_summary
from storage.publish import (
    intent_problem,
    pending_publications,
    published_names,
    published_versions,
    recover_publications,
    remove_sequence,
    withdraw_sequence,
)

#: a unit's error that starts so is a full disk (or quota): the run stops (DiskFullError)
DISK_FULL = "DISK FULL: "
#: set when a unit met a full disk: units not yet started are skipped, the run ends at once
_DISK_FULL = threading.Event()


class DiskFullError(RuntimeError):
    """The output's file system is full: the run stopped (one line: the file system, what is
    free, what to do). Finished units are kept; the next run, after space is freed, resumes."""


def is_disk_full(exc: BaseException) -> bool:
    return isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, getattr(errno, "EDQUOT", -1))


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
    units: dict[str, UnitPlan] | None = None,
) -> UnitOutcome:
    """Run one (sequence, stage); never raises for a stage error (the outcome is failed).

    A damaged upstream output is a cache miss, not a failure: when the stage fails and an
    upstream folder no longer holds what its completion record says (content hashes: a rewrite
    that kept every size passes the plan's check), that upstream unit is computed again (from
    ``units``, the sequence's unit plans; recursively, should its own upstream be damaged too)
    and the stage runs once more. The outcome's ``repaired`` lists what was remade."""
    before = _record_ids(out_root, upstream)
    outcome = _execute_once(unit, out_root, upstream, fingerprint, runtime)
    if outcome.status != Status.FAILED or not units:
        return outcome
    damaged = {}
    for stage, o in upstream.items():
        problem = check_record(Path(out_root) / o.location, deep=True)
        if problem:
            damaged[stage] = problem
    if not damaged:
        if _record_ids(out_root, upstream) != before:  # another unit repaired it meanwhile
            return _execute_once(unit, out_root, upstream, fingerprint, runtime)
        return outcome
    repaired = []
    for stage in (s for s in STAGES if s in damaged):
        again = execute_unit(
            units[stage],
            out_root,
            {u: _found(units[u], out_root) for u in STAGES[stage]},
            fingerprint,
            runtime,
            units,
        )
        if again.status != Status.DONE:
            return dataclasses.replace(
                outcome,
                error=outcome.error
                + (
                    f" (its upstream {stage} was damaged, {damaged[stage]}, and could not be made "
                    f"again: {again.error or again.status.value})"
                ),
            )
        repaired += [*again.repaired, f"{stage}: {damaged[stage]}"]
    outcome = _execute_once(unit, out_root, upstream, fingerprint, runtime)
    return dataclasses.replace(outcome, repaired=tuple(repaired))


def _record_ids(out_root: Path, upstream: dict[str, UnitOutcome]) -> dict[str, tuple[int, int]]:
    """(inode, mtime) of each upstream's completion record: changed when it was made again."""
    ids = {}
    for stage, o in upstream.items():
        try:
            st = os.stat(Path(out_root) / o.location / RECORD)
            ids[stage] = (st.st_ino, st.st_mtime_ns)
        except (OSError, KeyError):
            ids[stage] = (0, 0)
    return ids


def _found(unit: UnitPlan, out_root: Path) -> UnitOutcome:
    """The outcome of a unit taken as it is in the store (an upstream of a unit being repaired)."""
    final = stage_dir(out_root, unit.stage, unit.sequence, unit.key)
    return UnitOutcome(
        unit.sequence,
        unit.stage,
        unit.key,
        unit.parts,
        Status.CACHED,
        location=str(final.relative_to(out_root)),
    )


def _execute_once(
    unit: UnitPlan,
    out_root: Path,
    upstream: dict[str, UnitOutcome],
    fingerprint: str = "",
    runtime: Runtime = Runtime(),
) -> UnitOutcome:
    def outcome(status: Status, **more) -> UnitOutcome:
        return UnitOutcome(unit.sequence, unit.stage, unit.key, unit.parts, status, **more)

    if _DISK_FULL.is_set():
        return outcome(Status.SKIPPED, error="the run stopped: the output's disk is full")
    blocked = [s for s, o in upstream.items() if not o.finished]
    if blocked:
        return outcome(Status.SKIPPED, error=f"upstream {', '.join(blocked)} did not finish")
    final = stage_dir(out_root, unit.stage, unit.sequence, unit.key)
    location = str(final.relative_to(out_root))
    if final.exists():
        if reusable(unit, final):  # a whole output of this key (a run killed before recording it)
            summary = read_summary(final)
            return outcome(Status.DONE, location=location, summary=summary, reused=True)
        remove_output(final)  # damaged, forced, or a publication to make again
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
            write_record(tmp, stage=unit.stage, sequence=unit.sequence, key=unit.key)  # last
    except Exception as exc:  # noqa: BLE001 - one bad sequence fails alone, with its error
        if is_disk_full(exc):  # not this sequence's fault: the whole run stops (finish sets
            # the flag in the run's process: a worker process of a shared cluster keeps none)
            full = named(exc, final.parent) if isinstance(exc, OSError) else exc
            return outcome(Status.FAILED, error=DISK_FULL + os_error_line(full))
        return outcome(
            Status.FAILED,
            seconds=time.perf_counter() - started,
            error=_error_text(exc, final.parent),
            traceback=traceback.format_exc(limit=8),
        )
    return outcome(
        Status.DONE, location=location, summary=summary, seconds=time.perf_counter() - started
    )


def reusable(unit: UnitPlan, final: Path) -> bool:
    """Whether an output folder found at a unit's key can stand for running it: it is whole
    (its completion record verifies, content hashes included: the plan may have run the unit
    because hashing found it damaged), the unit is not forced, and it is not the export stage,
    whose work is the publication itself (made again whenever the plan says it must be), and it
    does not run because its upstream is being made again (flows.pipeline.plan: then it is made
    from that upstream's new output, as the plan says)."""
    return (
        not unit.force
        and unit.stage != "export"
        and not unit.reason.startswith("upstream ")  # its upstream is being made again: so is it
        and not check_record(final, deep=True)
    )


def remove_output(final: Path) -> None:
    """Remove a unit's output folder: renamed aside (hidden, swept after a kill), then deleted."""
    try:
        aside = move_into_place(final, temporary_name(final))
    except FileNotFoundError:  # removed meanwhile (another unit repairing the same output)
        return
    shutil.rmtree(aside, ignore_errors=True)


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
    #: leftovers of earlier runs removed at the start
    swept: int = 0
    #: publications (or withdrawals) a killed run left half done, completed at the start
    recovered: list[str] = field(default_factory=list)
    #: one line per publication intent that was not one this code wrote, rolled back instead
    rolled_back: list[str] = field(default_factory=list)
    #: sequences in the store (published, withdrawn or in the manifest) whose input is no longer
    #: under the data root, and those of them this run took out of the store (``prune``)
    gone: list[str] = field(default_factory=list)
    pruned: list[str] = field(default_factory=list)

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
    returns the sequences to run. Raises storage.manifest.OutputError / the source's InputError
    (storage.files) with one clear line."""
    for what, path in (("output store", config.output.root), ("dataset root", config.dataset.root)):
        try:  # the store records its paths as JSON / Parquet text, which must be UTF-8
            str(path).encode("utf-8")
        except UnicodeEncodeError:
            raise OutputError(
                f"{what} {shown(path)}: the path is not UTF-8 (undecodable bytes shown as "
                "\\udcXX); rename it or choose another folder"
            ) from None
    check_store_place(Path(config.output.root), Path(config.dataset.root))
    check_writable(Path(config.output.root))
    check_config_files(config)  # a bad model file is the config's error, not every sequence's
    if sequences is not None:
        return [str(s) for s in sequences]
    source(config).check_root(Path(config.dataset.root))
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
        if outcome.error.startswith(DISK_FULL):  # not recorded: the unit did not fail, the disk
            _DISK_FULL.set()  # units of this process not started yet are skipped
            raise DiskFullError(outcome.error[len(DISK_FULL) :])
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
            plan.units,
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
    prune: bool = False,
    stages: Collection[str] | None = None,
) -> RunReport:
    """Plan and run; the body of both flows (which pass a Prefect ``submitter``). Without one
    (``inline``) every unit runs here, in order. ``verify``: hash every input file and every
    output (stage products, published sequences, dataset-level exports) against its record.
    ``plans``: already made under this run's lock (flows.pipeline.plan.plan_without_hashing).
    ``lock_held``: the caller holds the output store's lock (checked) and keeps it.
    ``prune``: take sequences whose input is gone out of the store (else they are reported).
    ``stages``: a stage-level run of these stages only (benchmarks, tests): the others neither run
    nor count as anyone's upstream (fuse with ``body_source: ground-truth`` needs no fit), and
    the run publishes nothing dataset-level (no dataset export made, no sequence withdrawn)."""
    out_root, started = Path(config.output.root), time.perf_counter()
    ids = check_run_paths(config, sequences)
    run = tuple(s for s in STAGES if stages is None or s in stages)
    if not run or set(stages or ()) - set(run):
        raise ValueError(f"stages {sorted(stages or ())}: expected some of {list(STAGES)}")
    _DISK_FULL.clear()
    with holding_lock(out_root) if lock_held else run_lock(out_root), _stop_when_full(out_root):
        report = RunReport(out_root, [])
        # before the sweep: it reads temporaries
        report.recovered = recover_publications(out_root, report.rolled_back)
        report.swept = sweep_temporaries(out_root)
        if force:  # every cache product is made again too (storage.manifest.CACHE_PRODUCTS)
            remove_caches(out_root)
        manifest = Manifest.load(out_root)
        adopt_unrecorded_outputs(manifest)
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
            _gone(config, manifest, report, ids, prune)
            _dataset_exports(config, manifest, report, verify, force)
        _save(manifest, report)
    report.seconds = time.perf_counter() - started
    return report


@contextlib.contextmanager
def _stop_when_full(out_root: Path) -> Iterator[None]:
    """A full disk anywhere in a run (a unit, a publication, the manifest) ends it with one
    DiskFullError line; the temporaries written so far are removed (they hold the space the
    next run needs) while the lock is still held, so nothing but finished units is left."""
    try:
        yield
    except DiskFullError:
        _DISK_FULL.set()
        sweep_temporaries(out_root)
        raise
    except OSError as exc:
        if not is_disk_full(exc):
            raise
        _DISK_FULL.set()
        sweep_temporaries(out_root)
        raise DiskFullError(os_error_line(exc)) from None


def adopt_unrecorded_outputs(manifest: Manifest) -> None:
    """A store written before completion records (no ``completion_records`` in the manifest's
    meta): record every unit output it calls done as it is (what the code of then trusted), once;
    from then on a folder without its record is a unit that did not finish."""
    if manifest.meta.get("completion_records"):
        return
    for rec in manifest.rows.values():
        folder = manifest.root / rec.location
        if (
            rec.status == "done"
            and rec.location
            and (folder / "summary.json").is_file()
            and not (folder / RECORD).exists()
        ):
            write_record(folder, stage=rec.stage, sequence=rec.sequence, key=rec.key)
    manifest.meta["completion_records"] = RECORD_VERSION


def gone_sequences(config: Config, manifest: Manifest, selected: list[str]) -> list[str]:
    """Sequences the store knows (published, withdrawn, or in the manifest) whose input is not
    under the data root any more (deleted, renamed), the selected ones aside (they fail)."""
    root = Path(config.dataset.root)
    known = published_names(manifest.root) | {seq for seq, _ in manifest.rows}
    present = set(source(config).sequence_ids(root)) if root.exists() else set()
    return sorted(known - present - set(selected))


def store_problems(config: Config, manifest: Manifest, deep: bool = False) -> list[str]:
    """What ``status`` reports beyond the units (one line each): publications a killed run left
    half done, sequences whose input is gone, dataset-level exports that do not match the
    published sequences."""
    out_root = Path(config.output.root)
    lines = [
        f"{shown(seq):>6}  "
        + (
            f"{garbage}: the next rebuild or export rolls it back"
            if (garbage := intent_problem(out_root, seq))
            else "publication interrupted by a killed run (the next rebuild or export completes it)"
        )
        for seq in pending_publications(out_root)
    ]
    selected = selected_sequences(config) if Path(config.dataset.root).is_dir() else []
    lines += [
        f"{seq:>6}  in the dataset but no longer under the data root {config.dataset.root}; "
        "`rebuild --prune` takes it out"
        for seq in gone_sequences(config, manifest, selected)
    ]
    ex, key = dataset_export_inputs(config), dataset_export_key(config, out_root)
    empty = not published_versions(out_root)
    for fmt in ex.formats:
        problem = dataset_export_problem(out_root / "exports" / fmt, key, deep, empty)
        if problem:
            lines.append(f"{fmt} export stale: {problem}")
    return lines


def _gone(
    config: Config, manifest: Manifest, report: RunReport, selected: list[str], prune: bool
) -> None:
    report.gone = gone_sequences(config, manifest, selected)
    if not prune:
        return
    for seq in report.gone:
        try:
            remove_sequence(report.out_root, seq)
            for folder in (report.out_root / "stages").glob(f"*/{seq}"):
                remove_output(folder)
            (report.out_root / ".cache" / "sequences" / f"{seq}.json").unlink(missing_ok=True)
        except (OSError, ValueError) as exc:
            report.write_errors.append(f"pruning sequence {seq}: {exc}")
            continue
        manifest.drop_sequence(seq)
        report.pruned.append(seq)


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


EXPORT_RECORD = ".mobileocc-export.json"


def dataset_export_key(config: Config, out_root: Path) -> str:
    """What a dataset-level export is made of: its settings and the published version of every
    sequence (so a sequence published, withdrawn or gone changes it, whatever run did it)."""
    return inputs_hash(
        [dataset_export_inputs(config), published_versions(out_root), DATASET_EXPORTS_VERSION]
    )


def dataset_export_problem(
    folder: Path, key: str, deep: bool = False, nothing_published: bool = False
) -> str:
    """Why the export in ``folder`` does not match ``key`` ("" when it does): missing, made of
    other settings or sequences, or a file missing / of another size (``deep``: content).
    ``nothing_published``: no sequence is published, so there must be no export (an old one
    would still offer withdrawn sequences)."""
    if nothing_published:
        return f"{folder} exports sequences none of which is published" if folder.exists() else ""
    if not folder.is_dir():
        return f"{folder} is missing"
    try:
        record = read_record(folder, EXPORT_RECORD)
    except ValueError as exc:
        return str(exc)
    if record.get("key") != key:
        return "made of other settings or published sequences"
    return check_files(folder, record["files"], deep)


def _dataset_exports(
    config: Config, manifest: Manifest, report: RunReport, deep: bool, force: bool = False
) -> None:
    """The Occ3D / nuScenes exports of the whole dataset (``export.formats``), made again
    whenever they do not match the published sequences and their settings (its record:
    :func:`dataset_export_problem`). Each is written aside and swapped in, so a failed or killed
    export leaves the previous one (reported stale by ``status``). A failure is reported, not
    raised: the sequences are published. With no sequence published there is no export."""
    ex, key = dataset_export_inputs(config), dataset_export_key(config, report.out_root)
    done = manifest.meta.setdefault("dataset_exports", {})
    empty = not published_versions(report.out_root)
    for fmt in ex.formats:
        final = report.out_root / "exports" / fmt
        if not force and not dataset_export_problem(final, key, deep, empty):
            continue
        if empty:  # every sequence withdrawn: no export rather than one of withdrawn sequences
            remove_output(final)
            done.pop(fmt, None)
            report.dataset_exports[fmt] = "done"
            continue
        try:
            export_dataset(
                ex, report.out_root, Path(config.dataset.root), fmt, final, key=key, ours=True
            )
            done[fmt] = key
            report.dataset_exports[fmt] = "done"
        except Exception as exc:  # noqa: BLE001 - the sequences stay published
            done.pop(fmt, None)
            report.dataset_exports[fmt] = f"failed: {type(exc).__name__}: {exc}"


class _Progress:
    """One progress line for planning, then one per stage (never one per sequence); bars only on
    a terminal: written to a file or a pipe, one plain line per stage when its last unit ends
    (a bar's carriage-return redraws would fill the file)."""

    def __init__(self, report: RunReport, units: _Units, enabled: bool, sequences: int):
        import sys

        self.report, self.enabled, self.plan_bar = report, enabled, None
        self.tty = sys.stderr.isatty()
        self.bars: dict[str, Any] = {}
        if enabled and self.tty and sequences > 1:
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
        if not self.tty:
            left = dict(todo)

            def line(o: UnitOutcome) -> None:
                import sys

                if left.get(o.stage):
                    left[o.stage] -= 1
                    if not left[o.stage]:
                        # not print(): the Prefect flows' log_prints would take it
                        sys.stderr.write(f"{o.stage:>6}: {todo[o.stage]} unit(s) ended\n")
                        sys.stderr.flush()

            units.on_done = line
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
    key: str = "",
    ours: bool = False,
) -> Path:
    """Export the published dataset (every sequence) for occupancy trainers into ``target``
    (default ``OUT/exports/<fmt>``): written aside, recorded (``.mobileocc-export.json``: the
    files and ``key``) and swapped in whole; ``gt``: Occ3D labels from the synthetic ground truth
    under ``data_root`` instead of the pipeline's; ``data_root`` None: the raw data root recorded
    by the run that built the dataset. ``ours``: ``target`` is the store's own
    export folder (else :func:`check_export_target` refuses a folder of other things). Read
    under the store's read lock (storage.publish.reading) so no run changes the dataset
    meanwhile."""
    target = Path(target) if target is not None else Path(out_root) / "exports" / fmt
    if gt and fmt != "occ3d":
        raise ValueError(f"--gt exports Occ3D labels; it does not apply to --format {fmt}")
    if not ours:
        check_export_target(target)
    with staged_folder(target) as tmp:
        _export_into(ex, out_root, data_root, fmt, tmp, gt)
        write_record(tmp, format_record(fmt), format=fmt, key=key)
        if not ours:
            keep_other_formats(target, tmp, fmt)
        write_record(tmp, EXPORT_RECORD, format=fmt, key=key)
    return target


def format_record(fmt: str) -> str:
    """The record of one format's files in an export folder (``.mobileocc-export-<fmt>.json``)."""
    return f".mobileocc-export-{fmt}.json"


def keep_other_formats(target: Path, staged: Path, fmt: str) -> None:
    """Carry into ``staged`` the files another format's export wrote into ``target`` (FlashOcc
    wants the nuScenes tables and the Occ3D ``gts/`` in one folder: docs/exports.md), as its
    record lists them, so that exporting one format into a shared folder replaces that format's
    files only (a withdrawn sequence's old files go) and keeps the other's."""
    for other in ("occ3d", "nuscenes"):
        name = format_record(other)
        if other == fmt or not (target / name).is_file():
            continue
        try:
            files = read_record(target, name)["files"]
        except ValueError:
            continue  # an unreadable record: that export is not kept
        for rel in [*files, name]:
            src, dst = target / rel, staged / rel
            if dst.exists() or not src.is_file():
                continue
            dst.parent.mkdir(parents=True, exist_ok=True)
            try:
                os.link(src, dst)
            except OSError:
                shutil.copy2(src, dst)


def check_export_target(target: Path) -> None:
    """An export goes into a new folder, an empty one, or one holding an earlier export (its
    record says so); anything else (a file, a folder of other things) is refused with
    ExportTargetError, before any work."""
    if os.path.lexists(target) and not target.is_dir():
        raise ExportTargetError(f"export target {target} exists and is not a folder")
    if target.is_dir() and any(target.iterdir()) and not (target / EXPORT_RECORD).is_file():
        raise ExportTargetError(
            f"export target {target} holds files that are not a mobileocc export; choose a new "
            "or empty folder (an earlier export there is replaced as a whole)"
        )
    parent = (
        target.parent
    )  # made where missing, as `mkdir -p` (docs/exports.md: --to data/nuscenes)
    try:
        parent.mkdir(parents=True, exist_ok=True)
        probe = temporary_name(target)  # os.access says yes to root, even where nothing can go
        probe.mkdir()
        probe.rmdir()
    except FileExistsError:
        raise ExportTargetError(
            f"export target {target}: a file stands where its folder {parent} should be"
        ) from None
    except OSError as exc:
        raise ExportTargetError(
            f"export target {target}: its folder {parent} is not writable ({exc.strerror})"
        ) from None


class ExportTargetError(ValueError):
    """Where an export was asked to go cannot take it."""


def _export_into(
    ex: DatasetExportInputs, out_root: Path, data_root: Path, fmt: str, target: Path, gt: bool
) -> None:
    from storage.export.nuscenes import export_nuscenes
    from storage.export.occ3d import export_occ3d

    if fmt == "occ3d":
        export_occ3d(
            out_root,
            target,
            scene_prefix=ex.scene_prefix,
            val_sequences=ex.val_sequences,
            gt_root=data_root_for(out_root, data_root) if gt else None,
            source_root=_source_root(out_root, data_root),
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


def _source_root(out_root: Path, data_root: Path | None) -> Path | None:
    """The raw data root where one is known (the Occ3D export of robot logs names each image with
    the extension the nuScenes export gives it); None where it is not (it is not needed for the
    CODa layout, and export_occ3d says so when it is)."""
    from storage.manifest import recorded_data_root

    for root in (data_root, recorded_data_root(out_root)):
        if root is not None and Path(root).exists():  # a folder, or a single log file
            return Path(root)
    return None


def _first_line(text: str) -> str:
    return text.splitlines()[0] if text else ""


#: the reasons of units that run because their output was damaged (flows.pipeline.plan)
DAMAGED_REASONS = ("output damaged", "not published as recorded")


#: above this share of occupied voxels UNCLASSIFIED the end of a run says so (one line)
UNCLASSIFIED_WARN_SHARE = 0.5


def unclassified_share(summary: dict) -> float | None:
    """Share of occupied voxels (mask_lidar = 1) with no class in a fuse summary (None: the summary
    predates the count, or nothing is occupied)."""
    occ, unc = summary.get("occupied_voxels"), summary.get("unclassified_voxels")
    return unc / occ if occ and unc is not None else None


def unclassified_line(report: RunReport, cfg) -> str | None:
    """One line when the labels of the sequences fused are mostly (> 50 % of occupied voxels)
    UNCLASSIFIED: why (the image semantics the config asks for) and what to configure."""
    sums = [o.summary for (_, st), o in sorted(report.outcomes.items()) if st == "fuse"]
    occ = sum(s.get("occupied_voxels", 0) for s in sums)
    unc = sum(s.get("unclassified_voxels", 0) for s in sums)
    if not occ or unc / occ <= UNCLASSIFIED_WARN_SHARE:
        return None
    d, classes = cfg.detect, map_inputs(cfg).point_classes
    why = (
        "no image segmenter (detect.models.semantic.kind: none)"
        if d.image_provider == "models" and d.models.semantic.kind == "none"
        else f"the image semantics ({d.image_provider}) gave most returns no class"
    )
    if "geometry" in classes:
        why += f", and the geometric classes (map.point_classes: {classes}) could not tell them"
        more = ""
    else:
        why += f" and no geometric classes (map.point_classes: {classes})"
        more = ", or map.point_classes: camera+geometry (docs/geometric-classes.md)"
    return (
        f"LABELS MOSTLY UNCLASSIFIED: {100 * unc / occ:.1f} % of occupied voxels have no class: "
        f"{why}; configure detect.models.semantic (kind onnx: a Cityscapes segmenter, "
        f"configs/coda-onnx.yaml) or precomputed semantics (storage/PERCEPTION_FORMAT.md){more}"
    )


def summary_table(report: RunReport) -> str:
    """Time per stage, cached vs run; then every sequence that failed, was skipped, lost frames
    or was withdrawn, each with its reason (one line each), and what planning cost."""
    lines = []
    header = f"{'stage':<8}{'ran':>5}{'cached':>8}{'failed':>8}{'skipped':>9}{'seconds':>10}"
    lines.append(header)
    lines.append("-" * len(header))
    for stage in STAGES:
        outs = [o for (s, st), o in report.outcomes.items() if st == stage]
        ran = sum(o.status == Status.DONE and not o.reused for o in outs)
        cached = sum(o.status == Status.CACHED or o.reused for o in outs)
        failed = sum(o.status == Status.FAILED for o in outs)
        skipped = sum(o.status == Status.SKIPPED for o in outs)
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
    for seq in report.recovered:
        lines.append(f"RECOVERED {seq}: a publication a killed run left half done was completed")
    lines += [f"ROLLED BACK {line}" for line in report.rolled_back]
    for plan in report.plans:
        for stage, unit in plan.units.items():
            if unit.reason.startswith(DAMAGED_REASONS):
                lines.append(f"REPAIRED {plan.sequence}/{stage}: {unit.reason}")
    for (seq, stage), o in sorted(report.outcomes.items()):
        lines += [
            f"REPAIRED {seq}/{what.split(':', 1)[0]}: output damaged (found by {stage}): "
            f"{what.split(': ', 1)[-1]}"
            for what in o.repaired
        ]
    if report.pruned:
        lines.append(
            f"PRUNED {', '.join(report.pruned)}: no longer under the data root; taken out of "
            "the dataset"
        )
    elif report.gone:
        lines.append(
            f"GONE {', '.join(report.gone)}: in the dataset but no longer under the data root; "
            "`rebuild --prune` takes them out of the dataset"
        )
    for fmt, state in sorted(report.dataset_exports.items()):
        lines.append(f"{fmt} export: {state}")
    lines += [f"WRITE FAILED {e}" for e in report.write_errors]
    lines += [f"WARNING {p.sequence}: {w}" for p in report.plans for w in p.warnings]
    return "\n".join(shown(line) for line in lines)  # a name cannot forge a line
