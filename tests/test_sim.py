"""Synthetic campus sequences: determinism, CODa layout, ground-truth consistency, show."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from storage import gt as GT
from storage.sources.coda import writer as W
from tasks import conventions as C
from tasks.geometry import transform_points
from tasks.sim import GridSpec, SimOptions, Simulator
from tasks.sim import groundtruth as G
from tasks.sim.geometry import box_solid, ground_tile
from tasks.sim.sensors import LidarNoise, make_rig

SEED = 3


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> tuple[Path, Path]:
    from flows.commands.simulate import simulate

    a, b = tmp_path_factory.mktemp("simA"), tmp_path_factory.mktemp("simB")
    assert simulate(a, sequences=1, frames=2, seed=SEED, pedestrians=5, progress=False) == [0]
    simulate(b, sequences=1, frames=2, seed=SEED, pedestrians=5, progress=False)
    return a, b


@pytest.fixture(scope="module")
def clean_frame():
    """A noise-free frame (the geometry the ground truth describes), 8 people."""
    sim = Simulator(
        SimOptions(seed=11, frames=30, pedestrians=8),
        rig=make_rig(noise=LidarNoise(range_std_m=0.0, angle_std_deg=0.0)),
    )
    return sim, sim.frame(10)


def _files(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


def test_same_seed_gives_byte_identical_files(runs):
    a, b = _files(runs[0]), _files(runs[1])
    assert sorted(a) == sorted(b)
    assert [k for k in a if a[k] != b[k]] == []


def test_frame_workers_write_the_same_bytes(runs, tmp_path):
    # frames are pure functions of (options, index): two worker processes give the same files
    from flows.commands.simulate import simulate

    simulate(tmp_path, sequences=1, frames=2, seed=SEED, pedestrians=5, progress=False, workers=2)
    a, b = _files(runs[0]), _files(tmp_path)
    assert sorted(a) == sorted(b)
    assert [k for k in a if a[k] != b[k]] == []


def test_fast_mode_changes_only_the_cameras(runs, tmp_path):
    # --fast renders both cameras at half resolution; the scene, the LiDAR and the 3D ground truth
    # are the same bytes, the camera-derived fields are consistent with the smaller images
    from PIL import Image

    from flows.commands.simulate import FAST_IMAGE_SCALE, simulate
    from storage.sources.coda import CodaSequence

    simulate(tmp_path, sequences=1, frames=2, seed=SEED, pedestrians=5, progress=False, fast=True)
    slow = runs[0]
    for f in range(2):
        for rel in (
            f"3d_comp/os1/0/3d_comp_os1_0_{f}.bin",
            f"3d_semantic/os1/0/3d_semantic_os1_0_{f}.bin",
        ):
            assert (slow / rel).read_bytes() == (tmp_path / rel).read_bytes()
        a, b = GT.read_frame_gt(slow, 0, f), GT.read_frame_gt(tmp_path, 0, f)
        for name in (
            "occupancy",
            "occupancy_instance",
            "point_class",
            "point_instance",
            "vertices",
            "joints",
            "box_center",
            "box_size",
            "T_world_from_lidar",
        ):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
        assert b.cam0_semantic.shape == (512, 612) and b.cam0_instance.shape == (512, 612)
        with Image.open(tmp_path / f"2d_rect/cam1/0/2d_rect_cam1_0_{f}.jpg") as im:
            assert im.size == (612, 512)
        # the same people in view, their boxes at half the pixel coordinates (to a pixel)
        seen = ~np.isnan(a.box2d[:, 0])
        assert seen.any() and np.array_equal(seen, ~np.isnan(b.box2d[:, 0]))
        np.testing.assert_allclose(
            b.box2d[seen], (a.box2d[seen] + 0.5) * FAST_IMAGE_SCALE - 0.5, atol=1.0
        )
    cam = CodaSequence(tmp_path, 0, frame_stride=1).info.calibration.cameras["cam0"]
    full = make_rig().camera("cam0")
    assert (cam.width, cam.height) == (612, 512)
    np.testing.assert_allclose(cam.K[0, 0], full.K[0, 0] * FAST_IMAGE_SCALE)
    np.testing.assert_allclose(cam.T_cam_from_lidar, full.T_cam_from_lidar, atol=1e-9)
    meta = json.loads((tmp_path / "metadata/0.json").read_text())
    assert meta["simulation"] == "fast" and meta["image_scale"] == FAST_IMAGE_SCALE


def test_written_layout_is_coda(runs):
    root = runs[0]
    names = set(_files(root))
    for f in range(2):
        for name in (
            f"3d_comp/os1/0/3d_comp_os1_0_{f}.bin",
            f"2d_rect/cam0/0/2d_rect_cam0_0_{f}.jpg",
            f"2d_rect/cam1/0/2d_rect_cam1_0_{f}.jpg",
            f"3d_bbox/os1/0/3d_bbox_os1_0_{f}.json",
            f"3d_semantic/os1/0/3d_semantic_os1_0_{f}.bin",
            f"gt/0/gt_0_{f}.npz",
        ):
            assert name in names
        assert (root / f"3d_comp/os1/0/3d_comp_os1_0_{f}.bin").stat().st_size == 131072 * 5 * 4
        assert (root / f"3d_semantic/os1/0/3d_semantic_os1_0_{f}.bin").stat().st_size == 131072
    calib = root / "calibrations/0"
    for cam in ("cam0", "cam1"):
        intr = yaml.safe_load((calib / f"calib_{cam}_intrinsics.yaml").read_text())
        assert {
            "image_width",
            "image_height",
            "camera_matrix",
            "distortion_model",
            "distortion_coefficients",
            "rectification_matrix",
            "projection_matrix",
        } <= set(intr)
        assert (intr["image_width"], intr["image_height"]) == (1224, 1024)
        assert intr["distortion_model"] == "plumb_bob"
        assert (
            intr["distortion_coefficients"]["rows"] == 1
            and intr["distortion_coefficients"]["cols"] == 5
        )
        # CODa-faithful: a real rectification (R != I), a projection matrix of its own (P != [K | 0])
        R = np.asarray(intr["rectification_matrix"]["data"]).reshape(3, 3)
        P = np.asarray(intr["projection_matrix"]["data"]).reshape(3, 4)
        K = np.asarray(intr["camera_matrix"]["data"]).reshape(3, 3)
        assert 0.005 < np.abs(R - np.eye(3)).max() < 0.05 and np.abs(P[:, :3] - K).max() > 1.0
        assert np.any(np.asarray(intr["distortion_coefficients"]["data"]) != 0)
        ext = yaml.safe_load((calib / f"calib_os1_to_{cam}.yaml").read_text())["extrinsic_matrix"]
        assert (ext["rows"], ext["cols"], len(ext["data"])) == (4, 4, 16)
    c01 = yaml.safe_load((calib / "calib_cam0_to_cam1.yaml").read_text())["extrinsic_matrix"]
    assert set(c01) == {"R", "T"} and len(c01["T"]) == 3  # CODa's documented form
    base = yaml.safe_load((calib / "calib_os1_to_base.yaml").read_text())["extrinsic_matrix"]
    assert 0.8 <= np.asarray(base["data"]).reshape(4, 4)[2, 3] <= 1.0
    stamps = (root / "timestamps/0.txt").read_text().splitlines()
    assert stamps == ["1700000000.000000", "1700000000.100000"]
    poses = [line.split() for line in (root / "poses/dense_global/0.txt").read_text().splitlines()]
    assert len(poses) == 2 and all(len(p) == 8 for p in poses) and poses[1][0] == stamps[1]
    meta = json.loads((root / "metadata/0.json").read_text())
    assert meta["synthetic"] is True and meta["lighting"] == "day" and meta["frames"] == 2
    assert meta["sensor"] == "os1-128" and meta["crowd"] == "uncrowded" and "seed" in meta
    assert meta["ObjectTracking"]["training"] == [
        "3d_bbox/os1/0/3d_bbox_os1_0_0.json",
        "3d_bbox/os1/0/3d_bbox_os1_0_1.json",
    ]
    boxes = json.loads((root / "3d_bbox/os1/0/3d_bbox_os1_0_0.json").read_text())["3dbbox"]
    peds = [b for b in boxes if b["classId"] == "Pedestrian"]
    assert peds and all(b["instanceId"].startswith("Pedestrian:") for b in peds)
    for b in boxes:
        assert {
            "cX",
            "cY",
            "cZ",
            "l",
            "w",
            "h",
            "r",
            "p",
            "y",
            "instanceId",
            "labelAttributes",
        } <= set(b)
        assert b["labelAttributes"]["isOccluded"] in {
            "None",
            "Light",
            "Medium",
            "Heavy",
            "Full",
            "Unknown",
        }


def test_reader_recovers_the_rendering_camera(runs):
    # The images are rendered with the rectified pinhole; the files hold the raw camera, its
    # rectification and projection (as CODa's). The reader must give back the rendering camera.
    from storage.sources.coda import CodaSequence
    from tasks.sim.sensors import make_rig

    seq = CodaSequence(runs[0], 0, frame_stride=1)
    for c in make_rig().cameras:
        cam = seq.info.calibration.cameras[c.name]
        np.testing.assert_allclose(cam.K, c.K, atol=1e-9)
        np.testing.assert_allclose(cam.T_cam_from_lidar, c.T_cam_from_lidar, atol=1e-9)
        assert not np.allclose(cam.raw.T_cam_from_lidar, c.T_cam_from_lidar, atol=1e-3)
    frame = seq.frame(1)
    sweep_s = 0.1  # a unit check of the data, not a timing: one 10 Hz sweep's point times
    assert 0.9 * sweep_s < frame.point_time_s.max() < sweep_s  # the time channel is in nanoseconds
    assert frame.intensity_present and frame.box_problems == ()


def test_semantic_files_hold_coda_terrain_ids(runs):
    from tasks.metrics.coda_labels import semantic_to_classes

    root = runs[0]
    ids = np.fromfile(root / "3d_semantic/os1/0/3d_semantic_os1_0_1.bin", np.uint8)
    gt = GT.read_frame_gt(root, 0, 1)
    assert set(np.unique(ids)) <= {0, 1, 2}
    ground = (gt.point_class == C.ROAD) | (gt.point_class == C.TERRAIN)
    assert ground.sum() > 10000
    assert np.array_equal(semantic_to_classes(ids[ground]), gt.point_class[ground])
    assert np.all(ids[~ground] == 0)


def test_split_style_writes_blocks_of_frames(tmp_path, monkeypatch):
    import flows.commands.simulate as S
    from storage.sources.coda import CodaSequence

    assert S.split_style_frames(25) == [*range(10), *range(20, 25)]
    monkeypatch.setattr(S, "SPLIT_BLOCK_FRAMES", 2)  # blocks of 2 keep the test small
    S.simulate(
        tmp_path,
        sequences=1,
        frames=5,
        seed=SEED,
        pedestrians=0,
        progress=False,
        split_style=True,
        image_ext=".png",
    )
    sweeps = sorted(p.name for p in (tmp_path / "3d_comp/os1/0").iterdir())
    assert sweeps == [f"3d_comp_os1_0_{f}.bin" for f in (0, 1, 4)]
    assert len((tmp_path / "timestamps/0.txt").read_text().splitlines()) == 5
    assert len((tmp_path / "poses/dense_global/0.txt").read_text().splitlines()) == 5
    seq = CodaSequence(tmp_path, 0)
    assert seq.info.frame_indices == (0, 4) and "split-style" in seq.info.selection
    assert seq.frame(1).image_paths["cam0"].suffix == ".png"
    assert CodaSequence(tmp_path, 0, frames="metadata").info.frame_indices == (0, 4)


def test_lidar_file_matches_ground_truth_labels(runs):
    root = runs[0]
    data = W.read_lidar(root, 0, 1)
    gt = GT.read_frame_gt(root, 0, 1)
    returned = np.any(data[:, :3] != 0, axis=1)
    assert np.array_equal(returned, gt.point_class != C.UNLABELED)
    assert 0.5 < returned.mean() < 0.905  # 10 % dropout, the sky and the top rows return nothing
    assert np.all(gt.point_instance[~returned] == 0)
    seq = GT.read_sequence_gt(root, 0)
    assert seq.frames == (0, 1) and seq.grid_shape == (48, 48, 24)


#: range noise of the simulated OS1 (10 mm) times 3: a return this far in front of its surface
#: still belongs to the surface's voxel (storage/SCHEMA.md, "Voxel convention")
NOISE_TOLERANCE_M = 0.03


def _surface_voxels(occupancy, range_min, voxel_size_m, points_base, sensor_base, tol_m):
    """(N, 3) voxel index of the surface each point was returned from (its own voxel, or the one
    tol_m further along its ray when its own is free: tasks.metrics.static.surface_voxel_index)."""
    from tasks.metrics.static import surface_voxel_index

    return surface_voxel_index(occupancy, range_min, voxel_size_m, points_base, sensor_base, tol_m)


def _point_voxel_agreement(root: Path, sequence: int, frame: int) -> tuple[int, int]:
    """(agreeing, total) written LiDAR points inside the GT grid whose GT class is the class of the
    GT occupancy voxel of their surface (the noisy points: their voxel, or 3 sigma further along
    the ray where the noise threw them in front of it)."""
    seq = GT.read_sequence_gt(root, sequence)
    data = W.read_lidar(root, sequence, frame)
    gt = GT.read_frame_gt(root, sequence, frame)
    returned = np.any(data[:, :3] != 0, axis=1)
    pb = transform_points(seq.T_base_from_lidar, data[returned, :3].astype(np.float64))
    q = _surface_voxels(
        gt.occupancy,
        seq.grid_range_min,
        seq.grid_voxel_size_m,
        pb,
        seq.T_base_from_lidar[:3, 3],
        NOISE_TOLERANCE_M,
    )
    inside = np.all((q >= 0) & (q < seq.grid_shape), axis=1)
    agree = gt.occupancy[tuple(q[inside].T)] == gt.point_class[returned][inside]
    return int(agree.sum()), int(inside.sum())


@pytest.fixture(scope="module")
def three_scenes(tmp_path_factory) -> Path:
    """Three independent scenes (sequence seeds derived from SEED) of two frames, 5 people each."""
    from flows.commands.simulate import simulate

    root = tmp_path_factory.mktemp("sim3")
    simulate(root, sequences=3, frames=2, seed=SEED, pedestrians=5, progress=False)
    return root


def test_lidar_points_agree_with_their_ground_truth_voxel(three_scenes):
    # >= 99 % of the (noisy, 10 mm) points belong to a GT voxel of their class (their own voxel,
    # or the surface's voxel within 3 sigma behind them along the ray), pooled over six frames of
    # three scenes. What disagrees is physical, not a bug: a voxel holding a foot or a wheel on
    # the road is labelled by the object, and ground returns that the noise lifts above the
    # ground plane (a voxel face) land in it.
    counts = [_point_voxel_agreement(three_scenes, s, f) for s in range(3) for f in range(2)]
    agree, total = np.sum(counts, axis=0)
    assert total > 100000 and agree / total >= 0.99, counts


def test_points_fall_in_voxels_of_their_class(clean_frame):
    sim, f = clean_frame
    s = f.sweep
    ok = s.point_class != C.UNLABELED
    pb = transform_points(sim.rig.T_base_from_lidar, s.points[ok].astype(np.float64))
    # noise-free returns lie on their surfaces: one on a voxel face (the ground at z = 0) belongs
    # to the voxel behind it, a float32 rounding (1 mm) away along its ray
    q = _surface_voxels(
        f.occupancy,
        sim.grid.range_min,
        sim.grid.voxel_size_m,
        pb,
        sim.rig.T_base_from_lidar[:3, 3],
        0.001,
    )
    inside = np.all((q >= 0) & (q < sim.grid.shape), axis=1)
    assert inside.sum() > 10000
    grid_cls = f.occupancy[tuple(q[inside].T)]
    pt_cls = s.point_class[ok][inside]
    assert np.mean(grid_cls != C.FREE) > 0.999
    # Mixed voxels (a foot or a wheel on the road) keep the object's label, so ground points there
    # disagree: all points >= 98 %, points of objects >= 99.9 %.
    assert np.mean(grid_cls == pt_cls) >= 0.98
    objects = (pt_cls != C.ROAD) & (pt_cls != C.TERRAIN)
    assert np.mean(grid_cls[objects] == pt_cls[objects]) >= 0.999
    ped = pt_cls == C.PEDESTRIAN
    assert ped.sum() > 100
    inst = f.occupancy_instance[tuple(q[inside].T)]
    assert np.mean(inst[ped] == s.point_instance[ok][inside][ped]) >= 0.99


def test_unoccluded_keypoints_fall_in_the_instance_mask(clean_frame):
    _, f = clean_frame
    p = f.people
    clear = np.flatnonzero(p.visible_fraction >= 0.95)
    assert len(clear) >= 1
    mask_hits = []
    for k in clear:
        mask = f.cam0.instance == p.track_id[k]
        # 1-pixel dilation: joints of limbs seen edge-on sit on the silhouette border.
        grown = mask.copy()
        grown[1:] |= mask[:-1]
        grown[:-1] |= mask[1:]
        grown[:, 1:] |= mask[:, :-1]
        grown[:, :-1] |= mask[:, 1:]
        kp = p.keypoints[k]
        vis = kp[:, 2] == 2
        u, v = np.rint(kp[vis, 0]).astype(int), np.rint(kp[vis, 1]).astype(int)
        mask_hits.extend(grown[v, u])
    assert len(mask_hits) >= 12 and np.mean(mask_hits) >= 0.9


def test_stored_body_parameters_reproduce_vertices(clean_frame):
    sim, f = clean_frame
    p = f.people
    with torch.no_grad():
        out = sim.model(
            torch.as_tensor(p.betas),
            torch.as_tensor(p.global_orient),
            torch.as_tensor(p.body_pose),
            torch.as_tensor(p.transl),
        )
    assert np.abs(out.vertices.numpy() - p.vertices).max() < 1e-3
    assert np.abs(out.joints.numpy() - p.joints).max() < 1e-3


def test_occupancy_of_a_box_on_the_road_is_exact():
    grid = GridSpec()
    box = box_solid(
        [1.2, 0.0, 0.3], [0.4, 0.8, 0.6], 0.0, C.CAR, 1000
    )  # x 1.0-1.4, y +-0.4, z 0-0.6
    tile = ground_tile(0.0, 3.0, -1.0, 1.0, 0.0, C.ROAD)
    inp = G.OccupancyInput(
        [(tile.vertices, tile.faces, C.ROAD, True), (box.vertices, box.faces, C.CAR, False)],
        [(box.planes, C.CAR, box.vertices.min(0), box.vertices.max(0))],
        [],
        np.zeros((0, 3), np.int64),
        np.zeros(48 * 48 * 24, np.int32),
    )
    sem, inst = G.occupancy_grid(inp, grid)
    expected = np.full(grid.shape, C.FREE, np.uint8)
    # Road (the top of the earth: a face on a voxel face belongs to the voxel below it):
    # x 0.4-3.0 -> 0..13, y -1..1 -> 18..28 (the tile's edges lie on voxel faces and fall to one
    # side by floating-point rounding), z = 0 -> layer 4 only. The car (interior only): x 1.0-1.4 -> 3..4, y -0.4..0.4 -> 22..25,
    # z 0-0.6 -> 5..7.
    expected[0:14, 18:29, 4] = C.ROAD
    expected[3:5, 22:26, 5:8] = C.CAR
    assert np.array_equal(sem, expected)
    assert not inst.any()


def test_bad_ground_truth_field_is_rejected(tmp_path):
    arrays = {
        "grid_range_min": np.zeros(3),
        "grid_voxel_size_m": np.float64(0.2),
        "grid_shape": np.ones(3, np.int64),
        "person_faces": np.zeros((1, 3), np.int64),
        "keypoint_vertex_ids": np.zeros(5, np.int64),
        "T_base_from_lidar": np.eye(4, dtype=np.float32),
    }
    with pytest.raises(GT.GTFormatError, match="T_base_from_lidar"):
        GT.write_sequence_gt(tmp_path, 0, arrays)


def test_show_renders_a_frame(runs, tmp_path):
    from PIL import Image

    from flows.commands.show import show

    out = show(runs[0] / "gt" / "0", tmp_path / "frame.png", frame=1)
    im = np.asarray(Image.open(out))
    assert im.ndim == 3 and im.shape[0] == 640 and im.shape[1] > 1000
    assert len(np.unique(im.reshape(-1, 3), axis=0)) > 50
    with pytest.raises(ValueError, match="no frame 7"):
        show(runs[0] / "gt" / "0", tmp_path / "x.png", frame=7)


def test_lidar_on_a_flat_ground_hits_at_the_analytic_range():
    from tasks.sim.sensors import MeshSet, cast_lidar, lidar_directions

    tile = ground_tile(-50, 50, -50, 50, 0.0, C.ROAD)
    meshes = MeshSet(
        tile.vertices.astype(np.float32),
        tile.faces.astype(np.uint32),
        np.array([C.ROAD] * 2, np.uint8),
        np.zeros(2, np.uint16),
        np.ones((2, 3), np.float32),
    )
    T = np.eye(4)
    T[2, 3] = 0.9
    noise = LidarNoise(range_std_m=0.0, angle_std_deg=0.0, dropout=0.0)
    sweep = cast_lidar(
        meshes.raycasting_scene(), meshes, T, "os1-32", noise, np.random.default_rng(0)
    )
    dirs = lidar_directions().reshape(-1, 3)
    rows = np.repeat(np.arange(128), 1024)
    expect_hit = (dirs[:, 2] < 0) & (rows % 4 == 0) & (0.9 / np.maximum(-dirs[:, 2], 1e-9) <= 90.0)
    hit = sweep.point_class == C.ROAD
    assert np.array_equal(hit, expect_hit)
    rng_m = np.linalg.norm(sweep.points[hit], axis=1)
    np.testing.assert_allclose(rng_m, 0.9 / -dirs[hit, 2], rtol=1e-5)
    np.testing.assert_allclose(sweep.points[hit, 2], -0.9, atol=1e-4)
    assert np.all(sweep.points[~hit] == 0) and np.all(sweep.intensity[~hit] == 0)


def test_vertex_velocities_are_the_derivative_of_the_posed_bodies(clean_frame):
    """The ground truth's per-vertex velocity (world motion in base axes) against a 20 ms central
    difference of the posed people; walkers move on average with their own velocity; a walk that
    starts at t = 0 gives a one-sided difference, not the jump from the standing pose."""
    sim, f = clean_frame
    v = f.people.vertex_velocity_base
    assert v.dtype == np.float32 and v.shape == f.people.vertices.shape
    t, h = f.t_s, 0.01
    a, b = sim._pose_people(t - h, np.eye(4))[5], sim._pose_people(t + h, np.eye(4))[5]
    R_base_from_world = f.T_world_from_base[:3, :3].T
    err = np.abs(((b - a) / (2 * h)) @ R_base_from_world.T - v)
    # vz is looser: a body stands on its lowest vertex, whose switch from foot to foot is a kink
    assert err[..., :2].max() < 0.05 and err[..., 2].max() < 0.5
    walking = np.linalg.norm(f.people.velocity_base, axis=1) > 0.3
    assert walking.any()
    mean_xy = v[walking, :, :2].mean(axis=1)
    assert np.abs(mean_xy - f.people.velocity_base[walking]).max() < 0.4
    assert np.abs(sim.vertex_velocity_base(0)).max() < 10.0


def test_written_ground_truth_has_vertex_velocities(runs):
    g = GT.read_frame_gt(runs[0], 0, 1)
    assert g.vertex_velocity_base is not None and g.vertex_velocity_base.shape == g.vertices.shape
