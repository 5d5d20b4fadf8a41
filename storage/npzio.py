"""Deterministic ``.npz`` writing: same arrays -> byte-identical file, whatever the clock.

``np.savez`` stamps every zip entry with the current time, so two runs on the same inputs give
different bytes. :func:`save_npz_deterministic` writes the same container (one ``<key>.npy`` entry
per array, ``np.load`` reads it unchanged) with a fixed entry date (1980-01-01, the zip epoch),
entries in the order given, and fixed permissions.
"""

from __future__ import annotations

import io
import os
import zipfile
from pathlib import Path

import numpy as np

from storage.atomic import write_atomically

_ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)


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
