"""Precomputed CLIFF estimates (storage/cliff_files.py): round trip, conversion, every bad-file error."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch

from storage.cliff_files import CliffFileError, read_cliff_estimates, write_cliff_estimates
from tasks.body.rotations import axis_angle_to_matrix
from tasks.fit.init_oracle import cliff_to_params, params_to_cliff_camera

K = np.array([[1000.0, 0, 960], [0, 1000.0, 540], [0, 0, 1]])


def _estimates(n=3, seed=0):
    rng = np.random.default_rng(seed)
    aa = rng.normal(0.0, 0.4, (n, 24, 3))
    rot = axis_angle_to_matrix(torch.as_tensor(aa)).numpy()
    transl = np.stack([rng.uniform(-1, 1, n), rng.uniform(-0.5, 0.5, n), rng.uniform(3, 12, n)], 1)
    center = rng.uniform(200, 1500, (n, 2))
    size = rng.uniform(100, 400, n)
    return (
        dict(
            frame=np.arange(n) // 2,
            det_index=np.arange(n) % 2,
            rotmats=rot,
            betas=rng.normal(size=(n, 10)),
            cam_crop=params_to_cliff_camera(transl, center, size, K),
            bbox_center=center,
            bbox_size=size,
        ),
        aa,
        transl,
    )


def test_round_trip_crop_camera_and_transl_rows(tmp_path):
    est, aa, transl = _estimates(4)
    # rows 0, 2 with the crop camera, rows 1, 3 with a direct translation
    direct = np.full((4, 3), np.nan)
    direct[1::2] = transl[1::2]
    for key in ("cam_crop", "bbox_center"):
        est[key] = est[key].copy()
        est[key][1::2] = np.nan
    est["bbox_size"] = est["bbox_size"].copy()
    est["bbox_size"][1::2] = np.nan
    path = write_cliff_estimates(tmp_path / "0" / "cliff.parquet", transl=direct, **est)
    assert [p.name for p in (tmp_path / "0").iterdir()] == ["cliff.parquet"]  # no temporary
    got = read_cliff_estimates(path)
    assert got["frame"].tolist() == [0, 0, 1, 1] and got["det_index"].tolist() == [0, 1, 0, 1]
    assert got["has_transl"].tolist() == [False, True, False, True]
    np.testing.assert_allclose(got["rotmats"], est["rotmats"], atol=1e-6)
    p = cliff_to_params(
        got["rotmats"],
        got["betas"],
        got["cam_crop"],
        got["bbox_center"],
        got["bbox_size"],
        K,
        got["transl"],
        got["has_transl"],
    )
    # both placements land on the same translations (float32 storage)
    np.testing.assert_allclose(p.transl, transl, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(p.global_orient, aa[:, 0], atol=1e-4)
    np.testing.assert_allclose(p.body_pose, aa[:, 1:].reshape(-1, 69), atol=1e-4)


def _write_table(path, est, **changes):
    n = len(est["frame"])
    cols = {
        "frame": est["frame"].tolist(),
        "det_index": est["det_index"].tolist(),
        "rotmats": est["rotmats"].reshape(n, 216).tolist(),
        "betas": est["betas"].tolist(),
        "cam_crop": est["cam_crop"].tolist(),
        "bbox_center": est["bbox_center"].tolist(),
        "bbox_size": est["bbox_size"].tolist(),
        "transl": [None] * n,
    }
    for key, (row, value) in changes.items():
        cols[key][row] = value
    types = {"frame": pa.int64(), "det_index": pa.int64(), "bbox_size": pa.float32()}
    table = pa.table(
        {k: pa.array(v, type=types.get(k, pa.list_(pa.float32()))) for k, v in cols.items()}
    )
    pq.write_table(table, path)
    return path


def _bad_rotation():
    R = np.eye(3)
    R[0, 0] = 2.0  # a scaled axis: not orthonormal
    return R


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"rotmats": (1, [0.0] * 215)}, "rotmats must hold 216 numbers"),
        ({"betas": (2, [0.0] * 9)}, "betas must hold 10 numbers"),
        ({"betas": (1, [float("nan")] + [0.0] * 9)}, "betas has NaN/inf"),
        ({"cam_crop": (0, [0.5, float("inf"), 0.0])}, "cam_crop has NaN/inf"),
        ({"cam_crop": (0, [-0.5, 0.0, 0.0])}, "must be > 0"),
        ({"cam_crop": (2, None)}, "needs transl, or all of"),
        ({"transl": (1, [0.0, 0.0, 5.0])}, "both transl and crop-camera"),
        ({"det_index": (1, 0), "frame": (1, 0)}, "duplicate of row 0"),
        ({"det_index": (2, -1)}, "det_index >= 0"),
    ],
)
def test_bad_file_errors_name_file_row_and_value(tmp_path, changes, message):
    est, _, _ = _estimates(3)
    path = _write_table(tmp_path / "cliff.parquet", est, **changes)
    with pytest.raises(CliffFileError, match=message) as err:
        read_cliff_estimates(path)
    assert str(path) in str(err.value)
    row = next(iter(changes.values()))[0]
    assert f"row {row} (frame" in str(err.value)


def test_non_rotation_and_reflection_are_rejected(tmp_path):
    est, _, _ = _estimates(3)
    for R, what in ((_bad_rotation(), "R^T R - I"), (np.diag([1.0, 1.0, -1.0]), "det = -1.0")):
        rot = est["rotmats"].copy()
        rot[2, 5] = R
        path = _write_table(tmp_path / "cliff.parquet", {**est, "rotmats": rot})
        with pytest.raises(
            CliffFileError, match=r"row 2 \(frame 1, det_index 0\): rotmats\[5\] is not a rotation"
        ) as err:
            read_cliff_estimates(path)
        assert what in str(err.value)


def test_missing_file_column_and_unreadable_file(tmp_path):
    with pytest.raises(CliffFileError, match="file is missing"):
        read_cliff_estimates(tmp_path / "none.parquet")
    pq.write_table(pa.table({"frame": [0]}), tmp_path / "few.parquet")
    with pytest.raises(CliffFileError, match="missing columns"):
        read_cliff_estimates(tmp_path / "few.parquet")
    (tmp_path / "junk.parquet").write_bytes(b"not parquet")
    with pytest.raises(CliffFileError, match="not a readable Parquet file"):
        read_cliff_estimates(tmp_path / "junk.parquet")


def test_empty_file_is_normal(tmp_path):
    path = write_cliff_estimates(
        tmp_path / "cliff.parquet",
        np.zeros(0),
        np.zeros(0),
        np.zeros((0, 24, 3, 3)),
        np.zeros((0, 10)),
        np.zeros((0, 3)),
        np.zeros((0, 2)),
        np.zeros(0),
    )
    got = read_cliff_estimates(path)
    assert got["rotmats"].shape == (0, 24, 3, 3) and got["betas"].shape == (0, 10)
    p = cliff_to_params(
        got["rotmats"],
        got["betas"],
        got["cam_crop"],
        got["bbox_center"],
        got["bbox_size"],
        K,
        got["transl"],
        got["has_transl"],
    )
    assert len(p) == 0
