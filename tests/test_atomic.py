"""One atomic write for the whole project (storage/atomic.py): what it writes, what it leaves
behind, concurrent writers of one target, folders published whole; and a walk over storage/ and
flows/ that finds every rename onto a published name and every npz / whole-file write outside it."""

from __future__ import annotations

import ast
import errno
import threading
import zipfile
from pathlib import Path

import numpy as np
import pytest

import storage.atomic as atomic
from storage.atomic import (
    atomic_write_bytes,
    atomic_write_text,
    staged_folder,
    swap_in,
    write_atomically,
)
from storage.layout import TMP_PREFIX
from storage.npzio import save_npz_deterministic

ROOT = Path(__file__).resolve().parents[1]
HELPER = "storage/atomic.py"

#: calls that put a whole file or folder in place by themselves (module, name) ...
RENAMES = {("os", "replace"), ("os", "rename"), ("shutil", "move")}
NPZ = {"savez", "savez_compressed"}
#: ... and methods that write a whole file in one go (Path.write_text / write_bytes / rename)
WRITE_METHODS = {"write_text", "write_bytes", "rename"}
#: direct opens for writing that are no output: (file, function) -> why
ALLOWED_OPENS = {
    ("storage/manifest.py", "check_writable"): "a probe file, removed at once",
    ("flows/bench/scale.py", "loopback_cluster"): "a worker's log, streamed while it runs",
}


def _write_mode(call: ast.Call) -> bool:
    mode = call.args[1] if len(call.args) > 1 else None
    mode = next((k.value for k in call.keywords if k.arg == "mode"), mode)
    return isinstance(mode, ast.Constant) and any(c in str(mode.value) for c in "wx")


def bypasses(path: Path, rel: str) -> list[str]:
    """``file:line what`` for each write in ``path`` that does not go through the helper."""
    tree = ast.parse(path.read_text(), filename=rel)
    found = []

    def visit(node: ast.AST, function: str) -> None:
        for child in ast.iter_child_nodes(node):
            name = child.name if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef) else None
            if isinstance(child, ast.Call):
                f = child.func
                what = None
                if isinstance(f, ast.Attribute):
                    owner = f.value.id if isinstance(f.value, ast.Name) else None
                    if (owner, f.attr) in RENAMES or f.attr in NPZ or f.attr in WRITE_METHODS:
                        what = f"{owner + '.' if owner else '.'}{f.attr}"
                    # Path.replace(target): one positional argument (str.replace takes two,
                    # dataclasses.replace keywords)
                    elif f.attr == "replace" and len(child.args) == 1 and not child.keywords:
                        what = ".replace"
                elif isinstance(f, ast.Name) and (
                    f.id in NPZ
                    or (
                        f.id == "open"
                        and _write_mode(child)
                        and (rel, function) not in ALLOWED_OPENS
                    )
                ):
                    what = f.id
                if what is not None:
                    found.append(f"{rel}:{child.lineno} {what}")
            visit(child, name or function)

    visit(tree, "")
    return found


def all_bypasses(root: Path = ROOT) -> list[str]:
    found = []
    for layer in ("storage", "flows"):
        for path in sorted((root / layer).rglob("*.py")):
            rel = str(path.relative_to(root))
            if rel != HELPER:
                found += bypasses(path, rel)
    return found


def test_every_writer_goes_through_the_helper():
    assert all_bypasses() == []


def test_the_walk_finds_each_kind_of_bypass(tmp_path):
    (tmp_path / "storage").mkdir()
    (tmp_path / "flows").mkdir()
    (tmp_path / "storage" / "bad.py").write_text(
        "import os, shutil\nimport numpy as np\nfrom pathlib import Path\n"
        "def f(p, q, t):\n"
        "    os.replace(p, q)\n"
        "    np.savez(p, x=1)\n"
        "    Path(p).write_text(t)\n"
        "    Path(p).replace(q)\n"
        "    open(p, 'wb')\n"
        "    open(p, mode='w')\n"
        "    open(p)\n"  # reading: fine
        "    t.replace('a', 'b')\n"  # str.replace: fine
    )
    (tmp_path / "flows" / "bad.py").write_text(
        "import shutil\nfrom numpy import savez_compressed\n"
        "def g(p, q):\n    shutil.move(p, q)\n    savez_compressed(p)\n    p.rename(q)\n"
    )
    assert all_bypasses(tmp_path) == [
        "storage/bad.py:5 os.replace",
        "storage/bad.py:6 np.savez",
        "storage/bad.py:7 .write_text",
        "storage/bad.py:8 .replace",
        "storage/bad.py:9 open",
        "storage/bad.py:10 open",
        "flows/bad.py:4 shutil.move",
        "flows/bad.py:5 savez_compressed",
        "flows/bad.py:6 p.rename",
    ]


def _temporaries(folder: Path) -> list[Path]:
    return list(folder.rglob(f"{TMP_PREFIX}*"))


def test_write_replaces_the_target_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "a" / "b" / "file.bin"  # folders made
    assert atomic_write_bytes(target, b"one") == target
    assert target.read_bytes() == b"one"
    atomic_write_text(target, "zwei \u00fc")
    assert target.read_bytes() == "zwei \u00fc".encode()
    assert _temporaries(tmp_path) == []


def test_a_failed_write_keeps_the_old_file(tmp_path):
    target = tmp_path / "file.json"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError, match="half way"), write_atomically(target) as tmp:
        tmp.write_bytes(b"new, but")
        raise RuntimeError("half way")
    assert target.read_bytes() == b"old"
    assert _temporaries(tmp_path) == []


def test_a_disk_error_names_the_target(tmp_path):
    target = tmp_path / "file.bin"
    with pytest.raises(OSError) as info, write_atomically(target):
        raise OSError(errno.ENOSPC, "No space left on device")
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(target)
    assert not target.exists() and _temporaries(tmp_path) == []


def test_concurrent_writers_of_one_target_never_collide(tmp_path):
    """Eight threads rewrite one file while a reader reads it: no writer fails, every read is one
    writer's whole content, no temporary is left (a shared temporary name fails this: writers
    rename each other's half-written file, or find it gone)."""
    target = tmp_path / "shared.bin"
    size, writers, rounds = 1 << 16, 8, 25
    contents = [bytes([k]) * size for k in range(writers)]
    atomic_write_bytes(target, contents[0])
    errors, reads, stop = [], [], threading.Event()

    def write(k):
        try:
            for _ in range(rounds):
                atomic_write_bytes(target, contents[k])
        except Exception as exc:  # noqa: BLE001 - collected and asserted below
            errors.append(exc)

    def read():
        while not stop.is_set():
            reads.append(target.read_bytes())

    reader = threading.Thread(target=read)
    reader.start()
    threads = [threading.Thread(target=write, args=(k,)) for k in range(writers)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    stop.set()
    reader.join()
    assert errors == []
    assert reads and all(r in contents for r in reads)
    assert target.read_bytes() in contents
    assert _temporaries(tmp_path) == []


def test_staged_folder_publishes_whole_or_not_at_all(tmp_path):
    final = tmp_path / "exports" / "occ3d"
    with staged_folder(final) as tmp:
        (tmp / "a.json").write_text("1")
        assert not final.exists()  # nothing visible while it is written
    assert (final / "a.json").read_text() == "1"
    with pytest.raises(ValueError), staged_folder(final) as tmp:
        (tmp / "b.json").write_text("2")
        raise ValueError("export failed")
    assert sorted(p.name for p in final.iterdir()) == ["a.json"]  # the old one, untouched
    with staged_folder(final) as tmp:  # replace: the new folder swapped in whole
        (tmp / "c.json").write_text("3")
    assert sorted(p.name for p in final.iterdir()) == ["c.json"]
    with staged_folder(final, replace=False) as tmp:  # a key folder already there is kept
        (tmp / "d.json").write_text("4")
    assert sorted(p.name for p in final.iterdir()) == ["c.json"]
    assert _temporaries(tmp_path) == []


def test_swap_in_puts_the_old_folder_back_when_the_new_one_cannot_move(tmp_path, monkeypatch):
    final, new = tmp_path / "v1.zarr", tmp_path / f"{TMP_PREFIX}new"
    final.mkdir()
    (final / "old").write_text("old")
    new.mkdir()
    real = atomic.os.replace

    def failing(src, dst):
        if Path(src) == new:
            raise OSError(errno.EXDEV, "Invalid cross-device link")
        return real(src, dst)

    monkeypatch.setattr(atomic.os, "replace", failing)
    with pytest.raises(OSError):
        swap_in(new, final)
    assert (final / "old").read_text() == "old"
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(TMP_PREFIX)] == [new.name]


def test_npz_bytes_depend_on_the_arrays_only(tmp_path):
    arrays = {"b": np.arange(5, dtype=np.int16), "a": np.eye(3)}
    first = save_npz_deterministic(tmp_path / "1.npz", **arrays).read_bytes()
    second = save_npz_deterministic(tmp_path / "2.npz", **arrays).read_bytes()
    assert first == second
    with zipfile.ZipFile(tmp_path / "2.npz") as zf:
        assert [i.filename for i in zf.infolist()] == ["b.npy", "a.npy"]  # the order given
        assert {i.date_time for i in zf.infolist()} == {(1980, 1, 1, 0, 0, 0)}
    with np.load(tmp_path / "2.npz") as z:
        assert np.array_equal(z["a"], arrays["a"]) and z["b"].dtype == np.int16
