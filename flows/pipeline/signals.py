"""SIGINT (Ctrl-C) and SIGTERM stop a command within a second: one line, exit 130 / 143.

Stages run in pool threads (Prefect's thread runner) or in Dask worker processes, while signals
arrive in the main thread. Prefect turns SIGTERM into an exception of the main thread and Python
turns SIGINT into ``KeyboardInterrupt`` there, but neither stops a stage already computing in a
pool thread (a thread cannot be interrupted, and interpreter exit waits for the pool's threads),
so the run went on computing and holding the store's lock for minutes, and a Ctrl-C in a short
command printed a 60-line traceback.

So while a command runs, :func:`stop_on_signals` handles both signals itself: it prints one line
to stderr, ends this process's child processes (Dask workers of a local cluster, the temporary
Prefect server), and leaves with ``os._exit(128 + signal)``. Nothing else is needed for the store:
it is built to survive a SIGKILL at any point (key-named unit outputs published by rename,
completion records written last, the journal fsynced per unit, publications rolled forward from
their intent record), the kernel releases the run lock with the process, and the next run sweeps
the temporaries and resumes, recomputing only the units that were in flight.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Iterator

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)

#: the handler of the innermost :func:`stop_on_signals` block of this process (None outside)
_active: list = []


def _end_children(grace_s: float = 2.0) -> None:
    """Terminate this process's descendants, then kill those still there after ``grace_s``."""
    try:  # a dependency of distributed; without it children get only SIGHUP / PDEATHSIG
        import psutil
    except ImportError:
        return
    try:
        kids = psutil.Process().children(recursive=True)
    except psutil.Error:
        return
    for kid in kids:
        with contextlib.suppress(psutil.Error):
            kid.terminate()
    _, alive = psutil.wait_procs(kids, timeout=grace_s)
    for kid in alive:
        with contextlib.suppress(psutil.Error):
            kid.kill()


@contextlib.contextmanager
def stop_on_signals(what: str, after: str = "") -> Iterator[None]:
    """While the block runs, SIGINT / SIGTERM print ``<what>: stopped by SIGTERM<after>`` and
    exit 130 / 143 at once (see the module docstring). Installed only in the main thread (signal
    handlers can live nowhere else); the previous handlers come back when the block ends."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum: int, frame: object) -> None:  # noqa: ARG001 - the handler's signature
        for s in STOP_SIGNALS:  # a second Ctrl-C while children are ended changes nothing
            signal.signal(s, signal.SIG_IGN)
        name = signal.Signals(signum).name
        try:
            sys.stderr.write(f"\n{what}: stopped by {name}{after}\n")
            sys.stderr.flush()
        except (OSError, ValueError):  # stderr closed: the exit code still says it
            pass
        _end_children()
        os._exit(128 + signum)

    previous = {s: signal.signal(s, stop) for s in STOP_SIGNALS}
    _active.append(stop)
    try:
        yield
    finally:
        _active.pop()
        for s, handler in previous.items():
            signal.signal(s, handler)


@contextlib.contextmanager
def keep_stop_handlers() -> Iterator[None]:
    """Inside a Prefect flow body: put back the handlers of the enclosing :func:`stop_on_signals`.

    A Prefect flow run installs its own SIGTERM handler, which raises an exception in the main
    thread; the engine then waits for the task runner's threads, i.e. for the stages in flight,
    before the process ends (minutes). Nothing is changed outside a ``stop_on_signals`` block or
    outside the main thread."""
    if not _active or threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.signal(s, _active[-1]) for s in STOP_SIGNALS}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
