"""Prefect flows: ``rebuild_dataset`` (many sequences) and ``process_sequence`` (one).

One Prefect task is one (sequence, stage) unit: the unit of caching, retry and failure. The body
of the flows is flows.pipeline.units.run_units (planning, recording, withdrawing failed
sequences, the dataset-level exports), given a submitter that makes each unit a Prefect task on
the task runner ``config.dask`` asks for.
"""

from __future__ import annotations

import contextlib

from prefect import flow, task
from prefect.cache_policies import NO_CACHE
from prefect.futures import as_completed

from configs.schema import Config
from flows.pipeline.inputs import Runtime
from flows.pipeline.outcome import UnitOutcome
from flows.pipeline.plan import UnitPlan
from flows.pipeline.signals import keep_stop_handlers
from flows.pipeline.units import (  # noqa: F401 - the pipeline's API, as before the split
    DiskFullError,
    RunReport,
    Submitter,
    _record,
    check_run_paths,
    execute_unit,
    export_dataset,
    run_units,
    summary_table,
)


@task(name="stage", cache_policy=NO_CACHE, task_run_name="{unit.stage}-{unit.sequence}")
def stage_task(
    unit: UnitPlan,
    out_root,
    upstream: dict[str, UnitOutcome],
    fingerprint: str,
    runtime: Runtime,
    units: dict[str, UnitPlan] | None = None,
) -> UnitOutcome:
    return execute_unit(unit, out_root, upstream, fingerprint, runtime, units)


class PrefectSubmitter(Submitter):
    """Each unit a Prefect task (its upstream outcomes may be futures: Prefect waits for them)."""

    def __init__(self, config: Config):
        self.config = config

    def submit(self, stage: str, *args):
        with self._gpu_annotation(stage):
            return stage_task.submit(*args)

    def completed(self, futures: list):
        for fut in as_completed(futures):
            yield fut.result()

    def _gpu_annotation(self, stage: str):
        if stage == "fit" and self.config.dask.gpu_fit and self.config.dask.runner == "dask":
            import dask

            return dask.annotate(resources={"GPU": 1})
        return contextlib.nullcontext()


@flow(name="run-units", log_prints=True)
def _run_units_flow(
    config: Config,
    force: bool,
    sequences: list[str] | None,
    progress: bool,
    verify: bool = False,
    lock_held: bool = False,
    prune: bool = False,
) -> RunReport | DiskFullError:
    with keep_stop_handlers():  # Prefect's SIGTERM handler would wait for the stages in flight
        try:
            return run_units(
                config,
                force=force,
                sequences=sequences,
                progress=progress,
                verify=verify,
                lock_held=lock_held,
                submitter=PrefectSubmitter(config),
                prune=prune,
            )
        except DiskFullError as exc:
            # returned, not raised: Prefect would log a crash with a traceback; the caller
            # (flows/cli.py) raises it again, one line
            return exc


@flow(name="rebuild-dataset", log_prints=True)
def rebuild_dataset(
    config: Config,
    force: bool = False,
    sequences: list[str] | None = None,
    progress: bool = True,
    verify: bool = False,
    lock_held: bool = False,
    prune: bool = False,
) -> RunReport:
    """Every selected sequence through detect -> track -> fit / map -> fuse -> export, then the
    dataset-level exports of ``export.formats`` wherever they do not match the published
    sequences. ``lock_held``: the caller (the CLI) holds the store's lock; ``prune``: take
    sequences whose input is gone out of the dataset.

    The units run in a subflow on the task runner ``config.dask`` asks for (threads, a Dask
    LocalCluster, or ``dask.address``), however this flow was started (CLI, deployment, test).
    """
    from flows.pipeline.runtime import task_runner

    inner = _run_units_flow.with_options(task_runner=task_runner(config))
    return inner(config, force, sequences, progress, verify, lock_held, prune)


@flow(name="process-sequence", log_prints=True)
def process_sequence(config: Config, sequence: str, force: bool = False) -> RunReport:
    """One sequence through the six stages (on the task runner of ``config.dask``)."""
    return rebuild_dataset(config, force=force, sequences=[sequence], progress=False)
