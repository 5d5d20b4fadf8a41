"""Plausibility bounds of inputs (tasks/bounds.py), checked by the readers (issue 41, item 6).

Each out-of-bounds value fails its frame (a sweep) or its sequence (a calibration, a pose track,
a TF graph: tests/test_log_bad_input.py) with a line naming the file, the frame and the value."""

from __future__ import annotations

import numpy as np
import pytest

from storage.sources.coda.calibration import read_extrinsic
from storage.sources.coda.layout import CodaFormatError, CodaFrameError
from storage.sources.coda.reader import POINTS_PER_SWEEP, read_lidar_raw
from tasks.bounds import (
    MAX_CALIBRATION_TRANSLATION_M,
    MAX_POINT_COORDINATE_M,
    MAX_POSE_SPEED_M_S,
    pose_track_problem,
    rigid_problem,
    sweep_problem,
)


@pytest.mark.parametrize(
    "points, says",
    [
        (np.full((4, 3), 1e30), "beyond"),
        (np.array([[0, 0, 0], [0, 0, 2 * MAX_POINT_COORDINATE_M]]), "1 point(s) beyond"),
        (np.zeros((5, 3)), "all 5 points are at (0, 0, 0)"),
        (np.array([[0, 0, 0], [1.0, 2.0, 0.5]]), ""),
        (np.zeros((0, 3)), ""),  # empty input is normal input
    ],
)
def test_sweep_bounds(points, says):
    problem = sweep_problem(points)
    assert (says in problem) if says else problem == "", problem


def _T(t=(0.0, 0.0, 0.0), R=None):
    T = np.eye(4)
    T[:3, 3] = t
    if R is not None:
        T[:3, :3] = R
    return T


@pytest.mark.parametrize(
    "T, says",
    [
        (_T((1e6, 0, 0)), "translation is 1e+06 m"),
        (_T((MAX_CALIBRATION_TRANSLATION_M * 0.99, 0, 0)), ""),
        (_T(R=np.diag([1.0, 1.0, 2.0])), "not orthonormal"),
        (_T(R=np.diag([1.0, 1.0, -1.0])), "not orthonormal"),  # a mirror
        (_T((np.nan, 0, 0)), "non-finite"),
    ],
)
def test_rigid_bounds(T, says):
    problem = rigid_problem(T, "os1 -> cam0")
    assert (says in problem) if says else problem == "", problem


def test_pose_track_bounds():
    stamps = np.arange(4) * 100_000_000  # 10 Hz
    walk = np.array([[0.1 * k, 0, 0] for k in range(4)])
    assert pose_track_problem(stamps, walk) == ""
    jump = walk.copy()
    jump[2, 0] += MAX_POSE_SPEED_M_S  # a 20 m step in 0.1 s
    assert "pose 2 jumps" in pose_track_problem(stamps, jump)
    nan = walk.copy()
    nan[1, 1] = np.nan
    assert "pose 1 is not finite" in pose_track_problem(stamps, nan)


@pytest.mark.parametrize("value, says", [(1e30, "beyond 10000 m"), (0.0, "at (0, 0, 0)")])
def test_an_implausible_coda_sweep_fails_its_frame(value, says, tmp_path):
    raw = np.zeros((POINTS_PER_SWEEP, 4), "<f4")
    raw[:, :3] = value
    path = tmp_path / "3d_raw_os1_0_7.bin"
    path.write_bytes(raw.tobytes())
    with pytest.raises(CodaFrameError, match="implausible sweep") as err:
        read_lidar_raw(path, frame=7)
    assert says in str(err.value) and str(path) in str(err.value) and err.value.frame == 7


def test_a_coda_calibration_1e6_m_long_fails_its_sequence(tmp_path):
    path = tmp_path / "calib_os1_to_cam0.yaml"
    data = [1, 0, 0, 1.0e6, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]
    path.write_text(f"extrinsic_matrix:\n  rows: 4\n  cols: 4\n  data: {data}\n")
    with pytest.raises(CodaFormatError, match="translation is 1e\\+06 m") as err:
        read_extrinsic(path)
    assert str(path) in str(err.value)


@pytest.mark.parametrize("fmt", ["png-file", "compressed"])
def test_a_16_bit_png_is_scaled_not_read_as_white(fmt, tmp_path):
    """Regression (issue 41): a 16-bit grey PNG was read as an all-white RGB image."""
    import io

    from PIL import Image

    from storage.images import read_rgb
    from storage.sources.log.images import decode_compressed

    grey = (np.arange(12, dtype=np.uint16).reshape(3, 4) * 5000).astype(np.uint16)
    buf = io.BytesIO()
    Image.fromarray(grey).save(buf, format="PNG")
    if fmt == "png-file":
        (tmp_path / "a.png").write_bytes(buf.getvalue())
        rgb = read_rgb(tmp_path / "a.png")
    else:
        rgb = decode_compressed("png", buf.getvalue())
    assert rgb.shape == (3, 4, 3) and rgb.dtype == np.uint8
    np.testing.assert_array_equal(rgb[..., 0], np.round(grey / 257.0).astype(np.uint8))
    assert (rgb[..., 0] == rgb[..., 2]).all() and (rgb == 255).mean() < 0.2


def test_a_float_image_is_refused_naming_its_mode(tmp_path):
    from PIL import Image

    from storage.images import read_rgb

    Image.fromarray(np.ones((3, 4), np.float32)).save(tmp_path / "f.tiff")
    with pytest.raises(ValueError, match="mode 'F'") as err:
        read_rgb(tmp_path / "f.tiff")
    assert "f.tiff" in str(err.value)


def test_a_first_sweep_cut_to_the_4_channel_size_is_the_frame_named(copy_dataset):
    """Regression (issue 41): the sequence's channel count came from its first sweep, so a first
    sweep cut to exactly the 4-channel size made every good 5-channel frame "truncated" and
    named the cut frame last. The count is the sweeps' majority: the cut frame alone fails."""
    from storage.sources.coda.reader import CodaSequence

    root = copy_dataset()
    seq = CodaSequence(root, "1", frame_stride=1)
    frames = list(seq.info.frame_indices)
    assert seq.info.lidar_channels == 5 and len(frames) >= 3
    first = seq.lidar_path(frames[0])
    first.write_bytes(first.read_bytes()[: POINTS_PER_SWEEP * 4 * 4])  # a whole 4-channel size
    seq = CodaSequence(root, "1", frame_stride=1)
    assert seq.info.lidar_channels == 5
    with pytest.raises(CodaFrameError) as err:
        seq.frame(0)
    assert err.value.frame == frames[0] and first.name in str(err.value)
    assert seq.frame(1).points_lidar.shape[1] == 3  # the good frames read as before
