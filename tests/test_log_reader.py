"""The robot-log sequence source: topics found, frames picked, calibration from /tf_static, poses
from /tf, /odom or LiDAR odometry, images matched and decoded, the index cached."""

from __future__ import annotations

import numpy as np
import pytest

from configs.sources import CameraTopics, LogSettings
from storage.sources.log.bag import LogFormatError, find_logs
from storage.sources.log.reader import LogSequence
from tests.log_fixture import (
    COLS,
    R_CAM_FROM_LIDAR,
    ROWS,
    K,
    base_from_lidar,
    expected_pose,
    make_log,
    sweep,
)


@pytest.mark.parametrize(("fmt", "poses"), [("mcap", "tf"), ("ros1", "odometry")])
def test_log_reads_as_a_sequence(tmp_path, fmt, poses):
    path = make_log(tmp_path / f"run_a.{'bag' if fmt == 'ros1' else 'mcap'}", fmt, poses=poses)
    seq = LogSequence(path, frame_stride=2, min_range_m=0.5, cache_dir=tmp_path / "cache")
    info = seq.info
    assert seq.sequence == "run_a" and info.frame_indices == (0, 2, 4) and info.num_stamps == 6
    assert seq.lidar_topic == "/ouster/points" and seq.base_frame == "base_link"
    assert [c.image_topic for c in seq.camera_streams] == [
        "/stereo/left/image_rect_color/compressed",
        "/stereo/right/image_rect_color/compressed",
    ]
    np.testing.assert_array_equal(
        info.stamps_ns, 1_700_000_000_000_000_000 + np.array([0, 2, 4]) * 100_000_000
    )
    for i, k in enumerate(info.frame_indices):
        np.testing.assert_allclose(info.poses[i], expected_pose(k), atol=1e-12)
    cal = info.calibration
    np.testing.assert_array_equal(cal.T_base_from_lidar, base_from_lidar())
    np.testing.assert_array_equal(cal.cam0.K, K)
    np.testing.assert_allclose(cal.cam0.T_cam_from_lidar[:3, :3], R_CAM_FROM_LIDAR, atol=1e-15)
    frame = seq.frame(1)
    pts, intensity, t_ns = sweep(2)
    keep = np.flatnonzero(np.linalg.norm(pts, axis=1) > 0.5)
    np.testing.assert_array_equal(frame.points_lidar, pts[keep])
    np.testing.assert_array_equal(frame.intensity, intensity[keep])
    np.testing.assert_array_equal(frame.point_time_s, (t_ns[keep] / 1e9).astype(np.float32))
    assert frame.index == 2 and frame.stamp_ns == info.stamps_ns[1]
    rgb = seq.image("cam1", 2)
    assert rgb.shape == (48, 64, 3) and abs(int(rgb[0, 0, 1]) - 101) <= 2
    seq.check_images(4)
    facts = seq.facts()
    assert ("/ouster/points", "sensor_msgs/msg/PointCloud2", 6) == facts.topics[
        [t[0] for t in facts.topics].index("/ouster/points")
    ][:3]
    assert "t in ns (relative)" in facts.lidar_layout


def test_index_is_cached_by_fingerprint(tmp_path):
    path = make_log(tmp_path / "a.mcap")
    cache = tmp_path / "cache"
    LogSequence(path, cache_dir=cache)
    files = list((cache / "log-index").iterdir())
    assert len(files) == 1
    before = files[0].stat().st_mtime_ns
    seq = LogSequence(path, cache_dir=cache)  # read from the cache, not rebuilt
    assert files[0].stat().st_mtime_ns == before and seq.info.num_frames == 3
    make_log(tmp_path / "a.mcap", frames=8)  # a changed log gets an index of its own
    assert LogSequence(path, cache_dir=cache).info.num_stamps == 8
    assert len(list((cache / "log-index").iterdir())) == 2


def test_images_beyond_the_offset_leave_their_frame_out(tmp_path):
    path = make_log(tmp_path / "a.mcap", skip_images=(2,), image_offset_ns=20_000_000)
    seq = LogSequence(path, frame_stride=2)
    # sweep 2's nearest image is sweep 1's or 3's (80 / 120 ms away): left out and reported
    assert seq.info.frame_indices == (0, 4)
    assert "1 picked sweep(s) left out: 2 (no cam0 image within 50 ms" in seq.info.warnings[0]
    seq = LogSequence(path, frame_stride=2, settings=LogSettings(max_image_offset_ms=90))
    assert seq.info.frame_indices == (0, 2, 4)


def test_lidar_odometry_when_the_log_has_no_poses(tmp_path):
    path = make_log(tmp_path / "a.mcap", poses="none")
    seq = LogSequence(path, frame_stride=1, cache_dir=tmp_path / "cache", with_poses=False)
    assert seq.pose_source == "lidar-odometry"
    np.testing.assert_array_equal(seq.info.poses, np.tile(np.eye(4), (6, 1, 1)))


def test_overrides_and_their_errors(tmp_path):
    path = make_log(tmp_path / "a.mcap")
    settings = LogSettings(
        cameras=(("cam0", CameraTopics(image_topic="/stereo/right/image_rect_color/compressed")),)
    )
    seq = LogSequence(path, settings=settings, cameras=("cam0",))
    assert seq.camera_streams[0].info_topic == "/stereo/right/camera_info"
    with pytest.raises(LogFormatError, match="lidar_topic '/velodyne_points' is not in the log"):
        LogSequence(path, settings=LogSettings(lidar_topic="/velodyne_points"))
    with pytest.raises(LogFormatError, match="is a sensor_msgs/msg/CompressedImage, expected"):
        LogSequence(
            path, settings=LogSettings(lidar_topic="/stereo/left/image_rect_color/compressed")
        )


def test_find_logs(tmp_path):
    make_log(tmp_path / "b.mcap", frames=1)
    make_log(tmp_path / "a.bag", "ros1", frames=1)
    (tmp_path / "gt").mkdir()
    (tmp_path / "notes.txt").write_text("x")
    assert list(find_logs(tmp_path)) == ["a", "b"]
    assert list(find_logs(tmp_path / "b.mcap")) == ["b"]
    assert ROWS * COLS == 2048


@pytest.mark.parametrize(("fmt", "compress"), [("mcap", True), ("ros1", True), ("ros2", False)])
def test_compressed_chunks_and_ros2_folders_read_the_same(tmp_path, fmt, compress):
    plain = LogSequence(make_log(tmp_path / "plain.mcap"), frame_stride=1)
    name = {"mcap": "c.mcap", "ros1": "c.bag", "ros2": "c"}[fmt]
    path = make_log(tmp_path / name, fmt, compress=compress)
    other = LogSequence(path, frame_stride=1)
    assert other.sequence == "c" and (other.index.positions is None) == (fmt == "ros2")
    assert other.info.frame_indices == plain.info.frame_indices
    for i in (0, 3, 5, 1):  # out of order: chunks are fetched again
        a, b = plain.frame(i), other.frame(i)
        np.testing.assert_array_equal(a.points_lidar, b.points_lidar)
        np.testing.assert_array_equal(a.point_time_s, b.point_time_s)
        np.testing.assert_array_equal(plain.image("cam0", i), other.image("cam0", i))
    np.testing.assert_allclose(other.info.poses, plain.info.poses, atol=1e-12)


@pytest.mark.parametrize("fmt", ["mcap", "ros1"])
def test_pointcloud2_parsed_in_place_as_rosbags_deserialises_it(tmp_path, fmt):
    from storage.sources.log.positions import pointcloud2_of

    seq = LogSequence(make_log(tmp_path / f"a.{'bag' if fmt == 'ros1' else 'mcap'}", fmt))
    raw = seq._raw(seq.lidar_topic, 2)
    mine = pointcloud2_of(raw, seq.log.ros1)
    ref = seq.log.deserialize(bytes(raw), "sensor_msgs/msg/PointCloud2", seq.lidar_topic)
    assert mine.stamp_ns == ref.header.stamp.sec * 10**9 + ref.header.stamp.nanosec
    assert (mine.frame_id, mine.height, mine.width) == (ref.header.frame_id, ref.height, ref.width)
    assert mine.fields == [(f.name, f.offset, f.datatype, f.count) for f in ref.fields]
    assert (mine.point_step, mine.row_step) == (ref.point_step, ref.row_step)
    assert bytes(mine.data) == ref.data.tobytes()


def test_bench_logs_reads_every_sweep_of_each_log(tmp_path):
    """The benchmark's own bookkeeping (not a timing): each log read whole in a fresh process."""
    from flows.bench.logs import bench_logs, format_table

    r = bench_logs([2, 3], tmp_path)
    assert [x["sweeps"] for x in r["runs"]] == [2, 3]
    assert all(x["points"] > 0.8 * 131072 * x["sweeps"] for x in r["runs"])  # 10 % no-returns
    assert r["rss_ratio"] > 0 and "sweeps/s on one core" in format_table(r)
    assert not list(tmp_path.glob("*.mcap"))  # the logs are removed unless kept
