"""Deterministic ``.npz`` writing: same arrays -> byte-identical file, whatever the clock.

``np.savez`` stamps every zip entry with the current time, so two runs on the same inputs give
different bytes. :func:`save_npz_deterministic` writes the same container (one ``<key>.npy`` entry
per array, ``np.load`` reads it unchanged) with a fixed entry date (1980-01-01, the zip epoch),
entries in the order given, and fixed permissions.
"""

from __future__ import annotations

import io
import math
import os
import zipfile
from pathlib import Path
from typing import BinaryIO

import numpy as np

from storage.atomic import write_atomically

_ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)

#: the largest array an ``.npz`` member may hold (bytes, uncompressed): a ground-truth frame, a
#: stage product or an SMPL model is tens of MB; a member declaring more is refused before a byte
#: of it is allocated (a crafted file declaring 6 GB must not grow memory)
MAX_MEMBER_BYTES = 1 << 30


def check_npz_members(fh: BinaryIO, max_member_bytes: int = MAX_MEMBER_BYTES) -> None:
    """Before ``np.load`` reads the open ``.npz`` ``fh``: every member's declared (uncompressed)
    size is at most ``max_member_bytes``, and its ``.npy`` header (shape x item size) fits in
    that size. Reads only the zip directory and each member's header; ``fh`` is rewound.
    ValueError (saying which member and what it declares) otherwise; zipfile.BadZipFile for a
    file that is not a zip."""
    with zipfile.ZipFile(fh) as zf:
        for info in zf.infolist():
            if info.file_size > max_member_bytes:
                raise ValueError(
                    f"member {info.filename!r} declares {info.file_size} bytes, more than the "
                    f"{max_member_bytes} an array may hold"
                )
            if not info.filename.endswith(".npy"):
                continue
            with zf.open(info) as member:
                version = np.lib.format.read_magic(member)
                read_header = (
                    np.lib.format.read_array_header_1_0
                    if version == (1, 0)
                    else np.lib.format.read_array_header_2_0
                )
                shape, _, dtype = read_header(member)
            need = math.prod(shape) * dtype.itemsize
            if need > info.file_size:
                raise ValueError(
                    f"member {info.filename!r}: its header declares {shape} {dtype} "
                    f"({need} bytes), the member holds {info.file_size}"
                )
    fh.seek(0)


def load_npz(
    source: str | os.PathLike | BinaryIO,
    keys: list[str] | None = None,
    max_member_bytes: int = MAX_MEMBER_BYTES,
) -> dict[str, np.ndarray]:
    """Every array (or ``keys``) of the ``.npz`` at ``source`` (a path or an open binary file),
    no pickles, each member checked against ``max_member_bytes`` before it is read
    (:func:`check_npz_members`). Raises one of :data:`NPZ_ERRORS`; callers name the file."""
    if not hasattr(source, "read"):
        with open(source, "rb") as fh:
            return load_npz(fh, keys, max_member_bytes)
    check_npz_members(source, max_member_bytes)
    with np.load(source, allow_pickle=False) as z:
        return {k: z[k] for k in (z.files if keys is None else keys)}


#: what reading a damaged, truncated or crafted ``.npz`` raises
NPZ_ERRORS = (OSError, EOFError, ValueError, KeyError, zipfile.BadZipFile)


def save_npz_deterministic(
    path: str | os.PathLike, compressed: bool = True, **arrays: np.ndarray
) -> Path:
    """Write ``arrays`` to ``path`` as an ``.npz`` readable by ``np.load``; returns the path.

    compressed: deflate each entry (as ``np.savez_compressed``) or store it (as ``np.savez``).
    Written atomically (:func:`storage.atomic.write_atomically`): a reader never sees half a
    file. Object arrays are refused (they would need pickle to load).
    """
    path = Path(path)
    if not arrays:
        raise ValueError(f"save_npz_deterministic({path}): no arrays given")
    for key, value in arrays.items():
        if np.asanyarray(value).dtype.hasobject:
            raise ValueError(f"save_npz_deterministic({path}): array {key!r} has dtype object")
    method = zipfile.ZIP_DEFLATED if compressed else zipfile.ZIP_STORED
    with (
        write_atomically(path) as tmp,
        zipfile.ZipFile(tmp, mode="w", compression=method, allowZip64=True) as zf,
    ):
        for key, value in arrays.items():
            buffer = io.BytesIO()
            np.lib.format.write_array(buffer, np.asanyarray(value), allow_pickle=False)
            info = zipfile.ZipInfo(f"{key}.npy", date_time=_ZIP_EPOCH)
            info.compress_type = method
            info.external_attr = 0o644 << 16
            info.create_system = 3  # unix, independent of the host
            zf.writestr(info, buffer.getvalue())
    return path
