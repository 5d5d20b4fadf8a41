"""Thread pools of the occupancy kernels, one per requested size.

Kernels that split work over threads (numba functions compiled ``nogil``) take an explicit thread
count, so a caller that owns a share of the machine (a Dask worker with its allotment) passes it;
``None`` means one thread per core (``os.cpu_count()``). Results never depend on the count.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from threading import Lock

_POOLS: dict[int, ThreadPoolExecutor] = {}
_LOCK = Lock()


def resolve_threads(threads: int | None) -> int:
    """The thread count a kernel uses: ``threads`` (>= 1), or one per core for None."""
    if threads is None:
        return max(1, os.cpu_count() or 1)
    if int(threads) < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    return int(threads)


def executor(threads: int) -> ThreadPoolExecutor:
    """A pool of exactly ``threads`` workers, created once per size and reused."""
    with _LOCK:
        pool = _POOLS.get(threads)
        if pool is None:
            pool = _POOLS[threads] = ThreadPoolExecutor(
                max_workers=threads, thread_name_prefix=f"occupancy{threads}"
            )
        return pool
