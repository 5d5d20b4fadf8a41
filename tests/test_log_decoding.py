"""Robot-log decoding kernels: PointCloud2 from its fields, images, rectification, poses over
time, the TF tree, trajectory error."""

from __future__ import annotations

from io import BytesIO

import numpy as np
import pytest
from PIL import Image

from storage.sources.log.images import (
    CameraInfo,
    ImageDecodeError,
    Rectifier,
    decode_compressed,
    decode_raw,
)
from storage.sources.log.pointcloud import (
    OUSTER_FIELDS,
    Field,
    PointLayoutError,
    decode_pointcloud2,
    encode_pointcloud2,
)
from tasks.metrics.trajectory import trajectory_error
from tasks.poses.interpolate import interpolate_poses, slerp
from tasks.poses.rotations import invert, matrix_to_quat_wxyz, quat_wxyz_to_matrix, transform
from tasks.poses.tf import StampedEdge, TFGap, TFTree, static_edge

ROWS, COLS = 128, 1024


def ouster_sweep(seed=0):
    """An organised OS1-128 sweep as the Ouster driver lays it out, with no-returns."""
    rng = np.random.default_rng(seed)
    n = ROWS * COLS
    pts = (rng.normal(size=(n, 3)) * 8).astype(np.float32)
    pts[rng.random(n) < 0.2] = 0.0  # no return
    cols = {
        "x": pts[:, 0],
        "y": pts[:, 1],
        "z": pts[:, 2],
        "intensity": rng.uniform(0, 255, n).astype(np.float32),
        "t": np.tile(np.arange(COLS, dtype=np.uint32) * 97_656, ROWS),  # ns since the stamp
        "reflectivity": rng.integers(0, 255, n).astype(np.uint16),
        "ring": np.repeat(np.arange(ROWS, dtype=np.uint16), COLS),
        "range": (np.linalg.norm(pts, axis=1) * 1000).astype(np.uint32),
    }
    return pts, cols


def decode(fields, data, **kw):
    kw.setdefault("height", ROWS)
    kw.setdefault("width", COLS)
    kw.setdefault("point_step", 48)
    kw.setdefault("row_step", kw["point_step"] * kw["width"])
    return decode_pointcloud2([Field(*f) for f in fields], data, **kw)


def test_ouster_layout_decodes_exactly():
    pts, cols = ouster_sweep()
    data = encode_pointcloud2(cols)
    assert len(data) == ROWS * COLS * 48
    # the driver's record: x y z float32 at 0 4 8, intensity float32 at 16, t uint32 at 20
    rec = np.frombuffer(data, np.uint8).reshape(-1, 48)[5]
    assert np.frombuffer(rec[16:20].tobytes(), "<f4")[0] == cols["intensity"][5]
    assert np.frombuffer(rec[20:24].tobytes(), "<u4")[0] == cols["t"][5]
    cloud = decode(OUSTER_FIELDS, data, min_range_m=0.0)
    keep = np.flatnonzero(np.any(pts != 0, axis=1))  # exactly the no-returns are dropped
    np.testing.assert_array_equal(cloud.index, keep)
    np.testing.assert_array_equal(cloud.points, pts[keep])
    np.testing.assert_array_equal(cloud.intensity, cols["intensity"][keep])
    np.testing.assert_array_equal(cloud.ring, keep // COLS)
    assert cloud.layout.time == "t" and cloud.layout.time_unit == "ns"
    np.testing.assert_array_equal(
        cloud.time_s, (cols["t"][keep].astype(np.float64) / 1e9).astype(np.float32)
    )
    assert 0.09 < cloud.time_s.max() < 0.1  # one 10 Hz sweep: seconds, not nanoseconds


def test_range_test_matches_the_coda_reader_bit_for_bit():
    # the decoder writes np.linalg.norm's float32 sum out as (x*x + y*y) + z*z: same bits
    pts, _ = ouster_sweep(3)
    pts *= np.random.default_rng(4).choice([1e-3, 1.0, 30.0], size=(len(pts), 1)).astype(np.float32)
    x, y, z = pts.T
    np.testing.assert_array_equal(np.sqrt(x * x + y * y + z * z), np.linalg.norm(pts, axis=1))


def test_nan_points_padding_big_endian_and_unorganised():
    fields = [("x", 4, 7, 1), ("y", 8, 7, 1), ("z", 12, 7, 1), ("intensity", 20, 8, 1)]
    n = 6
    rec = np.zeros(n, dtype=np.dtype({"names": ["x", "y", "z", "intensity"],
                                      "formats": [">f4", ">f4", ">f4", ">f8"],
                                      "offsets": [4, 8, 12, 20], "itemsize": 32}))  # fmt: skip
    rec["x"] = [1, np.nan, 3, 0, 5, np.inf]
    rec["y"], rec["z"], rec["intensity"] = 1.0, 2.0, np.arange(n)
    rows = np.zeros((1, 32 * n + 8), np.uint8)  # row padding after the points
    rows[0, : 32 * n] = np.frombuffer(rec.tobytes(), np.uint8)
    cloud = decode(
        fields, rows, height=1, width=n, point_step=32, row_step=32 * n + 8, is_bigendian=True
    )
    np.testing.assert_array_equal(cloud.index, [0, 2, 3, 4])  # NaN and inf dropped
    np.testing.assert_array_equal(cloud.points[:, 0], [1, 3, 0, 5])
    np.testing.assert_array_equal(cloud.intensity, [0, 2, 3, 4])
    assert cloud.time_s is None and cloud.layout.time is None


@pytest.mark.parametrize(
    ("dtype", "scale", "unit"),
    [("f4", 1.0, "s"), ("f8", 1e3, "ms"), ("u4", 1e6, "us"), ("u4", 1e9, "ns")],
)
def test_time_unit_is_detected_from_the_values(dtype, scale, unit):
    datatype = {"f4": 7, "f8": 8, "u4": 6}[dtype]
    size = np.dtype(dtype).itemsize
    n = 1000
    rec = np.zeros(n, dtype=np.dtype({"names": ["x", "y", "z", "time"],
                                      "formats": ["<f4"] * 3 + ["<" + dtype],
                                      "offsets": [0, 4, 8, 12], "itemsize": 12 + size}))  # fmt: skip
    rec["x"] = 5.0
    rec["time"] = np.linspace(0, 0.1, n) * scale
    fields = [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("time", 12, datatype, 1)]
    cloud = decode(fields, rec.tobytes(), height=1, width=n, point_step=12 + size)
    assert cloud.layout.time_unit == unit
    np.testing.assert_allclose(cloud.time_s[-1], 0.1, rtol=1e-5)


def test_absolute_times_become_offsets_from_the_stamp():
    # Hesai-style: a float64 "timestamp" field of absolute Unix seconds per point
    n, stamp = 100, 1_700_000_000_123_456_789
    rec = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("timestamp", "<f8")])
    rec["x"] = 3.0
    rec["timestamp"] = stamp / 1e9 + np.arange(n) * 1e-3
    fields = [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("timestamp", 12, 8, 1)]
    cloud = decode(fields, rec.tobytes(), height=1, width=n, point_step=20, stamp_ns=stamp)
    assert cloud.layout.time_absolute and cloud.layout.time_unit == "s"
    np.testing.assert_allclose(cloud.time_s, np.arange(n) * 1e-3, atol=1e-6)


@pytest.mark.parametrize(
    ("fields", "kw", "words"),
    [
        ([("x", 0, 7, 1), ("y", 4, 7, 1)], {}, "no z field"),
        ([("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 9, 1)], {}, "datatype 9"),
        ([("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 46, 7, 1)], {}, "does not fit"),
        (OUSTER_FIELDS, {"row_step": 100}, "rows overlap"),
    ],
)
def test_unknown_layouts_are_named(fields, kw, words):
    _, cols = ouster_sweep()
    with pytest.raises(PointLayoutError, match=words):
        decode(fields, encode_pointcloud2(cols), **kw)


def test_a_cut_message_is_named():
    _, cols = ouster_sweep()
    with pytest.raises(PointLayoutError, match="a cut message"):
        decode(OUSTER_FIELDS, encode_pointcloud2(cols)[:-48])


# -- images ------------------------------------------------------------------------------------
def _encoded(rgb, fmt):
    buf = BytesIO()
    Image.fromarray(rgb).save(buf, format=fmt)
    return buf.getvalue()


def test_compressed_images_decode_as_the_image_files_do():
    rgb = np.random.default_rng(0).integers(0, 255, (24, 32, 3), dtype=np.uint8)
    jpeg = _encoded(rgb, "JPEG")
    expect = np.array(Image.open(BytesIO(jpeg)).convert("RGB"))
    np.testing.assert_array_equal(decode_compressed("rgb8; jpeg compressed bgr8", jpeg), expect)
    np.testing.assert_array_equal(decode_compressed("png", _encoded(rgb, "PNG")), rgb)
    with pytest.raises(ImageDecodeError, match="compressed depth"):
        decode_compressed("16UC1; compressedDepth", jpeg)
    with pytest.raises(ImageDecodeError, match="cannot be decoded"):
        decode_compressed("jpeg", jpeg[: len(jpeg) // 3])


def test_raw_encodings():
    rgb = np.random.default_rng(1).integers(0, 255, (4, 5, 3), dtype=np.uint8)
    pad = lambda a: np.pad(a.reshape(4, -1), ((0, 0), (0, 3))).tobytes()  # noqa: E731
    np.testing.assert_array_equal(decode_raw("rgb8", 4, 5, 18, pad(rgb)), rgb)
    np.testing.assert_array_equal(decode_raw("bgr8", 4, 5, 18, pad(rgb[:, :, ::-1])), rgb)
    gray = rgb[:, :, 0]
    np.testing.assert_array_equal(decode_raw("mono8", 4, 5, 8, pad(gray))[:, :, 2], gray)
    mono16 = (gray.astype(np.uint16) << 8).astype(">u2")
    np.testing.assert_array_equal(
        decode_raw("mono16", 4, 5, 10, mono16.tobytes(), bigendian=True)[:, :, 1], gray
    )
    bayer = np.zeros((8, 8), np.uint8)
    bayer[0::2, 0::2], bayer[0::2, 1::2], bayer[1::2, 0::2], bayer[1::2, 1::2] = 200, 100, 100, 30
    np.testing.assert_array_equal(decode_raw("bayer_rggb8", 8, 8, 8, bayer)[3, 3], [200, 100, 30])
    with pytest.raises(ImageDecodeError, match="'yuv422' is not supported"):
        decode_raw("yuv422", 4, 5, 10, bytes(40))
    with pytest.raises(ImageDecodeError, match="a cut message"):
        decode_raw("rgb8", 4, 5, 15, bytes(59))


def test_rectifier_undoes_distortion_and_rectification():
    import cv2

    w, h = 160, 120
    K = np.array([[100.0, 0, 79.5], [0, 100.0, 59.5], [0, 0, 1]])
    D = np.array([-0.25, 0.08, 0.001, -0.002, 0.0])
    R = cv2.Rodrigues(np.array([0.01, -0.02, 0.015]))[0]
    P = np.c_[np.array([[90.0, 0, 80], [0, 90.0, 60], [0, 0, 1]]), np.zeros(3)]
    info = CameraInfo(w, h, K, D, R, P, "plumb_bob", "cam")
    assert info.needs_rectifying() and info.check() is None
    # a smooth rectified scene, distorted into the raw image by projecting its pixels
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    scene = lambda uu, vv: 128 + 60 * np.sin(uu / 9.0) * np.cos(vv / 7.0)  # noqa: E731
    rays = np.linalg.inv(K) @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    und = cv2.undistortPoints(
        np.stack([u.ravel(), v.ravel()], 1)[:, None, :], K, D, R=R, P=P[:, :3]
    ).reshape(-1, 2)
    raw = np.clip(scene(und[:, 0], und[:, 1]).reshape(h, w), 0, 255).astype(np.uint8)
    del rays
    rect = Rectifier(info)(np.repeat(raw[:, :, None], 3, axis=2))[:, :, 0].astype(float)
    truth = scene(u, v)
    inner = (slice(20, h - 20), slice(20, w - 20))
    assert np.abs(rect[inner] - truth[inner]).mean() < 2.0  # grey levels of 0..255


def test_camera_info_problems_are_named():
    K = np.array([[100.0, 0, 50], [0, 100, 40], [0, 0, 1]])
    ok = CameraInfo(100, 80, K, np.zeros(5), np.eye(3), np.c_[K, np.zeros(3)], "plumb_bob", "c")
    assert ok.check() is None and not ok.needs_rectifying()
    bad = CameraInfo(0, 0, K, np.zeros(5), np.eye(3), np.c_[K, np.zeros(3)], "plumb_bob", "c")
    assert "image size 0 x 0" in bad.check()
    odd = CameraInfo(100, 80, K, np.ones(5), np.eye(3), np.c_[K, np.zeros(3)], "kannala", "c")
    assert "distortion_model 'kannala'" in odd.check()


# -- poses -------------------------------------------------------------------------------------
def _rot(axis, angle):
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.asarray(axis, float) * angle).as_matrix()


def test_quaternion_round_trip_and_inverse():
    for k in range(20):
        R = _rot(np.random.default_rng(k).normal(size=3), 0.3 * k)
        q = matrix_to_quat_wxyz(R)
        assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        np.testing.assert_allclose(quat_wxyz_to_matrix(q), R, atol=1e-12)
    T = transform(matrix_to_quat_wxyz(_rot([0, 0, 1], 0.7)), [1.0, 2.0, 3.0])
    np.testing.assert_allclose(invert(T) @ T, np.eye(4), atol=1e-12)


def test_interpolation_is_exact_at_samples_and_slerps_between():
    stamps = np.array([0, 100, 200], np.int64)
    t = np.array([[0, 0, 0], [1, 0, 0], [1, 2, 0]], float)
    q = np.array([matrix_to_quat_wxyz(_rot([0, 0, 1], a)) for a in (0.0, 0.4, 1.2)])
    poses, valid = interpolate_poses(stamps, t, q, np.array([100, 150, 25, -1, 201]))
    assert valid.tolist() == [True, True, True, False, False]
    np.testing.assert_array_equal(poses[0, :3, :3], quat_wxyz_to_matrix(q[1]))  # to the bit
    np.testing.assert_allclose(poses[1, :3, 3], [1, 1, 0])
    np.testing.assert_allclose(poses[1, :3, :3], _rot([0, 0, 1], 0.8), atol=1e-12)
    np.testing.assert_allclose(poses[2, :3, :3], _rot([0, 0, 1], 0.1), atol=1e-12)
    _, valid = interpolate_poses(stamps, t, q, np.array([150]), max_gap_ns=50)
    assert not valid[0]  # the samples around it are 100 ns apart
    # the shorter arc: q and -q are one rotation
    mid = slerp(q[1:2], -q[2:3], np.array([0.5]))
    np.testing.assert_allclose(quat_wxyz_to_matrix(mid[0]), _rot([0, 0, 1], 0.8), atol=1e-12)


def test_tf_tree_chains_static_and_stamped_edges():
    T_base_lidar = transform(matrix_to_quat_wxyz(_rot([0, 0, 1], 0.1)), [0.1, 0.0, 0.9])
    T_lidar_cam = transform(matrix_to_quat_wxyz(_rot([1, 0, 0], -np.pi / 2)), [0.08, 0.06, -0.1])
    static = {
        "os_sensor": static_edge("base_link", T_base_lidar[:3, 3], matrix_to_quat_wxyz(T_base_lidar[:3, :3])),
        "cam": static_edge("os_sensor", T_lidar_cam[:3, 3], matrix_to_quat_wxyz(T_lidar_cam[:3, :3])),
    }  # fmt: skip
    moving = StampedEdge(
        "map",
        np.array([0, 1000], np.int64),
        np.array([[0.0, 0, 0], [2.0, 0, 0]]),
        np.array([[1.0, 0, 0, 0], [1.0, 0, 0, 0]]),
    )
    tree = TFTree(static, {"base_link": moving})
    np.testing.assert_allclose(tree.lookup("cam", "os_sensor"), invert(T_lidar_cam), atol=1e-12)
    np.testing.assert_allclose(
        tree.lookup("base_link", "cam"), T_base_lidar @ T_lidar_cam, atol=1e-12
    )
    poses = tree.lookup("map", "os_sensor", np.array([500]))
    np.testing.assert_allclose(poses[0, :3, 3], T_base_lidar[:3, 3] + [1, 0, 0], atol=1e-12)
    with pytest.raises(TFGap, match="stamped"):
        tree.lookup("map", "os_sensor")
    with pytest.raises(TFGap, match="no value at stamp 2000"):
        tree.lookup("map", "os_sensor", np.array([2000]))
    with pytest.raises(TFGap, match="no common frame"):
        tree.lookup("imu", "cam")


def test_trajectory_error_of_a_shifted_drifting_path():
    n = 50
    gt = np.tile(np.eye(4), (n, 1, 1))
    gt[:, 0, 3] = np.linspace(0, 10, n)
    W = np.eye(4)  # the estimate lives in another world frame: the alignment removes it
    W[:3, :3], W[:3, 3] = _rot([0, 0, 1], 0.3), [5, -2, 0]
    est = W @ gt
    err = trajectory_error(est, gt)
    assert (
        err.ate_rmse_m < 1e-9 and err.final_drift_pct < 1e-9 and err.length_m == pytest.approx(10)
    )
    est = W @ gt
    drift = gt.copy()
    drift[:, 1, 3] += 0.5 * np.linspace(0, 1, n) ** 2  # curving off: 0.5 m over 10 m
    est = W @ drift
    err = trajectory_error(est, gt)
    # a straight-line drift would be absorbed by the alignment's rotation; a curve is not
    assert 0.01 < err.ate_rmse_m < 0.25 and err.final_drift_pct == pytest.approx(5.0, rel=0.01)


def _room_scan(rng, T_world_from_lidar, n=20_000):
    """Points on a 30 x 20 m room's floor and walls and on four pillars, resampled per scan,
    within 25 m of the sensor, in the LiDAR frame."""
    m = n // 6
    u = lambda lo, hi: rng.uniform(lo, hi, m)  # noqa: E731
    parts = [np.c_[u(-10, 20), u(-10, 10), np.zeros(m)]]  # floor
    parts += [np.c_[np.full(m, x), u(-10, 10), u(0, 3)] for x in (-10.0, 20.0)]
    parts += [np.c_[u(-10, 20), np.full(m, y), u(0, 3)] for y in (-10.0, 10.0)]
    for cx, cy in ((2, 4), (8, -5), (14, 3), (5, -1)):
        a = u(0, 2 * np.pi)
        parts.append(np.c_[cx + 0.4 * np.cos(a), cy + 0.4 * np.sin(a), u(0, 3)])
    world = np.concatenate(parts) + rng.normal(0, 0.01, (len(parts) * m, 3))
    local = (invert(T_world_from_lidar) @ np.c_[world, np.ones(len(world))].T).T[:, :3]
    return local[np.linalg.norm(local, axis=1) < 25].astype(np.float32)


def test_lidar_odometry_follows_a_known_drive():
    from tasks.poses.odometry import OdometrySettings, lidar_odometry

    rng = np.random.default_rng(0)
    gt = []
    for k in range(20):  # 1 m/s at 10 Hz, turning slowly
        T = np.eye(4)
        T[:3, :3] = _rot([0, 0, 1], 0.02 * k)
        T[:3, 3] = [0.1 * k, 0.02 * k, 1.0]
        gt.append(T)
    gt = np.stack(gt)
    settings = OdometrySettings(scan_max_range_m=30.0, deskew=False)
    est = lidar_odometry([(_room_scan(rng, T), None) for T in gt], settings)
    err = trajectory_error(est, np.linalg.inv(gt[0]) @ gt)
    np.testing.assert_array_equal(est[0], np.eye(4))
    assert err.ate_rmse_m < 0.03 and err.rotation_rmse_deg < 0.5, err
