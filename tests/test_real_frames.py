"""Real recordings (tests/data/real/, provenance and licence in each log's PROVENANCE.md): the
logs decode (frames, sizes, calibration), the recorded calibration projects the sweep onto the
image (a measured check against perturbed extrinsics), check-data's figures, and end to end (issue
38): the path that reads no ground truth exits 0 and no LiDAR return is exported free."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from configs.schema import load_config
from flows.commands.check_data import check_data
from storage.sources.log.reader import LogSequence

REAL = Path(__file__).parent / "data" / "real"
LOGS = ("sc_street", "sc_road", "acfr_lab")
#: the run that reads no simulator truth, until the default config is that path (issue 38 item 1)
NO_TRUTH = {
    "detect.image_provider": "models",
    "detect.models.semantic.kind": "none",
    "fit.init_provider": "lidar-keypoints",
}
#: per log: LiDAR topic, points in the source .pcd, the raw image size, the LiDAR's height above
#: the base (the ground plane convert.py found), fx of the rectified pinhole (the source's K; for
#: the fisheye, OpenCV's balance-1 K'), the distortion model
FACTS = {
    "sc_street": ("/hesai/pandar", 85_546, (1920, 1200), 2.066, 2117.31, "plumb_bob"),
    "sc_road": ("/hesai/pandar", 101_340, (1920, 1200), 1.981, 2152.8, "plumb_bob"),
    "acfr_lab": ("/velodyne_points", 24_163, (1920, 1208), 1.604, 810.987, "equidistant"),
}


def _log(name: str) -> Path:
    return REAL / name / f"{name}.mcap"


def _open(name: str, tmp_path: Path) -> LogSequence:
    return LogSequence(
        _log(name), frame_stride=1, cameras=("cam0",), cache_dir=tmp_path / "cache", with_poses=False
    )  # fmt: skip


@pytest.mark.parametrize("name", LOGS)
def test_real_log_decodes(name, tmp_path):
    topic, n_points, (w, h), height_m, fx, model = FACTS[name]
    seq = _open(name, tmp_path)
    info = seq.info
    assert info.frame_indices == (0,) and seq.lidar_topic == topic
    assert seq.base_frame == "base_link"
    frame = seq.frame(0)
    assert frame.points_lidar.shape == (n_points, 3) and frame.points_lidar.dtype == np.float32
    assert frame.intensity.shape == (n_points,) and frame.intensity_present
    assert frame.point_time_s is None  # the converted sweeps carry no per-point time
    cal = info.calibration
    cam = cal.cameras["cam0"]
    assert (cam.width, cam.height) == (w, h)
    assert (
        cam.K[0, 0] == pytest.approx(fx) and cam.raw.distortion[0] < 0
    )  # barrel distortion recorded
    np.testing.assert_allclose(cal.T_base_from_lidar[2, 3], height_m, atol=1e-3)
    # the optical axis looks along the LiDAR's x (forward): measured 0.8, 2.0, 8.3 degrees off
    forward = cam.T_cam_from_lidar[:3, :3].T @ [0.0, 0.0, 1.0]
    assert forward[0] > np.cos(np.radians(10.0))
    rgb = seq.image("cam0", 0)  # raw JPEG undistorted into the pinhole K
    assert rgb.shape == (h, w, 3) and rgb.dtype == np.uint8 and 60 < rgb.mean() < 200


def _rotate(T: np.ndarray, axis: int, deg: float) -> np.ndarray:
    """T_cam_from_lidar turned by ``deg`` about the camera's ``axis`` (0 x: pitch, 1 y: yaw)."""
    a = np.radians(deg)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(4)
    R[i, i] = R[j, j] = np.cos(a)
    R[i, j], R[j, i] = -np.sin(a), np.sin(a)
    return R @ T


def _share_inside(points: np.ndarray, K, T, box_px) -> float:
    """Share of ``points`` (N, 3) LiDAR frame projecting into the pixel box (u0, v0, u1, v1)."""
    pc = points.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    front = pc[:, 2] > 0.5
    uv = pc[front, :2] / pc[front, 2:] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    u0, v0, u1, v1 = box_px
    inside = (uv[:, 0] >= u0) & (uv[:, 0] < u1) & (uv[:, 1] >= v0) & (uv[:, 1] < v1)
    return float(inside.sum() / len(points))


#: sc_road's two vehicles ahead, located by hand once in each modality separately: a box in the
#: sweep (LiDAR frame, m: x0, x1, y0, y1, z0, z1) and the vehicle's box in the rectified image
#: (px: u0, v0, u1, v1), drawn on the picture without the points
VEHICLES = {
    "truck": ((28.8, 36.0, 2.9, 6.0, -1.7, 1.6), (580, 530, 810, 735)),
    "car": ((21.3, 24.5, -4.8, -2.2, -1.75, 0.4), (1205, 625, 1420, 785)),
}


@pytest.mark.parametrize("vehicle", VEHICLES)
def test_recorded_calibration_puts_a_vehicle_on_its_pixels(vehicle, tmp_path):
    """The recorded extrinsic puts >= 75 % of a vehicle's returns on its pixels; turned by 3
    degrees in pitch or yaw, or inverted (the transform's direction mistaken), at least 20 points
    fewer. Measured: truck (811 returns) 88.5 %, pitch -3 / +3 34.6 / 53.8 %, yaw -3 / +3
    48.3 / 41.9 %, inverted 0 %; car (463) 81.0 %, 13.8 / 47.5 %, 42.5 / 32.0 %, 0 %."""
    seq = _open("sc_road", tmp_path)
    cam = seq.info.calibration.cameras["cam0"]
    p = seq.frame(0).points_lidar
    (x0, x1, y0, y1, z0, z1), box_px = VEHICLES[vehicle]
    sel = (p[:, 0] > x0) & (p[:, 0] < x1) & (p[:, 1] > y0) & (p[:, 1] < y1)
    sel &= (p[:, 2] > z0) & (p[:, 2] < z1)
    pts = p[sel]
    assert len(pts) > 300  # a vehicle, not a few stray returns
    T = cam.T_cam_from_lidar
    recorded = _share_inside(pts, cam.K, T, box_px)
    assert recorded >= 0.75, recorded
    for axis in (0, 1):
        for deg in (-3.0, 3.0):
            wrong = _share_inside(pts, cam.K, _rotate(T, axis, deg), box_px)
            assert wrong <= recorded - 0.2, (axis, deg, wrong, recorded)
    assert _share_inside(pts, cam.K, np.linalg.inv(T), box_px) <= recorded - 0.2


#: acfr_lab's chessboard (the source's own segmentation of it, pose2_target.pcd, lies in this
#: box) and its four corners in the rectified image (px), read off the picture
BOARD_BOX_M = (1.55, 1.95, -0.15, 0.95, -0.55, 0.55)
BOARD_CORNERS_PX = ((600, 480), (840, 180), (1090, 390), (796, 676))


def test_recorded_calibration_puts_the_chessboard_on_its_pixels(tmp_path):
    """The chessboard's returns, projected with the recorded calibration (fisheye, rectified),
    centre within 25 px of the board's centre in the image; 3 degrees of pitch or yaw or 0.1 m
    sideways / up moves them >= 10 px further. Measured: 17.8 px; perturbed 31.0-64.8 px."""
    seq = _open("acfr_lab", tmp_path)
    cam = seq.info.calibration.cameras["cam0"]
    p = seq.frame(0).points_lidar
    x0, x1, y0, y1, z0, z1 = BOARD_BOX_M
    sel = (p[:, 0] > x0) & (p[:, 0] < x1) & (p[:, 1] > y0) & (p[:, 1] < y1)
    pts = p[sel & (p[:, 2] > z0) & (p[:, 2] < z1)].astype(np.float64)
    assert len(pts) > 800
    centre = np.mean(BOARD_CORNERS_PX, axis=0)

    def offset(T):
        pc = pts @ T[:3, :3].T + T[:3, 3]
        assert (pc[:, 2] > 0.5).all()
        uv = pc[:, :2] / pc[:, 2:] * [cam.K[0, 0], cam.K[1, 1]] + [cam.K[0, 2], cam.K[1, 2]]
        return float(np.linalg.norm(uv.mean(axis=0) - centre))

    T = cam.T_cam_from_lidar
    recorded = offset(T)
    assert recorded <= 25.0, recorded
    wrong = [_rotate(T, axis, deg) for axis in (0, 1) for deg in (-3.0, 3.0)]
    for axis in (0, 1):  # camera x (sideways) and y (up / down)
        shifted = T.copy()
        shifted[axis, 3] += 0.1
        wrong.append(shifted)
    for W in wrong:
        assert offset(W) >= recorded + 10.0, (offset(W), recorded)


@pytest.mark.parametrize("name", LOGS)
def test_check_data_on_real_logs(name):
    code, text = check_data(load_config(overrides={"dataset.root": str(REAL / name)}))
    assert code == 0, text
    assert "1 log(s): ready to run" in text and "BLOCKING" not in text
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("---"))
    row = lines[start + 1]
    assert row.split()[0] == name
    w, h = FACTS[name][2]
    assert f"cam0 {w}x{h} raw->rect" in row and "base_link" in row and "lidar-odometry" in row
    # figures: the share of the sweep in the image, the ground height under the base
    share = float(row.split("in img ")[1].split("%")[0]) / 100
    ground = float(row.split("ground ")[1].split("m")[0])
    assert 0.08 <= share <= 0.3, row  # measured: 12 %, 12 %, 23 %
    assert abs(ground) <= 0.05, row


# -- end to end (issue 38): these pass once its fixes are merged ---------------------------------
def free_returns_share(out: Path, log: Path, min_cluster: int = 5) -> dict[str, float]:
    """Per exported frame: the share of the grid's return-holding voxels that the Occ3D export
    calls free with no occupied voxel among their 26 neighbours, counted in 26-connected clusters
    of >= ``min_cluster`` such voxels (the issue's "no return is free" figure)."""
    from scipy import ndimage

    occ3d = out / "exports" / "occ3d"
    meta = json.loads((occ3d / "occ3d_metadata.json").read_text())
    grid, free = meta["grid"], meta["free_class"]
    lo, size = np.asarray(grid["range_min"]), float(grid["voxel_size_m"])
    shape = np.asarray(grid["shape"])
    seq = LogSequence(log, frame_stride=1, cameras=("cam0",), with_poses=False)
    T = seq.info.calibration.T_base_from_lidar
    ann = json.loads((occ3d / "annotations.json").read_text())["scene_infos"]
    out_shares = {}
    for scene, samples in ann.items():
        if scene != log.stem and not scene.endswith(f"-{log.stem}"):  # another log's scene
            continue
        for k, (token, sample) in enumerate(
            sorted(samples.items(), key=lambda s: s[1]["timestamp"])
        ):
            labels = np.load(occ3d / sample["gt_path"])["semantics"]
            p = seq.frame(k).points_lidar.astype(np.float64)
            idx = np.floor((p @ T[:3, :3].T + T[:3, 3] - lo) / size).astype(int)
            idx = idx[((idx >= 0) & (idx < shape)).all(axis=1)]
            hit = np.zeros(labels.shape, bool)
            hit[tuple(idx.T)] = True
            occupied = labels != free
            near = ndimage.binary_dilation(occupied, np.ones((3, 3, 3), bool))
            lie = hit & (labels == free) & ~near
            lab, n = ndimage.label(lie, np.ones((3, 3, 3), bool))
            sizes = np.bincount(lab.ravel())[1:]
            big = np.isin(lab, 1 + np.flatnonzero(sizes >= min_cluster))
            out_shares[f"{scene}/{token}"] = float(big.sum() / max(1, hit.sum()))
    return out_shares


def _rebuild(name: str, out: Path, settings: dict) -> int:
    from flows.cli import main

    sets = [a for k, v in settings.items() for a in ("--set", f"{k}={v}")]
    return main(["rebuild", "--data", str(REAL / name), "--out", str(out), *sets])


@pytest.fixture(scope="module")
def no_truth_runs(tmp_path_factory):
    """Each real log rebuilt with the CLI as a user would, with the no-truth settings; the exit
    code and the output folder per log."""
    runs = {}
    for name in LOGS:
        out = tmp_path_factory.mktemp(f"out-{name}")
        runs[name] = (_rebuild(name, out, NO_TRUTH), out)
    return runs


@pytest.mark.slow
def test_default_config_runs_on_a_real_log(tmp_path):
    """``rebuild`` with no config and no settings at all (issue 38 item 1). Before issue 38: exit 1, FramesFailed '... no ground truth for sequence acfr_lab frame 0'."""
    assert _rebuild("acfr_lab", tmp_path / "out", {}) == 0


@pytest.mark.slow
@pytest.mark.parametrize("name", LOGS)
def test_default_path_runs_on_a_real_log(no_truth_runs, name):
    """Before issue 38: exit 0 for both logs (with NO_TRUTH; with no config
    at all: exit 1, 'no ground truth for sequence ... frame 0')."""
    code, out = no_truth_runs[name]
    assert code == 0
    assert list((out / "exports" / "occ3d" / "gts").rglob("labels.npz"))


@pytest.mark.slow
@pytest.mark.parametrize("name", LOGS)
def test_no_return_is_exported_free(no_truth_runs, name):
    """At most 0.5 % of the return-holding voxels are free with nothing occupied beside them
    (clusters >= 5). Before issue 38 (NO_TRUTH): sc_street 100 % of 411
    return voxels, sc_road 98.3 % of 926, acfr_lab 97.3 % of 1,286: every voxel of the 0.2 m
    grid is exported free, the ground and the person included."""
    code, out = no_truth_runs[name]
    assert code == 0
    shares = free_returns_share(out, _log(name))
    assert shares and max(shares.values()) <= 0.005, shares


#: acfr_lab's standing person: the returns in this box of the base frame (m: x0, x1, y0, y1, z0,
#: z1; 348 returns, projecting onto the person's pixels u 1582-1881, v 341-760)
PERSON_BOX_BASE_M = (2.3, 2.75, -2.35, -1.75, 0.05, 2.0)


@pytest.mark.slow
@pytest.mark.xfail(
    reason="not yet: in this cluttered lab the person's returns join one 9,425-point cluster "
    "with the floor, walls and tripod (VLP-16 tilted 6.8 deg), so the LiDAR detector proposes "
    "no box on him and the image models are never run there",
    strict=False,
)
def test_the_person_in_view_is_labelled_pedestrian(no_truth_runs):
    """>= 70 % of the grid voxels holding the standing person's returns are exported pedestrian
    (issue 38: a person in plain view in a single frame gets a body). Before issue 38 (NO_TRUTH):
    0 %: 0 image detections and 25 LiDAR boxes, no track, the grid all free. After it (the
    default path, 2026-12-08): one LiDAR box, scored 0.38, on another object, 0 image
    detections, no track; 30 of the person's 36 voxels unclassified, 6 free beside them."""
    code, out = no_truth_runs["acfr_lab"]
    assert code == 0
    occ3d = out / "exports" / "occ3d"
    meta = json.loads((occ3d / "occ3d_metadata.json").read_text())
    grid = meta["grid"]
    [labels_path] = list((occ3d / "gts").rglob("labels.npz"))
    labels = np.load(labels_path)["semantics"]
    seq = LogSequence(_log("acfr_lab"), frame_stride=1, cameras=("cam0",), with_poses=False)
    T = seq.info.calibration.T_base_from_lidar
    pb = seq.frame(0).points_lidar.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    x0, x1, y0, y1, z0, z1 = PERSON_BOX_BASE_M
    sel = (pb[:, 0] > x0) & (pb[:, 0] < x1) & (pb[:, 1] > y0) & (pb[:, 1] < y1)
    person = pb[sel & (pb[:, 2] > z0) & (pb[:, 2] < z1)]
    assert len(person) > 300
    idx = np.floor((person - grid["range_min"]) / grid["voxel_size_m"]).astype(int)
    idx = np.unique(idx[((idx >= 0) & (idx < grid["shape"])).all(axis=1)], axis=0)
    assert len(idx) > 20  # the person is inside the grid
    pedestrian = meta["class_names"].index("pedestrian")
    share = float(np.mean(labels[tuple(idx.T)] == pedestrian))
    assert share >= 0.7, share
