"""The CODa raw-layout reader: layout variants and every bad-input error."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from storage.coda import CodaFormatError, CodaSequence, list_sequences, points_in_box, read_lidar_bin
from tests.coda_fixture import POINTS, make_coda


def test_reads_frames_at_5hz(tmp_path):
    make_coda(tmp_path, seq=3, frames=5)
    seq = CodaSequence(tmp_path, 3, frame_stride=2)
    assert seq.info.frame_indices == (0, 2, 4)
    frame = seq.frame(1)
    assert frame.index == 2 and frame.sequence == "3"
    assert frame.points_lidar.dtype == np.float32 and frame.points_lidar.shape == (2000, 3)
    assert frame.point_time_s is not None
    assert frame.stamp_ns == seq.info.stamps_ns[1] == round((1.6e9 + 0.2) * 1e9)
    np.testing.assert_allclose(frame.T_world_from_lidar[:3, 3], [0.2, 0, 0])
    assert frame.boxes[0].track_id == 3 and frame.boxes[0].occlusion == "Light"
    cam0 = seq.info.calibration.cam0
    assert cam0.K[0, 0] == 730 and cam0.width == 1224
    assert seq.info.calibration.T_base_from_lidar[2, 3] == 0.9
    assert list_sequences(tmp_path) == ["3"]
    assert any(p.suffix == ".bin" for p in seq.info.files)


def test_four_channels_jpg_images_and_dense_pose_fallback(tmp_path):
    make_coda(tmp_path, seq=8, frames=2, channels=4, image_ext=".jpg", pose_folder="dense")
    frame = CodaSequence(tmp_path, "8", frame_stride=1).frame(1)
    assert frame.point_time_s is None
    assert frame.image_paths["cam0"].suffix == ".jpg"


def test_3d_comp_choice(tmp_path):
    make_coda(tmp_path, frames=2, lidar_source="3d_comp")
    with pytest.raises(CodaFormatError, match=r"3d_raw_os1_0_0\.bin \(frame 0\): LiDAR file is missing"):
        CodaSequence(tmp_path, 0, lidar_source="3d_raw").frame(0)
    assert CodaSequence(tmp_path, 0, lidar_source="3d_comp").frame(0).points_lidar.shape[0] == 2000


def test_rotated_box_test_uses_yaw(tmp_path):
    make_coda(tmp_path, frames=1)
    box = CodaSequence(tmp_path, 0, frame_stride=1).frame(0).boxes[0]
    # l = 2 along the box x axis, yaw 90 deg: the long side lies along the LiDAR y axis
    pts = np.array([[5.0, 1.9, 0.0], [5.9, 1.0, 0.0]])
    assert points_in_box(pts, box).tolist() == [True, False]


def test_truncated_bin(tmp_path):
    make_coda(tmp_path, frames=1)
    path = tmp_path / "3d_raw/os1/0/3d_raw_os1_0_0.bin"
    path.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(CodaFormatError, match=r"3d_raw_os1_0_0\.bin \(frame 0\): \d+ bytes .*truncated"):
        CodaSequence(tmp_path, 0, frame_stride=1).frame(0)


@pytest.mark.parametrize("channels", [3, 6])
def test_bad_channel_count(tmp_path, channels):
    make_coda(tmp_path, frames=1)
    path = tmp_path / "3d_raw/os1/0/3d_raw_os1_0_0.bin"
    np.zeros((POINTS, channels), np.float32).tofile(path)
    with pytest.raises(CodaFormatError, match=rf"{channels} channels inferred .* expected 4 .* or 5"):
        read_lidar_bin(path, frame=0)


def test_nan_points(tmp_path):
    make_coda(tmp_path, frames=1)
    path = tmp_path / "3d_raw/os1/0/3d_raw_os1_0_0.bin"
    raw = np.fromfile(path, np.float32).reshape(POINTS, 5)
    raw[17, 1] = np.nan
    raw[99, 0] = np.inf
    raw.tofile(path)
    with pytest.raises(CodaFormatError, match=r"\(frame 0\): 2 points have NaN or inf values \(first at point 17"):
        CodaSequence(tmp_path, 0, frame_stride=1).frame(0)


def test_missing_calibration_file(tmp_path):
    make_coda(tmp_path, frames=1)
    (tmp_path / "calibrations/0/calib_os1_to_base.yaml").unlink()
    with pytest.raises(CodaFormatError, match=r"calib_os1_to_base\.yaml: calibration file is missing"):
        CodaSequence(tmp_path, 0)


def test_missing_calibration_key(tmp_path):
    make_coda(tmp_path, frames=1)
    path = tmp_path / "calibrations/0/calib_cam0_intrinsics.yaml"
    data = yaml.safe_load(path.read_text())
    del data["camera_matrix"]
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(CodaFormatError, match=r"calib_cam0_intrinsics\.yaml: calibration key 'camera_matrix' is missing"):
        CodaSequence(tmp_path, 0)


def test_wrong_size_calibration_matrix(tmp_path):
    make_coda(tmp_path, frames=1)
    path = tmp_path / "calibrations/0/calib_os1_to_cam0.yaml"
    path.write_text(yaml.safe_dump({"extrinsic_matrix": {"rows": 3, "cols": 3, "data": [1.0] * 9}}))
    with pytest.raises(CodaFormatError, match=r"extrinsic_matrix has 9 values, expected 4x4"):
        CodaSequence(tmp_path, 0)


def test_pose_lines_do_not_match_frames(tmp_path):
    make_coda(tmp_path, frames=4)
    path = tmp_path / "poses/dense_global/0.txt"
    path.write_text("".join(path.read_text().splitlines(keepends=True)[:3]))
    with pytest.raises(CodaFormatError, match=r"0\.txt: 3 pose lines but .*timestamps/0\.txt has 4 frames"):
        CodaSequence(tmp_path, 0)


def test_bad_pose_line(tmp_path):
    make_coda(tmp_path, frames=3)
    path = tmp_path / "poses/dense_global/0.txt"
    lines = path.read_text().splitlines()
    lines[1] = "1.0 0 0 0 2 0 0 0"
    path.write_text("\n".join(lines))
    with pytest.raises(CodaFormatError, match=r"line 2 \(frame 1\): quaternion norm 2\.0000"):
        CodaSequence(tmp_path, 0)


def test_non_monotonic_timestamps(tmp_path):
    make_coda(tmp_path, frames=4)
    path = tmp_path / "timestamps/0.txt"
    stamps = path.read_text().split()
    stamps[2], stamps[3] = stamps[3], stamps[2]
    path.write_text("\n".join(stamps))
    with pytest.raises(CodaFormatError, match=r"timestamps are not strictly increasing: line 4 .* \(frame 3\)"):
        CodaSequence(tmp_path, 0)


def test_unknown_sequence(tmp_path):
    make_coda(tmp_path, seq=2, frames=1)
    with pytest.raises(CodaFormatError, match=r"unknown sequence id '5' .*available: \['2'\]"):
        CodaSequence(tmp_path, 5)


def test_malformed_box_json(tmp_path):
    make_coda(tmp_path, frames=1)
    (tmp_path / "3d_bbox/os1/0/3d_bbox_os1_0_0.json").write_text('{"3dbbox": [{"classId": "Car"}]}')
    with pytest.raises(CodaFormatError, match=r"\(frame 0\): box 0 is malformed"):
        CodaSequence(tmp_path, 0, frame_stride=1).frame(0)


def test_missing_image(tmp_path):
    make_coda(tmp_path, frames=1)
    (tmp_path / "2d_rect/cam1/0/2d_rect_cam1_0_0.png").unlink()
    with pytest.raises(CodaFormatError, match=r"2d_rect_cam1_0_0\.png \(frame 0\): image is missing"):
        CodaSequence(tmp_path, 0, frame_stride=1).frame(0)
