"""The CODa raw-layout reader: layout variants of real downloads and every bad-input error."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from storage.coda import (
    CodaFormatError,
    CodaFrameError,
    CodaSequence,
    box_rotation,
    list_sequences,
    read_boxes,
    read_extrinsic,
    read_lidar_bin,
    stride_frames,
)
from tasks.geometry import points_in_boxes
from tests.coda_fixture import (
    K_RECT,
    POINTS,
    T_CAM0_FROM_OS1,
    make_coda,
    pedestrian_box,
    stereo_calibration,
)


def test_reads_frames_at_5hz(tmp_path):
    make_coda(tmp_path, seq=3, frames=5)
    seq = CodaSequence(tmp_path, 3, frame_stride=2)
    assert seq.info.frame_indices == (0, 2, 4) and seq.info.num_stamps == 5
    assert "5 of 5 frames have a 3d_comp sweep (all frames)" in seq.info.selection
    frame = seq.frame(1)
    assert frame.index == 2 and frame.sequence == "3"
    assert frame.points_lidar.dtype == np.float32 and frame.points_lidar.shape == (2000, 3)
    assert frame.stamp_ns == seq.info.stamps_ns[1] == round((1.6e9 + 0.2) * 1e9)
    np.testing.assert_allclose(frame.T_world_from_lidar[:3, 3], [0.2, 0, 0])
    assert (
        frame.boxes[0].track_id == 3
        and frame.boxes[0].occlusion == "Light"
        and frame.box_problems == ()
    )
    assert frame.semantic_labels is not None and frame.semantic_labels.shape == (2000,)
    assert frame.intensity_present
    assert seq.info.calibration.cam0.width == 1224
    assert (
        seq.info.calibration.T_base_from_lidar[2, 3] == 0.9
        and not seq.info.calibration.base_is_default
    )
    assert list_sequences(tmp_path) == ["3"]
    assert any(p.suffix == ".bin" for p in seq.info.files) and seq.info.warnings == ()


def test_fifth_channel_is_nanoseconds(tmp_path):
    # the devkit's decoder stores each column's time since the first column in ns (0 .. ~99.9 ms)
    make_coda(tmp_path, frames=1)
    frame = CodaSequence(tmp_path, 0, frame_stride=1).frame(0)
    t = frame.point_time_s
    assert t is not None and t.dtype == np.float32
    # a unit check of the data, not a timing: one 10 Hz sweep spans 0.1 s of point times
    sweep_s = 0.1
    assert 0.0 <= t.min() and 0.9 * sweep_s < t.max() < sweep_s  # seconds, not 1e8 "seconds"


def test_four_channels_png_images_and_dense_pose_fallback(tmp_path):
    make_coda(tmp_path, seq=8, frames=2, channels=4, image_ext=".png", pose_folder="dense")
    frame = CodaSequence(tmp_path, "8", frame_stride=1).frame(1)
    assert frame.point_time_s is None
    assert frame.image_paths["cam0"].suffix == ".png"


def test_3d_comp_is_the_default_and_3d_raw_a_choice(tmp_path):
    make_coda(tmp_path, frames=2)
    assert CodaSequence(tmp_path, 0).lidar_source == "3d_comp"
    with pytest.raises(
        CodaFormatError,
        match=r"no 3d_raw sweeps for sequence 0; found 3d_comp/os1/0: "
        r"set dataset.lidar_source: 3d_comp",
    ):
        CodaSequence(tmp_path, 0, lidar_source="3d_raw")
    make_coda(tmp_path / "raw", frames=2, lidar_source="3d_raw")
    assert (
        CodaSequence(tmp_path / "raw", 0, lidar_source="3d_raw").frame(0).points_lidar.shape[0]
        == 2000
    )


def test_split_style_sparse_frames(tmp_path):
    # a split download: timestamps and poses for all 40 frames, files only for annotated blocks
    present = list(range(4, 10)) + list(range(23, 30)) + [35]
    make_coda(tmp_path, frames=40, present=present)
    seq = CodaSequence(tmp_path, 0, frame_stride=2)
    assert seq.info.frame_indices == (4, 6, 8, 23, 25, 27, 29, 35)
    assert "files: 14 of 40 frames have a 3d_comp sweep (split-style subset)" in seq.info.selection
    frame = seq.frame(3)
    assert frame.index == 23
    assert frame.stamp_ns == round((1.6e9 + 2.3) * 1e9)  # matched to timestamps by number
    np.testing.assert_allclose(frame.T_world_from_lidar[:3, 3], [2.3, 0, 0])
    assert [f.index for f in seq.frames()] == list(seq.info.frame_indices)  # every frame reads
    # the metadata lists select the same way (here: only the frames of ObjectTracking)
    meta = {
        "ObjectTracking": {
            "training": [f"3d_bbox/os1/0/3d_bbox_os1_0_{f}.json" for f in (4, 5, 35)]
        }
    }
    make_coda(tmp_path / "m", frames=40, present=present, metadata=meta)
    by_meta = CodaSequence(tmp_path / "m", 0, frame_stride=2, frames="metadata")
    assert by_meta.info.frame_indices == (4, 35) and by_meta.info.selection.startswith(
        "metadata: 3"
    )


def test_stride_keeps_a_frame_every_k_raw_frames():
    assert stride_frames(range(10), 2) == (0, 2, 4, 6, 8)
    assert stride_frames([0, 1, 2, 5, 6, 7, 8], 2) == (0, 2, 5, 7)
    assert stride_frames([3, 1, 2], 1) == (1, 2, 3)


def test_frames_beyond_the_timestamps_are_an_error(tmp_path):
    make_coda(tmp_path, frames=4)
    (tmp_path / "3d_comp/os1/0/3d_comp_os1_0_0.bin").rename(
        tmp_path / "3d_comp/os1/0/3d_comp_os1_0_9.bin"
    )
    with pytest.raises(
        CodaFormatError, match=r"3d_comp_os1_0_9\.bin \(frame 9\): frame number beyond the 4 lines"
    ):
        CodaSequence(tmp_path, 0)


def _devkit_map(cv2, K, D, R, P, size=(1224, 1024)):
    return cv2.initUndistortRectifyMap(K, D, R, P, size, cv2.CV_32FC1)


def _bilinear(m, u, v):
    u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
    a, b = u - u0, v - v0
    return (
        (1 - a) * (1 - b) * m[v0, u0]
        + a * (1 - b) * m[v0, u0 + 1]
        + (1 - a) * b * m[v0 + 1, u0]
        + a * b * m[v0 + 1, u0 + 1]
    )


def _project(K, T, pts):
    pc = pts @ T[:3, :3].T + T[:3, 3]
    uv = pc[:, :2] / pc[:, 2:3] @ K[:2, :2].T + K[:2, 2]
    return uv, pc[:, 2]


def test_2d_rect_projection_is_exact(tmp_path):
    # Regression (issue 18): 2d_rect images are made with initUndistortRectifyMap(K, D, R, P); the
    # reader projected with K and the raw extrinsic (~11 px off on CODa's calibration). Check the
    # exposed pinhole against OpenCV's own rectification map: the rectified pixel of a LiDAR point
    # must sample the raw (distorted) pixel where the raw camera sees that point.
    cv2 = pytest.importorskip("cv2")
    make_coda(tmp_path, frames=1)
    seq = CodaSequence(tmp_path, 0, frame_stride=1)
    st = stereo_calibration()
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(3, 25, 4000), rng.uniform(-8, 8, 4000), rng.uniform(-1.5, 2.5, 4000)]
    for name in ("cam0", "cam1"):
        K_raw, D, R, P, T_raw = st[name]
        cam = seq.info.calibration.cameras[name]
        assert cam.rectified and not np.allclose(cam.raw.R_rect, np.eye(3))
        np.testing.assert_allclose(cam.K, P[:, :3])
        mapx, mapy = _devkit_map(cv2, K_raw, D, R, P)
        uv, z = _project(cam.K, cam.T_cam_from_lidar, pts)
        ok = (z > 1) & (uv[:, 0] > 10) & (uv[:, 0] < 1200) & (uv[:, 1] > 10) & (uv[:, 1] < 1000)
        raw_uv, _ = cv2.projectPoints(
            pts[ok], cv2.Rodrigues(T_raw[:3, :3])[0], T_raw[:3, 3], K_raw, D
        )
        raw_uv = raw_uv.reshape(-1, 2)
        err = np.hypot(
            _bilinear(mapx, *uv[ok].T) - raw_uv[:, 0], _bilinear(mapy, *uv[ok].T) - raw_uv[:, 1]
        )
        assert ok.sum() > 500 and np.median(err) < 0.02 and err.max() < 0.2, (
            name,
            np.median(err),
            err.max(),
        )
        # the old projection (camera_matrix, raw extrinsic) is far off on these rectified images
        old_uv, _ = _project(K_raw, T_raw, pts[ok])
        assert np.median(np.hypot(*(old_uv - uv[ok]).T)) > 5.0


def test_stereo_rows_agree_and_cam1_comes_from_cam0_to_cam1(tmp_path):
    # calib_cam0_to_cam1.yaml in CODa's documented {R, T} form; the fixture has no
    # calib_os1_to_cam1.yaml, so cam1's extrinsic is T_cam1_from_cam0 @ T_cam0_from_os1.
    make_coda(tmp_path, frames=1)
    calib = CodaSequence(tmp_path, 0).info.calibration
    st = stereo_calibration()
    np.testing.assert_allclose(calib.T_cam1_from_cam0, st["T01"], atol=1e-12)
    np.testing.assert_allclose(
        calib.cameras["cam1"].raw.T_cam_from_lidar, st["cam1"][4], atol=1e-12
    )
    pts = np.c_[np.linspace(3, 30, 50), np.linspace(-4, 4, 50), np.linspace(-1, 2, 50)]
    v0 = _project(calib.cameras["cam0"].K, calib.cameras["cam0"].T_cam_from_lidar, pts)[0][:, 1]
    v1 = _project(calib.cameras["cam1"].K, calib.cameras["cam1"].T_cam_from_lidar, pts)[0][:, 1]
    assert np.abs(v0 - v1).max() < 1e-6  # rectified: a point sits on the same row in both images
    # an explicit os1 -> cam1 file wins over the derived one
    path = tmp_path / "calibrations/0/calib_os1_to_cam1.yaml"
    path.write_text(
        yaml.safe_dump(
            {"extrinsic_matrix": {"rows": 4, "cols": 4, "data": np.eye(4).reshape(-1).tolist()}}
        )
    )
    np.testing.assert_allclose(
        CodaSequence(tmp_path, 0).info.calibration.cameras["cam1"].raw.T_cam_from_lidar, np.eye(4)
    )


def test_extrinsic_forms(tmp_path):
    rt = tmp_path / "rt.yaml"
    rt.write_text(
        yaml.safe_dump(
            {
                "extrinsic_matrix": {
                    "R": {"rows": 3, "cols": 3, "data": np.eye(3).ravel().tolist()},
                    "T": [0.1, 0.2, 0.3],
                }
            }
        )
    )
    T, P = read_extrinsic(rt)
    np.testing.assert_allclose(T[:3, 3], [0.1, 0.2, 0.3])
    assert P is None
    full = tmp_path / "full.yaml"
    full.write_text(
        yaml.safe_dump(
            {
                "extrinsic_matrix": {
                    "rows": 4,
                    "cols": 4,
                    "data": T_CAM0_FROM_OS1.ravel().tolist(),
                },
                "projection_matrix": {"rows": 3, "cols": 4, "data": list(range(12))},
            }
        )
    )
    T, P = read_extrinsic(full)
    assert P.shape == (3, 4) and T[0, 3] == 0.03
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"extrinsic_matrix": {"R": {"data": [1.0] * 9}, "T": [0, 0, 0]}}))
    with pytest.raises(
        CodaFormatError, match=r"bad\.yaml: extrinsic_matrix rotation is not orthonormal"
    ):
        read_extrinsic(bad)


def test_2d_raw_uses_the_raw_camera_with_a_warning(tmp_path):
    make_coda(tmp_path, frames=1)
    for cam in ("cam0", "cam1"):
        d = tmp_path / "2d_raw" / cam / "0"
        d.mkdir(parents=True)
        (d / f"2d_raw_{cam}_0_0.png").write_bytes(b"x")
    seq = CodaSequence(tmp_path, 0, frame_stride=1, image_source="2d_raw")
    cam0 = seq.info.calibration.cam0
    assert not cam0.rectified and cam0.K[0, 0] == pytest.approx(730.271578753826)
    np.testing.assert_allclose(cam0.T_cam_from_lidar, stereo_calibration()["cam0"][4])
    assert any("2d_raw images are distorted" in w for w in seq.info.warnings)
    assert seq.frame(0).image_paths["cam0"].parent.parent.parent.name == "2d_raw"
    with pytest.raises(CodaFrameError, match="image is missing"):  # no fallback to the other source
        (tmp_path / "2d_rect/cam0/0/2d_rect_cam0_0_0.jpg").unlink()
        CodaSequence(tmp_path, 0, frame_stride=1).frame(0)


@pytest.mark.parametrize(
    "config, meta, expected",
    [
        (None, {"lighting": "dark"}, ("night", "metadata")),
        (None, {"lighting": "normal"}, ("day", "metadata")),
        (None, {}, ("day", "default")),
        ("night", {"lighting": "normal"}, ("night", "config")),
        ("day", {"lighting": "dark"}, ("day", "config")),
    ],
)
def test_day_night_from_config_then_metadata(tmp_path, config, meta, expected):
    make_coda(tmp_path, frames=1)
    (tmp_path / "metadata/0.json").write_text(json.dumps(meta))
    info = CodaSequence(tmp_path, 0, lighting=config).info
    assert (info.lighting, info.lighting_source) == expected and info.is_night == (
        expected[0] == "night"
    )


def test_missing_base_calibration_uses_the_default_and_warns(tmp_path):
    make_coda(tmp_path, frames=1, base_file=False)
    with pytest.raises(
        CodaFormatError, match=r"calib_os1_to_base\.yaml: calibration file is missing"
    ):
        CodaSequence(tmp_path, 0)  # no default given: required
    info = CodaSequence(tmp_path, 0, lidar_height_m=0.75).info
    assert info.calibration.base_is_default
    expected = np.eye(4)
    expected[2, 3] = 0.75
    np.testing.assert_allclose(info.calibration.T_base_from_lidar, expected)
    assert len(info.warnings) == 1 and "calib_os1_to_base.yaml is missing" in info.warnings[0]
    assert "0.75 m above the ground" in info.warnings[0]


def test_bad_boxes_are_skipped_counted_and_reported(tmp_path):
    # Regression (issue 18): one zero-size box or an empty instanceId failed the whole sequence.
    boxes = [
        pedestrian_box(3),
        pedestrian_box(4, l=0.0),
        pedestrian_box(5, instanceId=""),
        {"classId": "Car"},
        pedestrian_box(6, cX=float("nan")),
        pedestrian_box(7, instanceId="Pedestrian:x"),
        pedestrian_box(8),
    ]
    make_coda(tmp_path, frames=1, boxes=boxes)
    frame = CodaSequence(tmp_path, 0, frame_stride=1).frame(0)
    assert [b.track_id for b in frame.boxes] == [3, 8]
    problems = frame.box_problems
    assert len(problems) == 5
    assert problems[0].startswith("box 1 (Pedestrian:4): non-positive size")
    assert problems[1].startswith("box 2 (Pedestrian): instanceId '' has no integer id")
    assert problems[2].startswith("box 3: malformed")
    assert problems[3].startswith("box 4 (Pedestrian:6): non-finite values")
    assert problems[4].startswith("box 5 (Pedestrian): instanceId 'Pedestrian:x'")


def test_unreadable_box_file_fails_its_frame(tmp_path):
    make_coda(tmp_path, frames=2)
    path = tmp_path / "3d_bbox/os1/0/3d_bbox_os1_0_0.json"
    path.write_text('{"3dbbox": [')
    seq = CodaSequence(tmp_path, 0, frame_stride=1)
    with pytest.raises(
        CodaFrameError, match=r"3d_bbox_os1_0_0\.json \(frame 0\): invalid JSON"
    ) as err:
        seq.frame(0)
    assert err.value.frame == 0 and err.value.path == path and err.value.sequence == "0"
    assert seq.frame(1).index == 1  # the other frames still read
    assert read_boxes(tmp_path / "3d_bbox/os1/0/3d_bbox_os1_0_1.json")[0][0].track_id == 3


def test_all_zero_intensity_is_detected(tmp_path):
    # the devkit's ego-compensation copies x y z only: 3d_comp intensity may be all zeros
    make_coda(tmp_path, frames=1, intensity_zero=True)
    frame = CodaSequence(tmp_path, 0, frame_stride=1).frame(0)
    assert not frame.intensity_present and len(frame.points_lidar) == 2000


def test_rotated_box_test_uses_yaw(tmp_path):
    make_coda(tmp_path, frames=1)
    box = CodaSequence(tmp_path, 0, frame_stride=1).frame(0).boxes[0]
    # l = 2 along the box x axis, yaw 90 deg: the long side lies along the LiDAR y axis
    pts = np.array([[5.0, 1.9, 0.0], [5.9, 1.0, 0.0]])
    inside = points_in_boxes(pts, [box.center], [box.size], [box_rotation(box.rpy)])
    assert inside.tolist() == [True, False]


def test_truncated_bin_is_a_frame_error(tmp_path):
    make_coda(tmp_path, frames=2)
    path = tmp_path / "3d_comp/os1/0/3d_comp_os1_0_0.bin"
    path.write_bytes(path.read_bytes()[:-100])
    seq = CodaSequence(tmp_path, 0, frame_stride=1)  # listing frames reads no sweep
    assert seq.info.frame_indices == (0, 1)
    with pytest.raises(
        CodaFrameError, match=r"3d_comp_os1_0_0\.bin \(frame 0\): \d+ bytes .*truncated"
    ) as err:
        seq.frame(0)
    assert (err.value.path, err.value.frame, err.value.sequence) == (path, 0, "0")
    assert seq.frame(1).index == 1


@pytest.mark.parametrize("channels", [3, 6])
def test_bad_channel_count(tmp_path, channels):
    make_coda(tmp_path, frames=1)
    path = tmp_path / "3d_comp/os1/0/3d_comp_os1_0_0.bin"
    np.zeros((POINTS, channels), np.float32).tofile(path)
    with pytest.raises(
        CodaFormatError, match=rf"{channels} channels inferred .* expected 4 .* or 5"
    ):
        read_lidar_bin(path, frame=0)


def test_nan_points(tmp_path):
    make_coda(tmp_path, frames=1)
    path = tmp_path / "3d_comp/os1/0/3d_comp_os1_0_0.bin"
    raw = np.fromfile(path, np.float32).reshape(POINTS, 5)
    raw[17, 1] = np.nan
    raw[99, 0] = np.inf
    raw.tofile(path)
    with pytest.raises(
        CodaFormatError, match=r"\(frame 0\): 2 points have NaN or inf values \(first at point 17"
    ):
        CodaSequence(tmp_path, 0, frame_stride=1).frame(0)


def test_missing_calibration_key(tmp_path):
    make_coda(tmp_path, frames=1)
    path = tmp_path / "calibrations/0/calib_cam0_intrinsics.yaml"
    data = yaml.safe_load(path.read_text())
    del data["camera_matrix"]
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(
        CodaFormatError,
        match=r"calib_cam0_intrinsics\.yaml: calibration key 'camera_matrix' is missing",
    ):
        CodaSequence(tmp_path, 0)


def test_missing_rectification_falls_back_with_a_warning(tmp_path):
    make_coda(tmp_path, frames=1)
    path = tmp_path / "calibrations/0/calib_cam0_intrinsics.yaml"
    data = yaml.safe_load(path.read_text())
    del data["rectification_matrix"], data["projection_matrix"]
    path.write_text(yaml.safe_dump(data))
    info = CodaSequence(tmp_path, 0).info
    np.testing.assert_allclose(
        info.calibration.cam0.K, np.asarray(data["camera_matrix"]["data"]).reshape(3, 3)
    )
    assert any("no rectification_matrix / projection_matrix" in w for w in info.warnings)
    assert not np.allclose(info.calibration.cam0.K, K_RECT)


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
    with pytest.raises(
        CodaFormatError, match=r"0\.txt: 3 pose lines but .*timestamps/0\.txt has 4 frames"
    ):
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
    with pytest.raises(
        CodaFormatError, match=r"timestamps are not strictly increasing: line 4 .* \(frame 3\)"
    ):
        CodaSequence(tmp_path, 0)


def test_unknown_sequence(tmp_path):
    make_coda(tmp_path, seq=2, frames=1)
    with pytest.raises(CodaFormatError, match=r"unknown sequence id '5' .*available: \['2'\]"):
        CodaSequence(tmp_path, 5)


def test_missing_image(tmp_path):
    make_coda(tmp_path, frames=1)
    (tmp_path / "2d_rect/cam1/0/2d_rect_cam1_0_0.jpg").unlink()
    with pytest.raises(
        CodaFrameError, match=r"2d_rect_cam1_0_0\.png \(frame 0\): image is missing"
    ):
        CodaSequence(tmp_path, 0, frame_stride=1).frame(0)
