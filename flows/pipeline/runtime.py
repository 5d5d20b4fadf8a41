"""Where flows run: the Prefect API they report to and the task runner (threads or Dask).

Without ``PREFECT_API_URL`` Prefect starts a temporary server per process, and Dask worker
processes would each start their own (measured with prefect 3.8). So when no API is
configured we start one temporary server here and export its address, which the Dask worker
processes inherit. The server is a child process; a small watchdog process ends it when this
process ends in any way (a SIGKILL included), so no server outlives its CLI.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import tempfile
from typing import Iterator

#: the watchdog: wait until the parent (the CLI) is gone, then end the server (SIGTERM, then SIGKILL)
_WATCHDOG = """
import os, signal, sys, time
parent, server = int(sys.argv[1]), int(sys.argv[2])
def alive(pid):
    try:
        os.kill(pid, 0)
        return True
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
def start_time(pid):
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[19]
    except OSError:
        return None
mark = start_time(server)
while os.getppid() == parent and alive(parent) and alive(server):
    time.sleep(0.5)
if alive(server) and start_time(server) == mark:  # the same process, not a reused pid
    os.kill(server, signal.SIGTERM)
    for _ in range(50):
        time.sleep(0.1)
        if not alive(server):
            break
    else:
        os.kill(server, signal.SIGKILL)
"""


def _watch(server_pid: int) -> subprocess.Popen:
    """Start the watchdog of the server ``server_pid`` (ends it when this process is gone)."""
    return subprocess.Popen([sys.executable, "-c", _WATCHDOG, str(os.getpid()), str(server_pid)],
                            stdin=subprocess.DEVNULL, start_new_session=True)

from configs.schema import Config


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
    server.start(timeout=120)
    watchdog = _watch(server.server_process.pid) if server.server_process is not None else None
    os.environ["PREFECT_API_URL"] = server.api_url
    try:
        with temporary_settings(updates={PREFECT_API_URL: server.api_url}):
            yield server.api_url
            _drain_prefect_workers()  # flush logs and events while the server still answers
    finally:
        os.environ.pop("PREFECT_API_URL", None)
        server.stop()
        if watchdog is not None:
            watchdog.terminate()
            watchdog.wait()


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
    return DaskTaskRunner(cluster_kwargs={
        "n_workers": d.workers, "threads_per_worker": d.threads_per_worker, "processes": True,
        "memory_limit": d.memory_limit, "dashboard_address": None,
    })
