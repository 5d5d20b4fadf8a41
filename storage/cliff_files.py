"""Precomputed initial body estimates (CLIFF outputs) for the fit stage: writer, reader, validation.

One Parquet file per sequence, ``<fit.init_dir>/<sequence>/cliff.parquet``, one row per person
detection, keyed by (frame, det_index). The columns are documented field by field in
``storage/PERCEPTION_FORMAT.md`` (section "cliff.parquet"). The reader returns plain arrays; the
conversion to SMPL parameters in the camera frame is ``tasks.fit.init_oracle.cliff_to_params``.
Every problem raises :class:`CliffFileError` naming the file, the row, its (frame, det_index) and
the value.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from storage.atomic import write_atomically

CLIFF_FILE = "cliff.parquet"
#: tolerance of the rotation check: max |R^T R - I| and |det R - 1|
ROTATION_TOL = 1e-3

CLIFF_SCHEMA = pa.schema(
    [
        ("frame", pa.int64()),
        ("det_index", pa.int64()),
        ("rotmats", pa.list_(pa.float32(), 24 * 9)),
        ("betas", pa.list_(pa.float32(), 10)),
        ("cam_crop", pa.list_(pa.float32(), 3)),
        ("bbox_center", pa.list_(pa.float32(), 2)),
        ("bbox_size", pa.float32()),
        ("transl", pa.list_(pa.float32(), 3)),
    ]
)
_CROP_COLUMNS = ("cam_crop", "bbox_center", "bbox_size")


class CliffFileError(ValueError):
    """A precomputed CLIFF file is missing, malformed or inconsistent."""


def cliff_path(root: str | os.PathLike, sequence: str) -> Path:
    """Where a sequence's estimates live under ``fit.init_dir``."""
    return Path(root) / str(sequence) / CLIFF_FILE


def write_cliff_estimates(
    path: str | os.PathLike,
    frame,
    det_index,
    rotmats,
    betas,
    cam_crop=None,
    bbox_center=None,
    bbox_size=None,
    transl=None,
) -> Path:
    """Write N estimates atomically (:func:`storage.atomic.write_atomically`).

    frame, det_index (N,) int; rotmats (N, 24, 3, 3) (joint 0 = global orientation in the OpenCV
    camera frame, the others relative to their parent); betas (N, 10). The placement is either
    CLIFF's crop camera (cam_crop (N, 3) = (s, tx, ty), bbox_center (N, 2) px, bbox_size (N,) px)
    or transl (N, 3) m in the camera frame; rows of an array that is given but NaN are written
    as null (so a file may mix both forms row by row). Validation happens on reading.
    """
    path = Path(path)
    n = len(np.asarray(frame))

    def rows(x, width):
        if x is None:
            return [None] * n
        a = np.asarray(x, np.float32).reshape(n, width)
        return [None if not np.isfinite(r).any() else r.tolist() for r in a]

    size = (
        [None] * n
        if bbox_size is None
        else [
            None if not np.isfinite(v) else float(v)
            for v in np.asarray(bbox_size, np.float32).reshape(n)
        ]
    )
    table = pa.table(
        {
            "frame": np.asarray(frame, np.int64),
            "det_index": np.asarray(det_index, np.int64),
            "rotmats": np.asarray(rotmats, np.float32).reshape(n, 216).tolist(),
            "betas": np.asarray(betas, np.float32).reshape(n, 10).tolist(),
            "cam_crop": rows(cam_crop, 3),
            "bbox_center": rows(bbox_center, 2),
            "bbox_size": size,
            "transl": rows(transl, 3),
        },
        schema=CLIFF_SCHEMA,
    )
    with write_atomically(path) as tmp:
        pq.write_table(table, tmp)
    return path


def _fail(path: Path, row: int | None, key, message: str) -> CliffFileError:
    where = f"{path}" if row is None else f"{path}: row {row} (frame {key[0]}, det_index {key[1]})"
    return CliffFileError(f"{where}: {message}")


def read_cliff_estimates(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read and validate one sequence's estimates.

    Returns frame (N,) int64, det_index (N,) int64, rotmats (N, 24, 3, 3) float64, betas (N, 10),
    has_transl (N,) bool, transl (N, 3) m, cam_crop (N, 3), bbox_center (N, 2), bbox_size (N,)
    float64; the placement columns a row does not use are zero.
    """
    path = Path(path)
    if not path.is_file():
        raise _fail(
            path,
            None,
            None,
            "file is missing (fit.init_provider 'precomputed' needs one per sequence)",
        )
    try:
        table = pq.read_table(path)
    except (pa.ArrowInvalid, OSError) as error:
        raise _fail(path, None, None, f"not a readable Parquet file ({error})") from error
    missing = [n for n in CLIFF_SCHEMA.names if n not in table.column_names]
    if missing:
        raise _fail(path, None, None, f"missing columns {missing}; expected {CLIFF_SCHEMA.names}")
    cols = {n: table.column(n).to_pylist() for n in CLIFF_SCHEMA.names}
    n = table.num_rows
    frame, det = cols["frame"], cols["det_index"]
    for i in range(n):
        if frame[i] is None or det[i] is None or det[i] < 0:
            raise _fail(
                path, i, (frame[i], det[i]), "frame and det_index must be non-null, det_index >= 0"
            )
    out = {
        "frame": np.asarray(frame, np.int64).reshape(n),
        "det_index": np.asarray(det, np.int64).reshape(n),
    }
    keys = list(zip(out["frame"].tolist(), out["det_index"].tolist()))

    def fixed(name, width, i, value):
        if value is None or len(value) != width:
            got = "null" if value is None else f"{len(value)} numbers"
            raise _fail(path, i, keys[i], f"{name} must hold {width} numbers, got {got}")
        a = np.asarray(value, np.float64)
        if not np.isfinite(a).all():
            raise _fail(path, i, keys[i], f"{name} has NaN/inf: {a.tolist()}")
        return a

    rot = np.zeros((n, 24, 3, 3))
    betas = np.zeros((n, 10))
    has_transl = np.zeros(n, bool)
    transl, cam, center, size = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 2)), np.zeros(n)
    seen: dict[tuple[int, int], int] = {}
    for i in range(n):
        if keys[i] in seen:
            raise _fail(path, i, keys[i], f"duplicate of row {seen[keys[i]]}")
        seen[keys[i]] = i
        rot[i] = fixed("rotmats", 216, i, cols["rotmats"][i]).reshape(24, 3, 3)
        betas[i] = fixed("betas", 10, i, cols["betas"][i])
        crop = [cols[c][i] is not None for c in _CROP_COLUMNS]
        if cols["transl"][i] is not None:
            if any(crop):
                raise _fail(
                    path, i, keys[i], "has both transl and crop-camera columns; give one placement"
                )
            has_transl[i] = True
            transl[i] = fixed("transl", 3, i, cols["transl"][i])
            if transl[i, 2] <= 0:
                raise _fail(
                    path,
                    i,
                    keys[i],
                    f"transl {transl[i].tolist()} must have z > 0 (in front of the camera)",
                )
        else:
            if not all(crop):
                raise _fail(
                    path, i, keys[i], "needs transl, or all of cam_crop, bbox_center, bbox_size"
                )
            cam[i] = fixed("cam_crop", 3, i, cols["cam_crop"][i])
            center[i] = fixed("bbox_center", 2, i, cols["bbox_center"][i])
            size[i] = fixed("bbox_size", 1, i, [cols["bbox_size"][i]])[0]
            if cam[i, 0] <= 0 or size[i] <= 0:
                raise _fail(
                    path,
                    i,
                    keys[i],
                    f"cam_crop scale s = {cam[i, 0]} and bbox_size = {size[i]} must be > 0",
                )
    # rotations: orthonormal with det +1 (a row of an unflattened or transposed-wrong file fails here)
    if n:
        err = np.abs(np.einsum("njki,njkl->njil", rot, rot) - np.eye(3)).max(axis=(2, 3))
        det_err = np.abs(np.linalg.det(rot) - 1.0)
        bad = (err > ROTATION_TOL) | (det_err > ROTATION_TOL)
        if bad.any():
            i, j = (int(v) for v in np.argwhere(bad)[0])
            raise _fail(
                path,
                i,
                keys[i],
                f"rotmats[{j}] is not a rotation matrix (max |R^T R - I| = "
                f"{err[i, j]:.3g}, det = {np.linalg.det(rot[i, j]):.4f}): {rot[i, j].round(4).tolist()}",
            )
    out.update(
        rotmats=rot,
        betas=betas,
        has_transl=has_transl,
        transl=transl,
        cam_crop=cam,
        bbox_center=center,
        bbox_size=size,
    )
    return out
