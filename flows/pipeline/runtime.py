"""Where flows run: the Prefect API they report to and the task runner (threads or Dask).

Without ``PREFECT_API_URL`` Prefect starts a temporary server per process, and Dask worker
processes would each start their own (measured with prefect 3.8). So when no API is
configured we start one temporary server here and export its address, which the Dask worker
processes inherit. The server is a child process that the kernel ends when this process ends in
any way (``PR_SET_PDEATHSIG`` on Linux, a ``kill -9`` included), so no server outlives its CLI.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from collections.abc import Iterator

from configs.schema import Config


def _die_with(parent: int):
    """A ``preexec_fn``: the child gets SIGTERM when ``parent`` ends, however it ends (Linux
    ``PR_SET_PDEATHSIG``; the kernel sends it, so a ``kill -9`` of the CLI is covered)."""
    import ctypes
    import signal

    libc = ctypes.CDLL(None, use_errno=True)  # loaded here: the child only calls into it

    def preexec() -> None:
        libc.prctl(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG
        if os.getppid() != parent:  # the parent died before the line above
            os.kill(os.getpid(), signal.SIGTERM)

    return preexec


@contextlib.contextmanager
def _server_dies_with_this_process() -> Iterator[None]:
    """While Prefect starts its temporary server, its ``subprocess.Popen`` gets :func:`_die_with`."""
    if not sys.platform.startswith("linux"):
        yield  # elsewhere the server ends with server.stop() only
        return
    import prefect.server.api.server as server_module

    real = server_module.subprocess.Popen

    def popen(*args, **kwargs):
        kwargs.setdefault("preexec_fn", _die_with(os.getpid()))
        return real(*args, **kwargs)

    server_module.subprocess.Popen = popen
    try:
        yield
    finally:
        server_module.subprocess.Popen = real


@contextlib.contextmanager
def prefect_api() -> Iterator[str | None]:
    """Use the configured Prefect API, or a temporary local server for the duration."""
    if os.environ.get("PREFECT_API_URL"):
        yield os.environ["PREFECT_API_URL"]
        return
    home = tempfile.mkdtemp(prefix="mobileocc-prefect-")
    os.environ.setdefault("PREFECT_HOME", home)
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    from prefect.server.api.server import SubprocessASGIServer
    from prefect.settings import PREFECT_API_URL, temporary_settings

    server = SubprocessASGIServer()
    with _server_dies_with_this_process():
        server.start(timeout=120)
    os.environ["PREFECT_API_URL"] = server.api_url
    try:
        with temporary_settings(updates={PREFECT_API_URL: server.api_url}):
            yield server.api_url
            _drain_prefect_workers()  # flush logs and events while the server still answers
    finally:
        os.environ.pop("PREFECT_API_URL", None)
        server.stop()


def _drain_prefect_workers() -> None:
    import inspect

    from prefect.events.worker import EventsWorker
    from prefect.logging.handlers import APILogWorker
    from prefect.utilities.asyncutils import run_coro_as_sync

    async def drain() -> None:
        for result in (APILogWorker.drain_all(), EventsWorker.drain_all()):
            if inspect.isawaitable(result):
                await result

    try:
        run_coro_as_sync(drain())
    except RuntimeError:  # workers never started
        pass


def task_runner(config: Config):
    """ThreadPoolTaskRunner, a Dask LocalCluster with worker processes, or an existing cluster."""
    d = config.dask
    if d.runner == "thread" and d.address is None:
        from prefect.task_runners import ThreadPoolTaskRunner

        return ThreadPoolTaskRunner(max_workers=max(1, d.workers))
    from prefect_dask import DaskTaskRunner

    if d.address:
        return DaskTaskRunner(address=d.address)
    return DaskTaskRunner(
        cluster_kwargs={
            "n_workers": d.workers,
            "threads_per_worker": d.threads_per_worker,
            "processes": True,
            "memory_limit": d.memory_limit,
            "dashboard_address": None,
        }
    )
