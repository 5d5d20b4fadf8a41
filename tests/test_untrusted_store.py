"""Nothing recorded in OUT is trusted to name a path; garbage there is rolled back (issue 41).

A publication intent, a completion record or a manifest row written by someone who can write OUT
(or damaged by a disk) must never make a run read or remove anything outside OUT, nor end in a
traceback; every name from a store is printed escaped (storage.layout.shown)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from storage import occupancy_store as occ
from storage import publish as pub
from storage.completion import check_files, check_record, write_record
from storage.layout import StoreError, recorded_path, shown
from storage.manifest import Manifest, StageRecord

GRID = (4, 3, 2)
ATTRS = {"range_min": [0.0] * 3, "range_max": [0.8, 0.6, 0.4], "voxel_size_m": 0.2,
         "config_hash": "c0"}  # fmt: skip


def _publish(root, seq="seq0", version="v1", value=3):
    staged = pub.stage_sequence(root, seq, version)
    occ.create_store(staged.store_path, 2, GRID, 2, ATTRS)
    occ.write_frames(staged.store_path, 0, {"semantics": np.full((2, *GRID), value, np.uint8)})
    pub.stage_table(staged, "sequences", [{"fingerprint": "f", "config_hash": "c",
                    "code_version": "1", "status": "ok", "num_frames": 2,
                    "occupancy_version": version}])  # fmt: skip
    pub.publish_sequence(staged)


def _intent(root, seq, body):
    path = root / ".publishing" / f"{seq}.json"
    path.parent.mkdir(exist_ok=True)
    path.write_bytes(body if isinstance(body, bytes) else json.dumps(body).encode())
    return path


@pytest.mark.parametrize(
    "text",
    ["a\nFAILED 0 sequence(s)", "a\x1b[31mred", "tab\there", "bad\udcffbyte", "x\u2028y"],
)
def test_a_name_is_printed_escaped(text):
    out = shown(text)
    assert out.isprintable() and "\n" not in out and "\x1b" not in out
    assert "\\" in out  # each hidden character shown as its escape
    assert shown("plain seq_1-é") == "plain seq_1-é"


@pytest.mark.parametrize(
    "rel, says",
    [("/etc", "absolute"), ("../x", "leaves the store"), ("a/../../b", "leaves the store"),
     ("", "not a path"), (None, "not a path"), ("a\nb", "control character")],
)  # fmt: skip
def test_a_recorded_path_outside_out_is_refused(rel, says, tmp_path):
    with pytest.raises(StoreError, match=says):
        recorded_path(tmp_path, rel, "an intent")


def test_a_recorded_path_through_a_symlink_is_refused(tmp_path):
    (tmp_path / "link").symlink_to(tmp_path.parent)
    with pytest.raises(StoreError, match="symbolic link"):
        recorded_path(tmp_path, "link/x", "an intent")


@pytest.mark.parametrize("staging", ["OUTSIDE", "../outside", ".tmp-x/../../outside"])
def test_a_crafted_intent_removes_nothing_outside_out(staging, tmp_path):
    out, outside = tmp_path / "out", tmp_path / "outside"
    (outside / "tables").mkdir(parents=True)
    (outside / "occupancy.zarr").mkdir()
    (outside / "precious.txt").write_text("keep me")
    _publish(out)
    before = pub.check_publication(out, "seq0", "v1", deep=True)
    assert before == ""
    staging = str(outside) if staging == "OUTSIDE" else staging
    _intent(out, "seq0", {"action": "publish", "staging": staging, "version": "v2",
                          "current": {"version": "v2", "files": {}}})  # fmt: skip
    assert "not a publication intent" in pub.intent_problem(out, "seq0")
    assert "rolls it back" in pub.check_publication(out, "seq0", "v1")
    lines: list[str] = []
    assert pub.recover_publications(out, lines) == []
    assert (outside / "precious.txt").read_text() == "keep me"
    assert (outside / "occupancy.zarr").is_dir()
    assert len(lines) == 1 and "rolled back" in lines[0] and "kept" in lines[0], lines
    assert not pub.pending_publications(out)
    assert pub.check_publication(out, "seq0", "v1", deep=True) == ""


@pytest.mark.parametrize(
    "garbage",
    [b"\x00\xff garbage", b"[1, 2]", b"{}", b'{"action": "publish"}',
     b'{"action": "withdraw", "row": 3}', b'{"action": "explode"}',
     b'{"action": "publish", "staging": ".tmp-x", "version": "v2", "current": {"version": "v2",'
     b' "files": {"/etc/passwd": [1, "0"]}}}'],
)  # fmt: skip
def test_a_garbage_intent_is_rolled_back_with_one_line(garbage, tmp_path):
    _publish(tmp_path)
    path = _intent(tmp_path, "seq0", garbage)
    problem = pub.check_publication(tmp_path, "seq0", "v1")
    assert str(path) in problem and "rolls it back" in problem
    lines: list[str] = []
    with pub.reading(tmp_path):  # readers complete / roll back pending intents first
        pass
    assert not path.exists()
    assert pub.check_publication(tmp_path, "seq0", "v1", deep=True) == ""
    _intent(tmp_path, "seq0", garbage)
    pub.recover_publications(tmp_path, lines)
    assert len(lines) == 1 and "\n" not in lines[0] and str(path) in lines[0]


def test_a_garbage_intent_over_a_half_publication_takes_the_sequence_out(tmp_path):
    _publish(tmp_path)
    part = next((tmp_path / "tables").rglob("*.parquet"))
    part.write_bytes(part.read_bytes()[:-3])  # a half-done publication left other tables
    _intent(tmp_path, "seq0", b"{")
    lines: list[str] = []
    pub.recover_publications(tmp_path, lines)
    assert "taken out" in lines[0]
    assert "seq0" not in pub.published_versions(tmp_path)


def test_a_completion_record_naming_a_path_outside_is_not_read(tmp_path):
    folder = tmp_path / "unit"
    folder.mkdir()
    (folder / "a.bin").write_bytes(b"abc")
    write_record(folder)
    assert check_record(folder, deep=True) == ""
    body = json.loads((folder / "complete.json").read_bytes())
    body["files"]["../../../../dev/zero"] = [0, "0"]  # a deep check would hash forever
    (folder / "complete.json").write_text(json.dumps(body))
    assert "leaves the store" in check_record(folder, deep=True)
    assert "absolute" in check_files(folder, {"/dev/zero": [0, "0"]}, deep=True)


@pytest.mark.parametrize(
    "location", ["/tmp", "stages/fit/../../../x", "stages/fit/other/k", "stages/../../etc/k"]
)
def test_a_manifest_row_naming_another_folder_names_none(location, tmp_path):
    m = Manifest(tmp_path)
    m.put(StageRecord("seq0", "fit", "k", "done", location=location))
    rec = m.get("seq0", "fit")
    assert rec.location == "" and rec.status == "failed" and "refused" in rec.error
    m.put(StageRecord("seq0", "fit", "k", "done", location="stages/fit/seq0/k"))
    assert m.get("seq0", "fit").location == "stages/fit/seq0/k"


def test_the_run_summary_prints_names_escaped(tmp_path):
    from flows.pipeline.units import RunReport, summary_table

    report = RunReport(tmp_path, [], recovered=["evil\nFAILED forged\x1b[2J"])
    text = summary_table(report)
    assert "\x1b" not in text and "FAILED forged" in text
    assert not any(line.startswith("FAILED forged") for line in text.splitlines())


def test_a_read_only_store_is_read_without_a_lock_and_refuses_recovery(tmp_path, monkeypatch):
    from tests.read_only import read_only_store

    out = tmp_path / "out"
    _publish(out)
    (out / ".lock").unlink(missing_ok=True)
    with read_only_store(out, monkeypatch) as (ro, how):
        with pub.reading(ro):  # no lock file can be made: none is needed, no run can write
            assert pub.published_versions(ro) == {"seq0": "v1"}, how
        assert not (ro / ".lock").exists()
    _intent(out, "seq0", {"action": "remove"})
    with read_only_store(out, monkeypatch) as (ro, how):
        with pytest.raises(StoreError, match="read-only, so it cannot be completed here"):
            with pub.reading(ro):
                pass


@pytest.mark.skipif(not Path("/proc/locks").exists(), reason="Linux /proc/locks")
@pytest.mark.parametrize("kind", ["LOCK_SH", "LOCK_EX"])
def test_a_lock_held_by_a_foreign_process_names_it(kind, tmp_path):
    """Regression (issue 41): a store locked by a live process that is not a run (it writes no
    host / pid into the lock file) was "being read (e.g. by export)"; the kernel names it."""
    import subprocess
    import sys

    from storage.manifest import StoreLockedError, run_lock

    lock = tmp_path / ".lock"
    lock.touch()
    code = (
        "import fcntl, sys, time; f = open(sys.argv[1], 'rb'); "
        f"fcntl.flock(f, fcntl.{kind}); print('held', flush=True); time.sleep(60)"
    )
    proc = subprocess.Popen([sys.executable, "-c", code, str(lock)], stdout=subprocess.PIPE)
    try:
        assert proc.stdout.readline().strip() == b"held"
        with pytest.raises(StoreLockedError) as err, run_lock(tmp_path):
            pass
        text = str(err.value)
        assert (
            f"pid {proc.pid}" in text and ("exclusive" if kind == "LOCK_EX" else "shared") in text
        )
        assert ("being read" in text) == (kind == "LOCK_SH"), text
    finally:
        proc.kill()
        proc.wait()
