"""The output store's lock and manifest: many processes racing for the lock never share it, a lock
left by a killed process is no lock, the manifest's journal survives a kill and compacts."""

from __future__ import annotations

import multiprocessing as mp
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from storage.manifest import (
    JOURNAL,
    MANIFEST,
    Manifest,
    StageRecord,
    StoreLockedError,
    run_lock,
)

ROOT = Path(__file__).resolve().parents[1]


def _contend(out: str, ready, queue, times: int = 30) -> None:
    """Take the lock ``times`` times (retrying at once when refused), each time checking that
    nobody else is inside; report (pid, refusals, overlaps). All start together when every
    process has reached the barrier ``ready`` (a start time on the clock let processes forked
    late on a loaded machine run one after the other, and never race)."""
    random.seed(os.getpid())
    ready.wait(timeout=120)
    refused, overlaps, got, deadline = 0, 0, 0, time.time() + 120
    while got < times and time.time() < deadline:
        try:
            with run_lock(Path(out)):
                try:
                    fd = os.open(os.path.join(out, "inside"), os.O_CREAT | os.O_EXCL | os.O_WRONLY)
                except FileExistsError:
                    overlaps += 1
                    fd = None
                if random.random() < 0.5:
                    time.sleep(0.0005)
                if fd is not None:
                    os.close(fd)
                    os.unlink(os.path.join(out, "inside"))
            got += 1
        except StoreLockedError:
            refused += 1
    queue.put((os.getpid(), refused, overlaps if got == times else -1))


@pytest.mark.parametrize("left_behind", ["dead pid", "empty"])
def test_racing_processes_never_hold_the_lock_together(left_behind, tmp_path):
    """Regression: with a lock left by a dead process, 4 runs started at once let two of them hold
    it together in 35 of 100 trials (the stale-lock takeover raced)."""
    ctx = mp.get_context("fork")
    for trial in range(1):
        out = tmp_path / f"out{trial}"
        out.mkdir()
        if left_behind != "none":
            (out / ".lock").write_text(
                '{"host": "x", "pid": 999999999}' if left_behind == "dead pid" else ""
            )
        queue, ready = ctx.Queue(), ctx.Barrier(12)
        procs = [ctx.Process(target=_contend, args=(str(out), ready, queue)) for _ in range(12)]
        for p in procs:
            p.start()
        results = [queue.get(timeout=180) for _ in procs]
        for p in procs:
            p.join(timeout=60)
        assert all(overlaps == 0 for _, _, overlaps in results), (
            results
        )  # -1: did not get it 30 times
        assert sum(refused for _, refused, _ in results) > 0  # they did race
        assert not (out / ".lock").exists() and not (out / "inside").exists()


def test_a_killed_holder_leaves_no_lock(tmp_path):
    code = (
        "import sys\nfrom storage.manifest import run_lock\n"
        "with run_lock(sys.argv[1]):\n    print('in', flush=True)\n    sys.stdin.read()\n"
    )
    holder = subprocess.Popen(
        [sys.executable, "-c", code, str(tmp_path)],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert holder.stdout.readline().strip() == "in"
    with (
        pytest.raises(StoreLockedError, match=f"in use by another run .*pid {holder.pid}"),
        run_lock(tmp_path),
    ):
        pass
    os.kill(holder.pid, signal.SIGKILL)
    holder.wait()
    assert (tmp_path / ".lock").exists()  # the file stays, the kernel's lock went with the process
    with run_lock(tmp_path):
        assert (tmp_path / ".lock").read_text().startswith('{"host"')


def test_readers_behind_a_killed_runs_lock_file_are_named_as_readers(tmp_path):
    """A run killed leaves its host and pid in the lock file; readers then hold the file (they
    write nothing), and a run refused must say it is being read, not name the dead run."""
    import socket

    from storage.manifest import read_lock

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)  # fmt: skip
    (tmp_path / ".lock").write_text(
        f'{{"host": "{socket.gethostname()}", "pid": {int(dead.stdout)}, "started": 0}}'
    )
    code = (
        "import sys\nfrom storage.manifest import read_lock\n"
        "with read_lock(sys.argv[1]):\n    print('in', flush=True)\n    sys.stdin.read()\n"
    )
    reader = subprocess.Popen(
        [sys.executable, "-c", code, str(tmp_path)],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    try:
        assert reader.stdout.readline().strip() == "in"
        with pytest.raises(StoreLockedError, match="is being read"), run_lock(tmp_path):
            pass
        with read_lock(tmp_path):  # readers share it
            pass
    finally:
        reader.communicate("", timeout=60)
    with run_lock(tmp_path):  # released with the reader
        pass


def _row(seq: str, stage: str, status: str = "done") -> StageRecord:
    return StageRecord(
        seq,
        stage,
        key=f"k-{seq}-{stage}",
        status=status,
        location=f"stages/{stage}/{seq}/k",
        summary={"frames": [0, 2]},
        parts={"code": "1"},
    )


def test_the_journal_survives_a_kill_and_compacts(tmp_path):
    m = Manifest(tmp_path)
    m.meta["config_hash"] = "abc"
    m.record(_row("0", "detect"))
    m.save()
    m.record(_row("0", "track"))
    m.record(_row("1", "detect", "failed"))
    with open(tmp_path / JOURNAL, "ab") as fh:  # a line cut by the kill
        fh.write(b'{"sequence": "1", "stage": "tr')
    loaded = Manifest.load(tmp_path)
    assert sorted(loaded.rows) == [("0", "detect"), ("0", "track"), ("1", "detect")]
    assert loaded.get("1", "detect").status == "failed" and loaded.meta == {"config_hash": "abc"}
    loaded.save()
    assert not (tmp_path / JOURNAL).exists() and (tmp_path / MANIFEST).exists()
    assert sorted(Manifest.load(tmp_path).rows) == sorted(loaded.rows)


def test_a_failed_journal_write_names_the_file(tmp_path):
    m = Manifest(tmp_path)
    (tmp_path / JOURNAL).mkdir()  # cannot be opened for appending
    with pytest.raises(OSError, match="manifest.journal"):
        m.record(_row("0", "detect"))
    assert m.get("0", "detect") is not None  # kept for the final save
