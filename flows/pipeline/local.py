"""Running units without Prefect: a thread pool, or a Dask cluster used directly.

When no Prefect API is configured, Prefect's only place to report to is a temporary server that
this process starts (12 s on a 2-core machine, 17 s a small rebuild's fixed cost in all) and
whose records vanish with the process. Such a run gains nothing from Prefect, so with ``dask.prefect: auto`` (the
default) it runs its units here instead: the same :func:`flows.pipeline.units.execute_unit` per
(sequence, stage), the same outcomes, the same bytes. With ``PREFECT_API_URL`` set, or
``dask.prefect: always``, the Prefect flows of flows/pipeline/run.py run them.

A unit is handed to the pool only once its upstream outcomes are known (never a thread held
waiting), so any order of submission is safe.
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor, as_completed
from typing import Any

from configs.schema import Config
from flows.pipeline.outcome import UnitOutcome
from flows.pipeline.units import RunReport, Submitter, execute_unit, run_units


class ThreadSubmitter(Submitter):
    """Units on ``workers`` threads of this process. ``submit`` returns a Future of the unit's
    outcome; the unit starts when every upstream Future in its arguments has an outcome."""

    def __init__(self, workers: int):
        self.pool = ThreadPoolExecutor(max_workers=max(1, workers), thread_name_prefix="unit")

    def submit(self, stage: str, *args: Any) -> Future:
        unit, out_root, upstream, *rest = args
        result: Future = Future()
        pending = {name: f for name, f in upstream.items() if isinstance(f, Future)}
        lock = threading.Lock()

        def start() -> None:
            ready = {
                name: (o.result() if isinstance(o, Future) else o) for name, o in upstream.items()
            }
            job = self.pool.submit(execute_unit, unit, out_root, ready, *rest)
            job.add_done_callback(lambda done: _forward(done, result))

        if not pending:
            start()
            return result
        left = [len(pending)]

        def one_done(_: Future) -> None:
            with lock:
                left[0] -= 1
                last = left[0] == 0
            if last:
                start()

        for f in pending.values():
            f.add_done_callback(one_done)
        return result

    def completed(self, futures: list) -> Iterator[UnitOutcome]:
        try:
            for fut in as_completed(futures):
                yield fut.result()
        finally:
            self.pool.shutdown(wait=True, cancel_futures=True)


def _forward(done: Future, result: Future) -> None:
    error = done.exception()
    if error is not None:
        result.set_exception(error)
    else:
        result.set_result(done.result())


class DaskSubmitter(Submitter):
    """Units as plain Dask tasks on ``client`` (upstream futures resolved by Dask; the fit routed to
    ``GPU`` workers when ``gpu_fit``)."""

    def __init__(self, client, gpu_fit: bool = False):
        self.client, self.gpu_fit = client, gpu_fit

    def submit(self, stage: str, *args: Any):
        resources = {"GPU": 1} if stage == "fit" and self.gpu_fit else None
        return self.client.submit(
            execute_unit, *args, pure=False, resources=resources, key=_key(stage, args[0])
        )

    def completed(self, futures: list) -> Iterator[UnitOutcome]:
        from distributed import as_completed as dask_completed

        for fut in dask_completed(futures):
            yield fut.result()


def _key(stage: str, unit) -> str:
    from dask.base import tokenize

    return f"{stage}-{unit.sequence}-{tokenize(unit.key)}"


def uses_prefect(config: Config) -> bool:
    """Whether a run's units go through Prefect: ``dask.prefect`` always / never, or with auto
    only where a Prefect API is configured (``PREFECT_API_URL``)."""
    mode = config.dask.prefect
    return mode == "always" or (mode == "auto" and bool(os.environ.get("PREFECT_API_URL")))


@contextlib.contextmanager
def submitter(config: Config) -> Iterator[Submitter]:
    """A :class:`ThreadSubmitter` for ``dask.runner: thread``, else a :class:`DaskSubmitter` on a
    local cluster of worker processes (or the scheduler at ``dask.address``), closed at the end."""
    d = config.dask
    if d.runner == "thread" and d.address is None:
        yield ThreadSubmitter(d.workers)
        return
    from distributed import Client, LocalCluster

    if d.address:
        with Client(d.address) as client:
            yield DaskSubmitter(client, d.gpu_fit)
        return
    with (
        LocalCluster(
            n_workers=d.workers,
            threads_per_worker=d.threads_per_worker,
            processes=True,
            memory_limit=d.memory_limit,
            dashboard_address=None,
        ) as cluster,
        Client(cluster) as client,
    ):
        yield DaskSubmitter(client, d.gpu_fit)


def run_without_prefect(config: Config, **kwargs: Any) -> RunReport:
    """:func:`flows.pipeline.units.run_units` with this module's submitters (``kwargs`` as there)."""
    with submitter(config) as units_submitter:
        return run_units(config, submitter=units_submitter, **kwargs)
