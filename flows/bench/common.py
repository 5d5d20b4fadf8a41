"""What the benchmarks share: the config of a bench run, the machine they ran on, and a fresh
process per measurement (so a peak RSS is the measurement's own)."""

from __future__ import annotations

import os
import platform
import resource
from pathlib import Path


def make_config(data_root: Path, out_root: Path, overrides: dict | None = None):
    """The simulator's oracle config (configs/oracle.yaml: the setting every stage-speed figure
    was measured in, perception of known quality on simulated data with gt/) pointed at
    ``data_root`` / ``out_root`` with dotted ``overrides``."""
    from configs.schema import ORACLE_CONFIG, load_config

    return load_config(
        ORACLE_CONFIG,
        overrides={
            "dataset.root": str(data_root),
            "output.root": str(out_root),
            **(overrides or {}),
        },
    )


def machine() -> dict:
    """CPU count and model, memory, load and library versions: the JSON's ``machine``."""
    import numpy as np

    model = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem_gb = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                mem_gb = round(int(line.split()[1]) / 1024**2, 1)
    except OSError:
        pass
    try:
        import torch

        torch_v, cuda = torch.__version__, torch.cuda.is_available()
        gpu = torch.cuda.get_device_name(0) if cuda else None
    except ImportError:  # pragma: no cover
        torch_v, cuda, gpu = None, False, None
    return {
        "cpu_count": os.cpu_count(),
        "cpu_affinity": len(os.sched_getaffinity(0)),
        "cpu_model": model,
        "memory_gb": mem_gb,
        "load_avg_1m": os.getloadavg()[0],
        "platform": platform.platform(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "torch": torch_v,
        "cuda": cuda,
        "gpu": gpu,
    }


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def spawned(fn, *args, **kwargs):
    """``fn(*args, **kwargs)`` in a fresh spawned process: its peak RSS is its own (not a daemon:
    it may start processes itself)."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(1, mp_context=mp.get_context("spawn")) as pool:
        return pool.submit(fn, *args, **kwargs).result()


def run_stages(config, stages: tuple[str, ...], submitter=None):
    """``stages`` of every sequence through the pipeline's runner in this process
    (flows.pipeline.units.run_units: a stage-level run, inline unless a ``submitter`` is given,
    recorded in OUT/manifest.json as a flow run records it). Returns its RunReport (``seconds``
    per unit in ``outcomes``); RuntimeError when a sequence or unit did not finish."""
    from flows.pipeline.units import run_units

    report = run_units(config, progress=False, submitter=submitter, stages=stages)
    bad = report.failed + report.skipped
    if bad:
        raise RuntimeError(
            "\n".join(f"sequence {o.sequence} stage {o.stage} {o.status}: {o.error}" for o in bad)
            + f"\n{bad[0].traceback}"
        )
    return report
