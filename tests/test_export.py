"""Occ3D and nuScenes exports of a tiny dataset built through our own storage API."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from storage import occupancy_store as occ
from storage import publish as pub
from storage.export import export_nuscenes, export_occ3d
from storage.export.common import quat_wxyz_from_matrix, sample_token
from tasks import conventions as C
from tasks.conventions import FREE, PEDESTRIAN, ROAD

GRID = (48, 48, 24)
SEQS = ("s0", "s1")
NF = 4
POINTS = 128 * 1024
W, H = 64, 48


def rz(yaw: float, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = t
    return T


T_BASE_FROM_LIDAR = rz(0.1, (0.2, 0.0, 0.8))
T_CAM0_FROM_LIDAR = np.array(
    [[0, -1, 0, 0.05], [0, 0, -1, -0.1], [1, 0, 0, 0.0], [0, 0, 0, 1]], dtype=np.float64
)
K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
BOX_CENTER_BASE = np.array([4.0, 1.0, 0.9])
BOX_SIZE_LWH = np.array([0.6, 0.5, 1.8])
BOX_YAW = 0.3


def T_world_from_base(seq_i: int, f: int) -> np.ndarray:
    return rz(0.2 * f + seq_i, (10.0 * seq_i + 0.5 * f, -2.0, 0.1))


def write_sweep(path: Path, frame: int) -> None:
    raw = np.zeros((POINTS, 5), np.float32)  # zeros = no-return
    ang = np.linspace(-np.pi, np.pi, 1024, endpoint=False)
    raw[:1024, 0], raw[:1024, 1], raw[:1024, 3] = 8 * np.cos(ang), 8 * np.sin(ang), 7.0
    # 10 points inside the pedestrian box (given in base, stored in the LiDAR frame)
    inside_base = (
        BOX_CENTER_BASE
        + np.c_[np.linspace(-0.1, 0.1, 10), np.zeros(10), np.linspace(-0.5, 0.5, 10)]
    )
    inside_lidar = (np.c_[inside_base, np.ones(10)] @ np.linalg.inv(T_BASE_FROM_LIDAR).T)[:, :3]
    raw[5000:5010, :3] = inside_lidar
    raw[5000:5010, 3] = frame
    path.parent.mkdir(parents=True, exist_ok=True)
    raw.tofile(path)


def build_tiny_dataset(root: Path, src: Path) -> Path:
    """2 sequences x 4 frames of 48x48x24, fake CODa .bin / .png sources under ``src``."""
    for si, seq in enumerate(SEQS):
        with pub.sequence_writer(root, seq, "k1") as staged:
            layout = occ.create_store(
                staged.store_path,
                NF,
                GRID,
                2,
                {
                    "voxel_size_m": 0.2,
                    "range_min": [0.4, -4.8, -1.0],
                    "range_max": [10.0, 4.8, 3.8],
                },
            )
            sem = np.full((NF, *GRID), FREE, np.uint8)
            sem[:, :, :, 4] = ROAD
            sem[:, 18:21, 28:31, 5:14] = PEDESTRIAN
            sem[:, 0, 0, 0] = np.arange(NF) + 10 * si  # frame marker
            mask = np.zeros((NF, *GRID), np.uint8)
            mask[:, :, :, :12] = 1
            vel = np.zeros((NF, *GRID, 2), np.float16)
            vel[:, 18:21, 28:31, 5:14] = (1.0, 0.5)
            for start, stop in layout.write_units():
                occ.write_frames(
                    staged.store_path,
                    start,
                    {
                        "semantics": sem[start:stop],
                        "mask_lidar": mask[start:stop],
                        "mask_camera": mask[start:stop] * 0 + 1,
                        "velocity": vel[start:stop],
                    },
                )
            rows = []
            for f in range(NF):
                raw = 2 * f
                lidar = f"3d_raw/os1/{si}/3d_raw_os1_{si}_{raw}.bin"
                cam = f"2d_raw/cam0/{si}/2d_raw_cam0_{si}_{raw}.png"
                write_sweep(src / lidar, f)
                (src / cam).parent.mkdir(parents=True, exist_ok=True)
                Image.fromarray(np.full((H, W, 3), f * 20, np.uint8)).save(src / cam)
                Twb = T_world_from_base(si, f)
                rows.append(
                    {
                        "frame": f,
                        "raw_frame": raw,
                        "stamp_ns": 1_675_000_000_000_000_000 + si * 10**12 + f * 200_000_000,
                        "T_world_from_lidar": (Twb @ T_BASE_FROM_LIDAR).ravel(),
                        "T_world_from_base": Twb.ravel(),
                        "lidar_path": lidar,
                        "cam0_path": cam,
                        "class_counts": [0] * C.NUM_CLASSES,
                        "is_night": False,
                    }
                )
            pub.stage_table(staged, "frames", rows)
            pub.stage_table(
                staged,
                "instances",
                [
                    {
                        "track_id": 7,
                        "frame": f,
                        "box3d_center": BOX_CENTER_BASE,
                        "box3d_size": BOX_SIZE_LWH,
                        "box3d_yaw": BOX_YAW,
                        "vx": 1.0 if f % 2 else 0.0,
                        "vy": 0.0,
                    }
                    for f in range(NF)
                ],
            )
            pub.stage_table(
                staged,
                "sequences",
                [
                    {
                        "fingerprint": f"fp{si}",
                        "config_hash": "c",
                        "code_version": "0.1.0",
                        "status": "ok",
                        "num_frames": NF,
                        "occupancy_version": "k1",
                        "K": K.ravel(),
                        "T_cam0_from_lidar": T_CAM0_FROM_LIDAR.ravel(),
                        "T_base_from_lidar": T_BASE_FROM_LIDAR.ravel(),
                        "image_width": W,
                        "image_height": H,
                    }
                ],
            )
    return root


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    base = tmp_path_factory.mktemp("tiny")
    return build_tiny_dataset(base / "dataset", base / "dataset"), base


def test_occ3d_labels_and_annotations(tiny):
    root, base = tiny
    ann_path = export_occ3d(root, base / "occ3d", val_sequences=("s1",))
    ann = json.loads(ann_path.read_text())
    assert ann["train_split"] == ["coda-s0"] and ann["val_split"] == ["coda-s1"]
    infos = ann["scene_infos"]["coda-s1"]
    assert len(infos) == NF
    tok2 = sample_token("s1", 2)
    rec = infos[tok2]
    assert rec["prev"] == sample_token("s1", 1) and rec["next"] == sample_token("s1", 3)
    assert infos[sample_token("s1", 0)]["prev"] == "" and infos[sample_token("s1", 3)]["next"] == ""
    assert rec["timestamp"] == (1_675_000_000_000_000_000 + 10**12 + 2 * 200_000_000) // 1000
    np.testing.assert_allclose(rec["ego_pose"]["translation"], T_world_from_base(1, 2)[:3, 3])
    cam = rec["camera_sensor"]["CAM_FRONT"]
    assert cam["intrinsic"] == K.tolist() and cam["img_path"].startswith(
        "samples/CAM_FRONT/coda-s1__CAM_FRONT__"
    )
    # the way Occ3D / FlashOcc loaders read labels
    labels = np.load(base / "occ3d" / "gts" / "coda-s1" / tok2 / "labels.npz")
    sem, ml, mc = labels["semantics"], labels["mask_lidar"], labels["mask_camera"]
    assert sem.shape == ml.shape == mc.shape == GRID
    assert sem.dtype == ml.dtype == mc.dtype == np.uint8
    assert (
        sem[0, 0, 0] == 12
        and sem[19, 29, 8] == PEDESTRIAN
        and sem[5, 5, 4] == ROAD
        and sem[5, 5, 20] == FREE
    )
    assert ml[:, :, :12].all() and not ml[:, :, 12:].any() and mc.all()
    assert rec["gt_path"] == f"gts/coda-s1/{tok2}/labels.npz"
    # OpenOcc's flow beside the labels: (X, Y, Z, 2) float16 m/s, the store's velocity
    flow = labels["flow"]
    assert flow.shape == (*GRID, 2) and flow.dtype == np.float16
    assert tuple(flow[19, 29, 8]) == (1.0, 0.5) and not flow[5, 5, 4].any()
    # time order (issue 32: a scene's samples were listed by token): scenes by first sample,
    # samples as recorded, prev / next chaining them
    assert list(ann["scene_infos"]) == ["coda-s0", "coda-s1"]
    assert list(infos) == [sample_token("s1", f) for f in range(NF)]
    stamps = [r["timestamp"] for r in infos.values()]
    assert stamps == sorted(stamps) and len(set(stamps)) == NF
    # deterministic: a second export is byte-identical
    export_occ3d(root, base / "occ3d_again", val_sequences=("s1",))
    for rel in ("annotations.json", f"gts/coda-s1/{tok2}/labels.npz"):
        a, b = (base / d / rel for d in ("occ3d", "occ3d_again"))
        assert hashlib.sha1(a.read_bytes()).digest() == hashlib.sha1(b.read_bytes()).digest()
    with pytest.raises(ValueError, match="val_sequences"):
        export_occ3d(root, base / "bad", val_sequences=("s9",))


def test_quaternion_round_trip():
    from pyquaternion import Quaternion

    rng = np.random.default_rng(3)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        R = Quaternion(q).rotation_matrix
        got = quat_wxyz_from_matrix(R)
        np.testing.assert_allclose(Quaternion(got).rotation_matrix, R, atol=1e-12)
        assert got[0] >= 0
    np.testing.assert_allclose(
        quat_wxyz_from_matrix(np.diag([1.0, -1.0, -1.0])), [0, 1, 0, 0], atol=1e-12
    )


def test_nuscenes_export_loads_in_devkit(tiny):
    pytest.importorskip("nuscenes")
    from nuscenes.nuscenes import NuScenes
    from nuscenes.utils.data_classes import LidarPointCloud

    root, base = tiny
    out = base / "nusc"
    export_nuscenes(root, out, version="v1.0-mini")
    nusc = NuScenes("v1.0-mini", str(out), verbose=False)
    assert len(nusc.scene) == 2 and len(nusc.sample) == 2 * NF and len(nusc.instance) == 2
    assert {s["name"] for s in nusc.scene} == {"coda-s0", "coda-s1"}
    sample = nusc.get("sample", sample_token("s1", 1))
    assert set(sample["data"]) == {"CAM_FRONT", "LIDAR_TOP"} and len(sample["anns"]) == 1
    assert sample["timestamp"] == (1_675_000_000_000_000_000 + 10**12 + 200_000_000) // 1000
    # LiDAR: 5 channels, no-returns dropped, in the sensor frame; the box comes back in that frame
    path, boxes, _ = nusc.get_sample_data(sample["data"]["LIDAR_TOP"])
    pc = LidarPointCloud.from_file(path)
    assert pc.points.shape == (4, 1024 + 10)
    np.testing.assert_allclose(pc.points[3, 1024:], 1.0)  # intensity = frame index 1
    (box,) = boxes
    center_lidar = np.linalg.inv(T_BASE_FROM_LIDAR) @ np.r_[BOX_CENTER_BASE, 1.0]
    np.testing.assert_allclose(box.center, center_lidar[:3], atol=1e-9)
    np.testing.assert_allclose(box.wlh, [0.5, 0.6, 1.8])
    np.testing.assert_allclose(box.orientation.yaw_pitch_roll[0], BOX_YAW - 0.1, atol=1e-9)
    ann = nusc.get("sample_annotation", sample["anns"][0])
    assert ann["num_lidar_pts"] == 10 and ann["category_name"] == "human.pedestrian.adult"
    assert nusc.get("attribute", ann["attribute_tokens"][0])["name"] == "pedestrian.moving"
    R_wb = T_world_from_base(1, 1)[:3, :3]
    np.testing.assert_allclose(ann["velocity"], R_wb @ [1.0, 0.0, 0.0], atol=1e-6)
    # camera: image present, size recorded, intrinsics
    cam_path, _, K_back = nusc.get_sample_data(sample["data"]["CAM_FRONT"])
    assert Image.open(cam_path).size == (W, H)
    np.testing.assert_allclose(K_back, K)
    sd = nusc.get("sample_data", sample["data"]["CAM_FRONT"])
    assert (sd["width"], sd["height"]) == (W, H)
    cs = nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
    from pyquaternion import Quaternion

    T = np.eye(4)
    T[:3, :3] = Quaternion(cs["rotation"]).rotation_matrix
    T[:3, 3] = cs["translation"]
    np.testing.assert_allclose(T, T_BASE_FROM_LIDAR @ np.linalg.inv(T_CAM0_FROM_LIDAR), atol=1e-12)
    # deterministic tables
    again = base / "nusc2"
    export_nuscenes(root, again, version="v1.0-mini")
    for name in ("sample", "sample_annotation", "ego_pose", "sample_data"):
        assert (out / "v1.0-mini" / f"{name}.json").read_bytes() == (
            again / "v1.0-mini" / f"{name}.json"
        ).read_bytes()


def test_nuscenes_export_names_missing_source(tiny, tmp_path):
    root, base = tiny
    with pytest.raises(FileNotFoundError, match=r"frame 0: cam0 image file"):
        export_nuscenes(root, tmp_path / "out", source_root=tmp_path / "nowhere")


def test_plain_pickle_holds_only_numpy_ndarray_and_bytearray():
    """Training infos must load under numpy 1.x: no numpy._core globals (numpy 2's default)."""
    import pickle

    from storage.plain_pickle import dumps_plain, pickle_globals

    obj = {
        "infos": [
            {
                "a": np.arange(6, dtype=np.float32).reshape(2, 3),
                "names": np.array(["pedestrian"]),
                "empty": np.zeros((0, 9)),
                "flag": np.array([True, False]),
                "t": (1, 2.5, "x", None),
            }
        ],
        "view": np.eye(4)[:, ::2],
    }
    data = dumps_plain(obj)
    assert pickle_globals(data) == {("numpy", "ndarray"), ("builtins", "bytearray")}
    assert ("numpy._core.multiarray", "_reconstruct") in pickle_globals(
        pickle.dumps(np.zeros(2))
    )  # the trap
    back = pickle.loads(data)
    for k in ("a", "names", "empty", "flag"):
        np.testing.assert_array_equal(back["infos"][0][k], obj["infos"][0][k])
        assert back["infos"][0][k].dtype == obj["infos"][0][k].dtype
    np.testing.assert_array_equal(back["view"], obj["view"])
    assert back["infos"][0]["a"].flags.writeable and back["infos"][0]["t"] == (1, 2.5, "x", None)
    assert dumps_plain(obj) == data
    for bad in ({"x": np.float64(1.0)}, {"x": np.array([object()])}, {"x": {1.5: 1}}):
        with pytest.raises(TypeError, match="object"):
            dumps_plain(bad)


def test_infos_carry_the_occupancy_challenge_fields(tiny):
    """prev / next / frame_idx / can_bus / occ_gt_path (the CVPR 2023 challenge's and BEVFormer-occ's
    NuSceneOcc.get_data_info read them: KeyError 'prev' before issue 32), in time order."""
    import pickle

    root, base = tiny
    out = base / "nusc_challenge"
    export_nuscenes(root, out, version="v1.0-mini", val_sequences=("s1",))
    for split, seq in (("train", "s0"), ("val", "s1")):
        with open(out / f"mobileocc_infos_{split}.pkl", "rb") as f:  # our own file
            infos = pickle.load(f)["infos"]
        assert [i["timestamp"] for i in infos] == sorted(i["timestamp"] for i in infos)
        toks = [sample_token(seq, f) for f in range(NF)]
        assert [i["token"] for i in infos] == toks
        for k, info in enumerate(infos):
            assert info["frame_idx"] == k
            assert info["prev"] == (toks[k - 1] if k else "")
            assert info["next"] == (toks[k + 1] if k + 1 < NF else "")
            assert info["occ_gt_path"] == f"gts/coda-{seq}/{toks[k]}/labels.npz"
            assert info["can_bus"].shape == (18,) and not info["can_bus"].any()
        assert infos[0]["can_bus"] is not infos[1]["can_bus"]  # the dataset writes into it


def test_overlapping_scenes_are_refused():
    from storage.export.nuscenes import time_ordered

    a = [{"scene_name": "a", "timestamp": t} for t in (10, 20, 30)]
    b = [{"scene_name": "b", "timestamp": t} for t in (40, 50)]
    assert [r["timestamp"] for r in time_ordered(b + a, "train")] == [10, 20, 30, 40, 50]
    c = [{"scene_name": "c", "timestamp": t} for t in (25, 35)]
    with pytest.raises(ValueError, match="scenes 'a' and 'c' of the val split overlap"):
        time_ordered(a + c, "val")


def test_flashocc_settings_for_an_asymmetric_grid(tiny):
    """The BEV x-flip is off on our grid (x 0.4..10 m: flipping moves every frustum point out),
    the y-flip stays; a larger input reaches more of the camera-visible cells; the depth bins
    reach past the grid's far corner."""
    root, base = tiny
    export_occ3d(root, base / "occ3d_meta")
    meta = json.loads((base / "occ3d_meta" / "occ3d_metadata.json").read_text())["flashocc"]
    assert meta["bda_aug_conf"]["flip_dx_ratio"] == 0.0
    assert meta["bda_aug_conf"]["flip_dy_ratio"] == 0.5
    assert meta["num_classes"] == C.NUM_CLASSES and meta["Dz"] == 24 and meta["src_size"] == [H, W]
    cover = [s["frustum_coverage"] for s in meta["input_sizes"]]
    assert all(0 < a < b <= 1 for a, b in zip(cover, cover[1:])), cover
    assert all(
        h % 16 == 0 and w % 16 == 0 for h, w in (s["input_size"] for s in meta["input_sizes"])
    )
    cam = (T_BASE_FROM_LIDAR @ np.linalg.inv(T_CAM0_FROM_LIDAR))[:3, 3]
    far = max(
        np.linalg.norm(np.array([x, y, z]) - cam)
        for x in (0.4, 10.0)
        for y in (-4.8, 4.8)
        for z in (-1.0, 3.8)
    )
    lo, hi, step = meta["grid_config"]["depth"]
    assert far < hi and step == 0.25 and lo == 0.5


def test_frustum_points_project_back_to_their_input_pixels():
    """FlashOcc's test-time resize + crop inverted: each frustum point projects to the original
    pixel ((u_in + crop_w) / s, (v_in + crop_h) / s), at its depth."""
    from tasks.occupancy.lss_frustum import frustum_points_base

    T_base_from_cam = T_BASE_FROM_LIDAR @ np.linalg.inv(T_CAM0_FROM_LIDAR)
    K1 = np.array([[730.0, 0, 611.5], [0, 730.0, 511.5], [0, 0, 1]])
    pts = frustum_points_base(K1, T_base_from_cam, (1224, 1024), (256, 304), (1.0, 3.0, 1.0))
    s = 304 / 1224
    crop_h = int(1024 * s) - 256  # 254 - 256 = -2: two padded rows on top
    u_in, v_in = np.linspace(0, 303, 19), np.linspace(0, 255, 16)
    pc = (np.c_[pts, np.ones(len(pts))] @ np.linalg.inv(T_base_from_cam).T)[:, :3]
    uv = (pc @ K1.T)[:, :2] / pc[:, 2:3]
    dd, vv, uu = np.meshgrid([1.0, 2.0], v_in, u_in, indexing="ij")
    np.testing.assert_allclose(pc[:, 2], dd.ravel(), atol=1e-9)
    np.testing.assert_allclose(uv[:, 0], uu.ravel() / s, atol=1e-6)
    np.testing.assert_allclose(uv[:, 1], (vv.ravel() + crop_h) / s, atol=1e-6)
