"""Planning from the fingerprint memo: an unchanged dataset is planned without opening a file, a
changed file is the only one hashed again, ``--verify`` sees what size + mtime + inode cannot."""

from __future__ import annotations

import builtins
import json
import os
from pathlib import Path

import pytest

from configs.schema import ORACLE_CONFIG, load_config
from flows.pipeline.plan import PlanCosts, plan_run, plan_without_hashing
from storage.completion import write_record
from storage.manifest import (
    FingerprintCache,
    Manifest,
    StageRecord,
    atomic_write_bytes,
    stage_dir,
)
from tests.coda_fixture import make_coda


@pytest.fixture()
def store(tmp_path):
    data = tmp_path / "data"
    for seq in (0, 1):
        make_coda(data, seq=seq, frames=4)
    out = tmp_path / "out"
    out.mkdir()
    return (
        data,
        out,
        load_config(ORACLE_CONFIG, overrides={"dataset.root": str(data), "output.root": str(out)}),
    )


def _plan(config, out: Path, verify: bool = False):
    costs = PlanCosts()
    manifest = Manifest.load(out)
    plans = plan_run(
        config, manifest, FingerprintCache(out / ".cache" / "sequences", verify), costs=costs
    )
    return plans, costs, manifest


def _all_done(plans, out: Path) -> None:
    """Record every unit as done, as a finished run leaves the store."""
    manifest = Manifest.load(out)
    for plan in plans:
        for stage, unit in plan.units.items():
            folder = stage_dir(out, stage, plan.sequence, unit.key)
            folder.mkdir(parents=True)
            write_record(folder, stage=stage, sequence=plan.sequence, key=unit.key)
            if stage == "export":  # published, with nothing in it
                atomic_write_bytes(
                    out / "occupancy" / plan.sequence / "current.json",
                    json.dumps({"version": unit.key, "files": {}}).encode(),
                )
            manifest.put(
                StageRecord(
                    plan.sequence,
                    stage,
                    unit.key,
                    "done",
                    str(folder.relative_to(out)),
                    parts=unit.parts,
                )
            )
    manifest.save()


def _stale(plans) -> dict[tuple[str, str], str]:
    return {(p.sequence, s): u.reason for p in plans for s, u in p.units.items() if not u.fresh}


def _opened_under(root: Path, monkeypatch) -> list[str]:
    """Record every file under ``root`` opened from now on (builtins.open and os.open)."""
    opened, prefix = [], os.path.abspath(root) + os.sep
    real_open, real_os_open = builtins.open, os.open

    def note(path) -> None:
        if isinstance(path, (str, os.PathLike)) and os.path.abspath(path).startswith(prefix):
            opened.append(os.fspath(path))

    monkeypatch.setattr(
        builtins, "open", lambda file, *a, **k: (note(file), real_open(file, *a, **k))[1]
    )
    monkeypatch.setattr(
        os, "open", lambda path, *a, **k: (note(path), real_os_open(path, *a, **k))[1]
    )
    return opened


def test_an_unchanged_dataset_is_planned_without_opening_a_file(store, monkeypatch):
    data, out, config = store
    plans, costs, _ = _plan(config, out)
    assert costs.memo_hits == 0 and costs.files_hashed > 0 and not any(p.error for p in plans)
    _all_done(plans, out)
    opened = _opened_under(data, monkeypatch)
    again, costs, _ = _plan(config, out)
    assert opened == [] and costs.memo_hits == 2 and costs.files_hashed == 0
    assert _stale(again) == {}
    assert [p.fingerprint for p in again] == [p.fingerprint for p in plans]
    # with nothing to hash, the command line plans without a task runner
    assert (
        plan_without_hashing(
            config, Manifest.load(out), FingerprintCache(out / ".cache" / "sequences")
        )
        is not None
    )


def test_a_changed_file_is_the_only_one_hashed_again(store):
    data, out, config = store
    plans, _, _ = _plan(config, out)
    _all_done(plans, out)
    sweep = data / "3d_comp/os1/1/3d_comp_os1_1_2.bin"
    raw = bytearray(sweep.read_bytes())
    raw[-8:-4] = bytes([0, 0, 192, 63])
    sweep.unlink()
    sweep.write_bytes(bytes(raw))  # a new file: new inode and mtime
    assert (
        plan_without_hashing(
            config, Manifest.load(out), FingerprintCache(out / ".cache" / "sequences")
        )
        is None
    )
    again, costs, _ = _plan(config, out)
    assert costs.memo_hits == 1 and costs.files_hashed == 1
    assert _stale(again)[("1", "detect")] == "input files changed" and (
        "0",
        "detect",
    ) not in _stale(again)


def test_verify_sees_an_edit_that_keeps_size_mtime_and_inode(store):
    """The documented trade-off: the default trusts (size, mtime, inode); --verify reads."""
    data, out, config = store
    plans, _, _ = _plan(config, out)
    _all_done(plans, out)
    sweep = data / "3d_comp/os1/1/3d_comp_os1_1_2.bin"
    st = os.stat(sweep)
    with open(sweep, "r+b") as fh:  # in place: same inode, same size
        fh.seek(st.st_size - 8)
        fh.write(bytes([0, 0, 192, 63]))
    os.utime(sweep, ns=(st.st_atime_ns, st.st_mtime_ns))  # and the old mtime
    assert _stale(_plan(config, out)[0]) == {}
    verified, costs, _ = _plan(config, out, verify=True)
    assert _stale(verified)[("1", "detect")] == "input files changed" and (
        "0",
        "detect",
    ) not in _stale(verified)
    assert costs.memo_hits == 0 and costs.files_hashed > 0


def test_the_config_and_the_planner_import_no_torch():
    """status / dry-run / a no-op rebuild start in about a second: torch (~1 s to import) is only
    imported where a unit runs (the fit weights live in torch-free tasks/fit/weights.py)."""
    import subprocess
    import sys

    code = (
        "import sys, configs.schema, flows.pipeline.plan, flows.pipeline.units\n"
        "print(sorted(m for m in ('torch', 'prefect', 'flows.stages') if m in sys.modules))"
    )
    run = subprocess.run(
        [sys.executable, "-c", code],
        cwd=Path(__file__).resolve().parents[1],
        capture_output=True,
        text=True,
        check=True,
    )
    assert run.stdout.strip() == "[]"
