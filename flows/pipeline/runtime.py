"""Where flows run: the Prefect API they report to and the task runner (threads or Dask).

Without ``PREFECT_API_URL`` Prefect starts a temporary server per process, and Dask worker
processes would each start their own (measured with prefect 3.8). So when no API is
configured we start one temporary server here and export its address, which the Dask worker
processes inherit. The server is a child process that the kernel ends when this process ends in
any way (``PR_SET_PDEATHSIG`` on Linux, a ``kill -9`` included), so no server outlives its CLI.

Before any work, a configured API (``PREFECT_API_URL``) and a configured scheduler
(``dask.address``) must answer; a temporary server must start within its time limit. Otherwise
:class:`RunnerUnavailable` says which address, what happened and what to do (one line; the CLI
exits 2), where Prefect or Dask would raise deep inside the run.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from collections.abc import Iterator

from configs.schema import Config

#: seconds a configured Prefect API or Dask scheduler has to answer before a run starts
ANSWER_TIMEOUT_S = 10.0
#: seconds the temporary Prefect server has to start
SERVER_START_TIMEOUT_S = 120


class RunnerUnavailable(RuntimeError):
    """The Prefect API or the Dask scheduler a run needs cannot be reached (checked first)."""


def check_prefect_api(url: str, timeout_s: float = ANSWER_TIMEOUT_S) -> None:
    """``url`` (a Prefect API, ``.../api``) answers its health check, else RunnerUnavailable."""
    import httpx

    try:
        response = httpx.get(f"{url.rstrip('/')}/health", timeout=timeout_s)
        response.raise_for_status()
    except (httpx.HTTPError, OSError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise RunnerUnavailable(
            f"PREFECT_API_URL={url} does not answer ({reason}): start that Prefect server, or "
            "unset PREFECT_API_URL so that mobileocc starts a temporary one"
        ) from None


def check_scheduler(address: str, timeout_s: float = ANSWER_TIMEOUT_S) -> None:
    """A ``tcp://host:port`` Dask scheduler accepts a connection, else RunnerUnavailable (other
    schemes are left to Dask)."""
    import socket
    from urllib.parse import urlsplit

    parts = urlsplit(address if "://" in address else f"tcp://{address}")
    if parts.scheme != "tcp":
        return
    try:
        host, port = parts.hostname, parts.port or 8786
    except ValueError as exc:  # a port that is not a number
        raise RunnerUnavailable(f"dask.address {address!r} is not host:port ({exc})") from None
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            pass
    except OSError as exc:
        raise RunnerUnavailable(
            f"dask.address {address}: no Dask scheduler answers there "
            f"({exc.strerror or exc}); start it, or leave out --address to run on this machine"
        ) from None


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
        check_prefect_api(os.environ["PREFECT_API_URL"])
        yield os.environ["PREFECT_API_URL"]
        return
    home = tempfile.mkdtemp(prefix="mobileocc-prefect-")
    os.environ.setdefault("PREFECT_HOME", home)
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    from prefect.server.api.server import SubprocessASGIServer
    from prefect.settings import PREFECT_API_URL, temporary_settings

    server = SubprocessASGIServer()
    try:
        with _server_dies_with_this_process():
            server.start(timeout=SERVER_START_TIMEOUT_S)
    except RuntimeError as exc:  # Prefect's own message carries the server's output
        server.stop()
        raise RunnerUnavailable(
            f"the temporary Prefect server did not start within {SERVER_START_TIMEOUT_S} s "
            f"({str(exc).splitlines()[0][:200]}); on a busy machine, start one "
            "(`prefect server start`) and set PREFECT_API_URL to it"
        ) from None
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
