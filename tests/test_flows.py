"""Small flows under Prefect's test harness: thread and Dask process runners, the stage cache,
failure isolation and the run lock."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from configs.schema import load_config
from flows.pipeline import rebuild_dataset
from flows.plan import STAGES
from storage.manifest import Manifest, StoreLockedError, run_lock
from storage.tables import read_table

pytestmark = [pytest.mark.usefixtures("prefect_harness"), pytest.mark.xdist_group("prefect")]


def _config(data: Path, out: Path, **overrides):
    # few fit iterations: these tests are about orchestration, not fit quality
    return load_config(overrides={"dataset.root": str(data), "output.root": str(out),
                                  "fit.iterations": 5, **overrides})


def _run(cfg, **kw):
    return rebuild_dataset(cfg, progress=False, **kw)


def _ran(report) -> set[tuple[str, str]]:
    return {k for k, o in report.outcomes.items() if o["status"] in ("done", "failed")}


@pytest.fixture()
def dataset(copy_dataset):
    return copy_dataset()


def test_thread_runner_and_cache_consequences(dataset, tmp_path):
    out = tmp_path / "out"
    cfg = _config(dataset, out)
    first = _run(cfg)
    assert _ran(first) == {(s, st) for s in ("0", "1") for st in STAGES}
    assert all(o["status"] == "done" for o in first.outcomes.values())
    # every stage says plainly whether it computes its product yet
    assert all("implemented" in o["summary"] for o in first.outcomes.values())
    # the published instances carry the fitted bodies (regression: the export left the 3D boxes
    # empty, so the nuScenes export had no pedestrian annotations)
    inst = read_table(out, "instances").to_pandas().dropna(subset=["box3d_center"])
    assert len(inst) > 0 and all(1.0 < size[2] < 2.2 for size in inst["box3d_size"])

    # nothing changed -> nothing recomputed
    assert _ran(_run(cfg)) == set()

    # one sequence's files edited -> only that sequence runs
    bin_path = dataset / "3d_raw/os1/1/3d_raw_os1_1_2.bin"
    raw = bytearray(bin_path.read_bytes())
    raw[-8:-4] = bytes([0, 0, 192, 63])  # one intensity value becomes 1.5
    bin_path.write_bytes(bytes(raw))
    assert _ran(_run(cfg)) == {("1", st) for st in STAGES}

    # a fuse-only setting changed -> only fuse and export run
    finer = _config(dataset, out, **{"fuse.grid.voxel_size_m": 0.1})
    assert _ran(_run(finer)) == {(s, st) for s in ("0", "1") for st in ("fuse", "export")}

    # a stage's output deleted -> that stage and what depends on it run again
    manifest = Manifest.load(out)
    shutil.rmtree(out / manifest.get("0", "map").location)
    assert _ran(_run(finer)) == {("0", "map"), ("0", "fuse"), ("0", "export")}

    # a sequence added -> only it runs
    for sub in ("3d_raw/os1", "2d_rect/cam0", "2d_rect/cam1", "3d_bbox/os1", "calibrations", "gt"):
        src = dataset / sub / "1"
        dst = dataset / sub / "2"
        shutil.copytree(src, dst)
        for f in sorted(dst.rglob("*_1_*")):
            f.rename(f.with_name(f.name.replace("_1_", "_2_")))
    for sub, ext in (("timestamps", "txt"), ("poses/dense_global", "txt"), ("metadata", "json")):
        shutil.copy(dataset / sub / f"1.{ext}", dataset / sub / f"2.{ext}")
    assert _ran(_run(finer)) == {("2", st) for st in STAGES}


def test_bad_sequence_fails_alone(dataset, tmp_path):
    out = tmp_path / "out"
    path = dataset / "3d_raw/os1/0/3d_raw_os1_0_2.bin"
    path.write_bytes(path.read_bytes()[:1000])
    report = _run(_config(dataset, out))
    failed = report.failed
    assert [(o["sequence"], o["stage"]) for o in failed] == [("0", "detect")]
    assert "3d_raw_os1_0_2.bin (frame 2)" in failed[0]["error"] and "truncated" in failed[0]["error"]
    assert all(report.outcomes[("1", st)]["status"] == "done" for st in STAGES)
    assert report.outcomes[("0", "fuse")]["status"] == "skipped"
    manifest = Manifest.load(out)
    assert manifest.get("0", "detect").status == "failed"
    assert "truncated" in manifest.get("0", "detect").error
    assert manifest.get("1", "export").status == "done"


def test_unknown_sequence_is_recorded(dataset, tmp_path):
    cfg = _config(dataset, tmp_path / "out", **{"dataset.sequences": ["1", "9"]})
    report = _run(cfg)
    assert report.outcomes[("9", "detect")]["status"] == "failed"
    assert "unknown sequence id '9'" in report.outcomes[("9", "detect")]["error"]
    assert report.outcomes[("1", "export")]["status"] == "done"


def test_second_run_on_same_store_is_refused(dataset, tmp_path):
    out = tmp_path / "out"
    with run_lock(out):
        with pytest.raises(StoreLockedError, match="is in use by another run"):
            _run(_config(dataset, out))


def test_dask_process_runner_matches_thread_runner(dataset, tmp_path):
    threads = _run(_config(dataset, tmp_path / "a"))
    dask = _run(_config(dataset, tmp_path / "b", **{"dask.runner": "dask", "dask.workers": 2}))
    assert {k: o["status"] for k, o in dask.outcomes.items()} == {
        k: o["status"] for k, o in threads.outcomes.items()}
    ma, mb = Manifest.load(tmp_path / "a"), Manifest.load(tmp_path / "b")
    assert {k: r.key for k, r in ma.rows.items()} == {k: r.key for k, r in mb.rows.items()}
    for (seq, stage), rec in ma.rows.items():
        a = (tmp_path / "a" / rec.location / "summary.json").read_text()
        b = (tmp_path / "b" / mb.get(seq, stage).location / "summary.json").read_text()
        assert json.loads(a) == json.loads(b)
