"""Per-frame fan-out from inside a stage: straight to Dask when the stage runs on a Dask worker.

Prefect tasks cost ~70 ms each on the Dask runner, raw ``client.submit`` under 1 ms
(measured with prefect 3.8 / distributed 2026.8), so a stage is one Prefect task and its frame chunks go to
Dask directly. ``worker_client`` secedes the calling worker thread while it waits, which avoids
the deadlock of a task blocking its own worker's thread pool.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any


def _on_dask_worker() -> bool:
    try:
        from distributed import get_worker
    except ImportError:  # pragma: no cover - distributed is a dependency
        return False
    try:
        get_worker()
    except ValueError:
        return False
    return True


def limit_threads(threads: int) -> None:
    """Size this process's kernel thread pools for a unit that owns ``threads`` cores: BLAS /
    OpenMP pools to ``threads``; torch to one thread always (its results depend on its thread count,
    so outputs stay byte-identical whatever the workers' allotment; the parallelism comes from the
    workers). The occupancy kernels take their count as an argument (Runtime.threads).

    Order matters: torch's intra-op pool is the OpenMP runtime it ships (libgomp), which
    threadpoolctl's OpenMP limit sets too, so torch is sized after it (the other way round a unit
    of 2 threads ran torch on 2: the fit stage at a fifth of its one-thread rate under load,
    docs/fit-benchmark.md)."""
    import torch
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=threads)
    if torch.get_num_threads() != 1:
        torch.set_num_threads(1)


def _limited(fn: Callable[..., Any], threads: int, *args: Any) -> Any:
    limit_threads(threads)
    return fn(*args)


def fan_out(
    fn: Callable[..., Any], args: Sequence[tuple], resources: dict | None = None, threads: int = 1
) -> list:
    """Call ``fn(*a)`` for every ``a`` in ``args``; results in the order of ``args``.

    On a Dask worker the calls are submitted to the cluster (each sized to ``threads`` threads:
    :func:`limit_threads`); elsewhere they run here, in order.
    """
    if len(args) > 1 and _on_dask_worker():
        from distributed import worker_client

        with worker_client() as client:
            futures = [
                client.submit(_limited, fn, threads, *a, pure=False, resources=resources)
                for a in args
            ]
            return client.gather(futures)
    return [fn(*a) for a in args]
