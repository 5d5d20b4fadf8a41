"""A read-only output store for tests, whoever runs them (issue 41, item 5).

Tests run as root in CI, and root ignores permission bits, so ``chmod -R a-w`` proves nothing
there. In order of preference: a read-only bind mount (``mount --bind`` then ``remount,ro``: the
kernel refuses every write with EROFS, as on a shared dataset's read-only mount; needs
CAP_SYS_ADMIN); else, for a user other than root, ``chmod -R a-w`` (EACCES); else every write
call of this process under the folder (``os.open`` / ``open`` for writing, ``os.mkdir``,
``os.replace``, ``os.rename``, ``os.unlink``, ``os.rmdir``) raises EROFS (monkeypatched: the
weakest, it misses writes by native code). ``how`` says which one was used.
"""

from __future__ import annotations

import builtins
import contextlib
import errno
import os
import shutil
import stat
import subprocess
from collections.abc import Iterator
from pathlib import Path


def _mount_read_only(src: Path, dst: Path) -> bool:
    if os.geteuid() != 0 or not shutil.which("mount"):
        return False
    dst.mkdir(parents=True, exist_ok=True)
    if subprocess.run(["mount", "--bind", str(src), str(dst)], capture_output=True).returncode:
        return False
    if subprocess.run(["mount", "-o", "remount,bind,ro", str(dst)], capture_output=True).returncode:
        subprocess.run(["umount", str(dst)], capture_output=True)
        return False
    return True


@contextlib.contextmanager
def read_only_store(store: Path, monkeypatch) -> Iterator[tuple[Path, str]]:
    """``with read_only_store(out, monkeypatch) as (path, how):`` ``path`` shows ``out`` read-only."""
    view = store.with_name(store.name + "-ro")
    if _mount_read_only(store, view):
        try:
            yield view, "bind mount"
        finally:
            subprocess.run(["umount", str(view)], capture_output=True)
        return
    if os.geteuid() != 0:
        modes = {p: p.stat().st_mode for p in [store, *store.rglob("*")]}
        for p in modes:
            p.chmod(modes[p] & ~(stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH))
        try:
            yield store, "chmod"
        finally:
            for p, mode in modes.items():
                p.chmod(mode)
        return
    inside = str(store.resolve()) + os.sep

    def under(path) -> bool:
        try:
            return os.path.abspath(os.fspath(path)).startswith(inside)
        except TypeError:
            return False

    def refuse(path):
        raise OSError(errno.EROFS, "Read-only file system", os.fspath(path))

    real_open, real_os_open = builtins.open, os.open

    def fake_open(file, mode="r", *a, **k):
        if isinstance(file, (str, os.PathLike)) and under(file) and set(mode) & set("wax+"):
            refuse(file)
        return real_open(file, mode, *a, **k)

    def fake_os_open(path, flags, *a, **k):
        writes = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_TRUNC | os.O_APPEND
        if under(path) and flags & writes:
            refuse(path)
        return real_os_open(path, flags, *a, **k)

    def guard(real):
        def call(path, *a, **k):
            if under(path):
                refuse(path)
            return real(path, *a, **k)

        return call

    monkeypatch.setattr(builtins, "open", fake_open)
    monkeypatch.setattr(os, "open", fake_os_open)
    for name in ("mkdir", "replace", "rename", "unlink", "rmdir"):
        monkeypatch.setattr(os, name, guard(getattr(os, name)))
    yield store, "monkeypatched EROFS"
