"""Units without Prefect (flows/pipeline/local.py): the same outcomes and bytes as the Prefect
flows, on the thread pool and on a Dask cluster; a unit starts only after its upstream."""

from __future__ import annotations

import hashlib
import threading
import time
from concurrent.futures import Future
from pathlib import Path
from types import SimpleNamespace

import pytest

from configs.schema import load_config
from flows.pipeline import local
from flows.pipeline.local import ThreadSubmitter, run_without_prefect, uses_prefect


def _config(data: Path, out: Path, **overrides):
    return load_config(
        overrides={
            "dataset.root": str(data),
            "output.root": str(out),
            "fit.iterations": 5,
            **overrides,
        }
    )


def _published_bytes(out: Path) -> dict[str, str]:
    """sha256 of every file of the dataset (tables, published sequences, exports), by path."""
    skip = (".cache", "stages", "manifest", ".lock", "journal")
    return {
        str(p.relative_to(out)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(out.rglob("*"))
        if p.is_file()
        and not any(part.startswith(skip) for part in p.relative_to(out).parts)
        and p.suffix != ".json"  # run-specific records (times, paths) aside
    }


def test_prefect_only_where_an_api_is_configured(monkeypatch, tmp_path):
    monkeypatch.delenv("PREFECT_API_URL", raising=False)
    cfg = _config(tmp_path, tmp_path / "out")
    assert not uses_prefect(cfg)
    assert uses_prefect(_config(tmp_path, tmp_path / "out", **{"dask.prefect": "always"}))
    monkeypatch.setenv("PREFECT_API_URL", "http://127.0.0.1:1/api")
    assert uses_prefect(cfg)
    assert not uses_prefect(_config(tmp_path, tmp_path / "out", **{"dask.prefect": "never"}))


@pytest.mark.xdist_group("prefect")
def test_thread_and_dask_without_prefect_match_the_prefect_flow(
    copy_dataset, tmp_path, prefect_harness
):
    from flows.pipeline.run import rebuild_dataset

    data = copy_dataset()
    with_prefect = rebuild_dataset(_config(data, tmp_path / "prefect"), progress=False)
    threads = run_without_prefect(_config(data, tmp_path / "threads"), progress=False)
    dask = run_without_prefect(
        _config(data, tmp_path / "dask", **{"dask.runner": "dask", "dask.workers": 2}),
        progress=False,
    )
    statuses = {k: o.status for k, o in with_prefect.outcomes.items()}
    assert statuses and all(s.value == "done" for s in statuses.values())
    assert {k: o.status for k, o in threads.outcomes.items()} == statuses
    assert {k: o.status for k, o in dask.outcomes.items()} == statuses
    reference = _published_bytes(tmp_path / "prefect")
    assert any(name.endswith(".parquet") for name in reference)
    assert _published_bytes(tmp_path / "threads") == reference
    assert _published_bytes(tmp_path / "dask") == reference


def test_a_unit_starts_after_its_upstream_even_on_one_thread(monkeypatch):
    """Downstream units submitted before their upstream finished wait without holding the only
    thread (a pool thread blocked on a queued upstream would deadlock)."""
    order: list[str] = []
    gate = threading.Event()

    def fake_execute(unit, out_root, upstream, *rest):
        if unit.stage == "detect":
            gate.wait(5)
        assert all(not isinstance(o, Future) for o in upstream.values())
        order.append(f"{unit.stage}<-{','.join(sorted(upstream))}")
        return SimpleNamespace(stage=unit.stage, sequence=unit.sequence)

    monkeypatch.setattr(local, "execute_unit", fake_execute)
    sub = ThreadSubmitter(workers=1)

    def unit(stage):
        return SimpleNamespace(stage=stage, sequence="0")

    detect = sub.submit("detect", unit("detect"), "out", {})
    track = sub.submit("track", unit("track"), "out", {"detect": detect})
    fit = sub.submit("fit", unit("fit"), "out", {"detect": detect, "track": track})
    time.sleep(0.05)
    assert order == []  # detect holds the one thread; track and fit wait off the pool
    gate.set()
    done = [o.stage for o in sub.completed([detect, track, fit])]
    assert sorted(done) == ["detect", "fit", "track"]
    assert order == ["detect<-", "track<-detect", "fit<-detect,track"]
