"""Opening input files safely, and the one error type of bad input.

Every reader of user data opens files through :func:`open_regular` (or checks them with
:func:`regular_stat`): only regular files are read. A FIFO, a device, a socket, a directory or a
symlink loop in place of a data file is a named :class:`InputError`, never a hang: the file is
opened with ``O_NONBLOCK`` (opening a FIFO for reading would otherwise wait for a writer) and its
type is checked on the open descriptor before a byte is read.

:class:`InputError` is the error of bad input everywhere in ``storage/`` (the CODa reader's
``CodaFormatError`` / ``CodaFrameError`` and the ground truth's ``GTFormatError`` are kinds of it):
its message names the file, the frame where there is one, the value and what was expected, and it
carries ``path`` and ``frame`` so a caller can fail that frame (or that sequence) alone.
"""

from __future__ import annotations

import io
import os
import stat
from pathlib import Path


class InputError(ValueError):
    """Bad or missing input: ``path`` (or None) and ``frame`` (raw frame number, or None)."""

    def __init__(
        self,
        message: str,
        path: Path | str | None = None,
        frame: int | None = None,
        sequence: str | None = None,
    ):
        super().__init__(message)
        self.path = None if path is None else Path(path)
        self.frame = frame
        self.sequence = sequence


def where(path: Path | str, frame: int | None = None) -> str:
    """``path (frame N)``: how messages name a place in the input."""
    return f"{path}" + (f" (frame {frame})" if frame is not None else "")


def file_kind(mode: int) -> str:
    """What a stat mode is, in words (for messages)."""
    for test, name in (
        (stat.S_ISREG, "regular file"),
        (stat.S_ISDIR, "directory"),
        (stat.S_ISFIFO, "FIFO (named pipe)"),
        (stat.S_ISCHR, "character device"),
        (stat.S_ISBLK, "block device"),
        (stat.S_ISSOCK, "socket"),
        (stat.S_ISLNK, "symbolic link"),
    ):
        if test(mode):
            return name
    return f"special file (mode {oct(mode)})"


def _open_error(path: Path, frame: int | None, what: str, exc: OSError) -> InputError:
    if isinstance(exc, FileNotFoundError):
        return InputError(f"{where(path, frame)}: {what} is missing", path, frame)
    reason = exc.strerror or str(exc)
    if exc.errno == getattr(os, "ELOOP", None) or "symbolic links" in reason:
        reason = f"symlink loop ({reason})"
    return InputError(f"{where(path, frame)}: cannot open the {what}: {reason}", path, frame)


def regular_stat(path: Path | str, frame: int | None = None, what: str = "file") -> os.stat_result:
    """``os.stat`` of a regular file (symlinks followed); InputError naming the file otherwise."""
    path = Path(path)
    try:
        st = os.stat(path)
    except OSError as exc:
        raise _open_error(path, frame, what, exc) from None
    if not stat.S_ISREG(st.st_mode):
        raise InputError(
            f"{where(path, frame)}: the {what} is a {file_kind(st.st_mode)}, expected a regular file",
            path,
            frame,
        )
    return st


def open_regular(
    path: Path | str, frame: int | None = None, what: str = "file"
) -> io.BufferedReader:
    """Open a regular file for reading in binary mode, never blocking on a FIFO or a device."""
    path = Path(path)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        raise _open_error(path, frame, what, exc) from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise InputError(
                f"{where(path, frame)}: the {what} is a {file_kind(st.st_mode)}, expected a regular "
                "file",
                path,
                frame,
            )
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_bytes(
    path: Path | str, frame: int | None = None, what: str = "file", max_bytes: int | None = None
) -> bytes:
    """The whole content of a regular file; a read error names the file. ``max_bytes``: a file
    larger than that is refused (its size checked on the open descriptor, before a byte is read
    or memory allocated for it)."""
    path = Path(path)
    with open_regular(path, frame, what) as fh:
        size = os.fstat(fh.fileno()).st_size
        if max_bytes is not None and size > max_bytes:
            raise InputError(
                f"{where(path, frame)}: the {what} is {size} bytes, more than the {max_bytes} "
                "this reader takes",
                path,
                frame,
            )
        try:
            return fh.read() if max_bytes is None else fh.read(max_bytes + 1)[:max_bytes]
        except OSError as exc:
            raise InputError(
                f"{where(path, frame)}: cannot read the {what}: {exc.strerror or exc}", path, frame
            ) from None


def read_text(path: Path | str, frame: int | None = None, what: str = "file") -> str:
    """A regular file as UTF-8 text; undecodable bytes are an InputError naming the file."""
    data = read_bytes(path, frame, what)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(
            f"{where(path, frame)}: the {what} is not UTF-8 text (byte {exc.start}: "
            f"{data[exc.start : exc.start + 1]!r})",
            path,
            frame,
        ) from None
