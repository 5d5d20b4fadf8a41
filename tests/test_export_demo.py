"""The documented export commands on a demo-like run (relative --data / --out, as `make demo`), and
the training infos read the way FlashOcc / BEVDet datasets read them.

Regressions pinned (issue 19): the nuScenes export joined the data root twice (frames table paths
carried the root: `demo-data/demo-data/...png does not exist`); mask_camera held voxels outside
mask_lidar; NaN velocities; FlashOcc needed patches to read the export.
"""

from __future__ import annotations

import json
import os
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from pyquaternion import Quaternion

from configs.schema import ORACLE_CONFIG, load_config
from flows.cli import main
from flows.pipeline.run import rebuild_dataset
from storage.dataset import open_dataset
from storage.export.common import DETECTION_CLASSES, sample_token
from storage.gt import read_frame_gt
from storage.plain_pickle import pickle_globals
from storage.tables import read_table
from tasks import conventions as C

pytestmark = [pytest.mark.usefixtures("prefect_harness"), pytest.mark.xdist_group("prefect")]


@pytest.fixture(scope="module")
def demo(synthetic_root, tmp_path_factory, prefect_harness):
    """`make demo`'s layout in a fresh folder: demo-data/ (raw + gt), demo-out/ (the dataset), and
    the README's export commands run from that folder with relative paths."""
    work = tmp_path_factory.mktemp("demo")
    shutil.copytree(synthetic_root, work / "demo-data")
    cwd = os.getcwd()
    os.chdir(work)
    try:
        cfg = load_config(
            ORACLE_CONFIG,
            overrides={
                "dataset.root": "demo-data",
                "output.root": "demo-out",
                "fit.iterations": 5,
                "export.val_sequences": ["1"],
            },
        )
        report = rebuild_dataset(cfg, progress=False)
        assert not report.failed
        common = ["--out", "demo-out", "--set", "export.val_sequences=['1']"]
        # FlashOcc's layout: the nuScenes tables, samples, infos and the Occ3D gts in data/nuscenes
        assert main(["export", *common, "--format", "nuscenes", "--to", "data/nuscenes"]) == 0
        assert main(["export", *common, "--format", "occ3d", "--to", "data/nuscenes"]) == 0
        assert main(["export", *common, "--format", "occ3d", "--gt", "--to", "gt-occ3d"]) == 0
        yield work, cfg
    finally:
        os.chdir(cwd)


def test_published_paths_are_relative_and_masks_nested(demo):
    work, cfg = demo
    frames = read_table(work / "demo-out", "frames").to_pylist()
    assert frames and all(
        not Path(r["lidar_path"]).is_absolute() and not r["lidar_path"].startswith("demo-data")
        for r in frames
    )
    assert all((work / "demo-data" / r["cam0_path"]).is_file() for r in frames)
    ds = open_dataset(work / "demo-out")
    for seq in ds.sequences:
        arrays = ds.arrays(seq, lazy="zarr")
        cam, lidar = np.asarray(arrays["mask_camera"][:]), np.asarray(arrays["mask_lidar"][:])
        assert cam.any() and not (cam.astype(bool) & ~lidar.astype(bool)).any()
    inst = read_table(work / "demo-out", "instances").to_pandas().dropna(subset=["box3d_center"])
    assert len(inst) > 0
    assert np.isfinite(inst[["vx", "vy"]].to_numpy(np.float64)[inst["vx"].notna().to_numpy()]).all()
    sizes = np.stack(inst["box3d_size"].to_numpy())
    assert (sizes[:, 2] > 1.0).all() and np.isfinite(inst["box3d_yaw"].to_numpy()).all()


def test_nuscenes_export_of_the_demo_loads_in_the_devkit(demo):
    pytest.importorskip("nuscenes")
    from nuscenes.nuscenes import NuScenes

    work, _ = demo
    root = work / "data" / "nuscenes"
    nusc = NuScenes("v1.0-trainval", str(root), verbose=False)
    assert {s["name"] for s in nusc.scene} == {"coda-0", "coda-1"}
    for sd in nusc.sample_data:
        assert (root / sd["filename"]).is_file()
    assert len(nusc.sample_annotation) > 0
    for ann in nusc.sample_annotation:
        assert ann["visibility_token"] in {"1", "2", "3", "4"}
        assert ann["velocity"] is None or np.isfinite(ann["velocity"]).all()


# ---- a faithful re-implementation of the field access of FlashOcc's NuScenesDatasetOccpancy (and
# BEVDet's NuScenesDatasetBEVDet it extends), its pipelines PrepareImageInputs,
# LoadAnnotationsBEVDepth, LoadOccGTFromFile, PointToMultiViewDepth and its EgoPoseDataset
# (Yzichen/FlashOCC, projects/mmdet3d_plugin/datasets); mmcv's pkl loading is pickle.load.


def _load_annotations(ann_file: Path, load_interval: int = 1) -> tuple[list[dict], dict]:
    with open(ann_file, "rb") as f:  # our own file
        data = pickle.load(f)
    infos = list(sorted(data["infos"], key=lambda e: e["timestamp"]))[::load_interval]
    return infos, data["metadata"]


def _get_data_info(infos: list[dict], index: int, prototype: str, adj_ids=(1, 2, 1)) -> dict:
    info = infos[index]
    d = {
        "sample_idx": info["token"],
        "pts_filename": info["lidar_path"],
        "sweeps": info["sweeps"],
        "timestamp": info["timestamp"] / 1e6,
    }
    if "ann_infos" in info:
        d["ann_infos"] = info["ann_infos"]
    if prototype == "mmcv":
        paths, lidar2img = [], []
        for _, cam in info["cams"].items():
            paths.append(cam["data_path"])
            lidar2cam_r = np.linalg.inv(cam["sensor2lidar_rotation"])
            lidar2cam_t = cam["sensor2lidar_translation"] @ lidar2cam_r.T
            rt = np.eye(4)
            rt[:3, :3] = lidar2cam_r.T
            rt[3, :3] = -lidar2cam_t
            intrinsic = cam["cam_intrinsic"]
            viewpad = np.eye(4)
            viewpad[: intrinsic.shape[0], : intrinsic.shape[1]] = intrinsic
            lidar2img.append(viewpad @ rt.T)
        d.update(img_filename=paths, lidar2img=lidar2img)
    else:
        d["curr"] = info
        adjacent = []
        for select_id in range(*adj_ids):
            j = max(index - select_id, 0)
            adjacent.append(info if infos[j]["scene_token"] != info["scene_token"] else infos[j])
        d["adjacent"] = adjacent
    d["occ_gt_path"] = info["occ_path"]
    return d


def _get_ann_info(info: dict, use_valid_flag: bool = True) -> dict:
    mask = info["valid_flag"] if use_valid_flag else info["num_lidar_pts"] > 0
    boxes, names = info["gt_boxes"][mask], info["gt_names"][mask]
    velocity = info["gt_velocity"][mask]
    velocity[np.isnan(velocity[:, 0])] = [0.0, 0.0]
    return {"gt_bboxes_3d": np.concatenate([boxes, velocity], axis=-1), "gt_names": names}


def _T(translation, rotation) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Quaternion(*rotation).rotation_matrix
    T[:3, 3] = translation
    return T


def _sensor_transforms(info: dict, cam: str) -> tuple[np.ndarray, np.ndarray]:
    c = info["cams"][cam]
    return (
        _T(c["sensor2ego_translation"], c["sensor2ego_rotation"]),
        _T(c["ego2global_translation"], c["ego2global_rotation"]),
    )


def _lidar2img_depth_chain(info: dict, cam: str) -> np.ndarray:
    """PointToMultiViewDepth: lidar -> lidar ego -> global -> camera ego -> camera -> image."""
    lidar2ego = _T(info["lidar2ego_translation"], info["lidar2ego_rotation"])
    ego2global = _T(info["ego2global_translation"], info["ego2global_rotation"])
    cam2ego, camego2global = _sensor_transforms(info, cam)
    cam2img = np.eye(4)
    cam2img[:3, :3] = info["cams"][cam]["cam_intrinsic"]
    return cam2img @ np.linalg.inv(camego2global @ cam2ego) @ ego2global @ lidar2ego


def test_training_infos_read_like_flashocc(demo):
    work, cfg = demo
    root = work / "data" / "nuscenes"
    meta = json.loads((root / "nuscenes_metadata.json").read_text())
    assert json.loads((root / "occ3d_metadata.json").read_text())["grid"] == meta["grid"]
    assert (
        meta["num_classes"] == C.NUM_CLASSES
        and meta["free_class"] == C.FREE
        and meta["class_names"][C.FREE] == "free"
        and meta["class_names"][C.UNCLASSIFIED] == "unclassified"
        and meta["occ3d_class_names"][C.UNCLASSIFIED] == "others"
    )
    g = cfg.fuse.grid
    assert (
        meta["grid"]["range_min"] == list(g.range_min)
        and meta["grid"]["voxel_size_m"] == g.voxel_size_m
    )
    assert meta["flashocc"]["grid_config"]["x"] == [g.range_min[0], g.range_max[0], g.voxel_size_m]
    assert meta["flashocc"]["Dz"] == meta["grid"]["shape"][2] == 24
    assert meta["train_scenes"] == ["coda-0"] and meta["val_scenes"] == ["coda-1"]

    ds = open_dataset(work / "demo-out")
    seq_rows = {s: ds.table("sequences", s).to_pylist()[0] for s in ds.sequences}
    frame_rows = {
        (s, r["frame"]): r for s in ds.sequences for r in ds.table("frames", s).to_pylist()
    }
    boxes = {(s, r["frame"]): [] for s in ds.sequences for r in ds.table("frames", s).to_pylist()}
    for s in ds.sequences:
        for r in ds.table("instances", s).to_pylist():
            if r["box3d_center"] is not None:
                boxes[(s, r["frame"])].append(r)
    seen = 0
    for split, seqs in (("train", ["0"]), ("val", ["1"])):
        path = root / f"mobileocc_infos_{split}.pkl"
        # plain data: numpy 1.x unpickles it too (no numpy._core globals)
        assert pickle_globals(path.read_bytes()) <= {
            ("numpy", "ndarray"),
            ("builtins", "bytearray"),
        }
        infos, metadata = _load_annotations(path)
        assert metadata["version"] == "v1.0-trainval" and metadata["num_classes"] == C.NUM_CLASSES
        assert {i["scene_name"] for i in infos} == {f"coda-{s}" for s in seqs}
        assert [i["timestamp"] for i in infos] == sorted(i["timestamp"] for i in infos)
        for index, info in enumerate(infos):
            seq = info["scene_name"].split("-", 1)[1]
            frame = next(
                f for (s, f) in frame_rows if s == seq and sample_token(s, f) == info["token"]
            )
            row, srow = frame_rows[(seq, frame)], seq_rows[seq]
            K = np.asarray(srow["K"]).reshape(3, 3)
            T_cam_from_lidar = np.asarray(srow["T_cam0_from_lidar"]).reshape(4, 4)
            T_base_from_lidar = np.asarray(srow["T_base_from_lidar"]).reshape(4, 4)
            T_world_from_base = np.asarray(row["T_world_from_base"]).reshape(4, 4)
            P = np.eye(4)
            P[:3, :3] = K
            expected = P @ T_cam_from_lidar
            d = _get_data_info(infos, index, "mmcv")
            np.testing.assert_allclose(d["lidar2img"][0], expected, atol=1e-9)
            assert Image.open(d["img_filename"][0]).size == (
                srow["image_width"],
                srow["image_height"],
            )
            pts = np.fromfile(d["pts_filename"], np.float32).reshape(
                -1, 5
            )  # LoadPointsFromFile load_dim=5
            assert len(pts) > 1000
            d = _get_data_info(infos, index, "bevdet4d")
            assert all(a["scene_token"] == info["scene_token"] for a in d["adjacent"])
            np.testing.assert_allclose(
                _lidar2img_depth_chain(d["curr"], "CAM_FRONT"), expected, atol=1e-9
            )
            cam2ego, ego2global = _sensor_transforms(d["curr"], "CAM_FRONT")
            np.testing.assert_allclose(ego2global, T_world_from_base, atol=1e-9)
            np.testing.assert_allclose(
                cam2ego, T_base_from_lidar @ np.linalg.inv(T_cam_from_lidar), atol=1e-9
            )
            # EgoPoseDataset.get_global_pose: global from lidar
            np.testing.assert_allclose(
                _T(info["ego2global_translation"], info["ego2global_rotation"])
                @ _T(info["lidar2ego_translation"], info["lidar2ego_rotation"]),
                np.asarray(row["T_world_from_lidar"]).reshape(4, 4),
                atol=1e-9,
            )
            # LoadOccGTFromFile
            labels = np.load(os.path.join(d["occ_gt_path"], "labels.npz"))
            assert labels["semantics"].shape == tuple(meta["grid"]["shape"])
            assert labels["mask_camera"].dtype == np.uint8
            # LoadAnnotationsBEVDepth: ego-frame (base) boxes [x y z l w h yaw vx vy] and labels
            ann_boxes, ann_labels = d["ann_infos"]
            ours = [r for r in boxes[(seq, frame)]]
            kept = [k for k, n in enumerate(info["num_lidar_pts"]) if n > 0]
            assert len(ann_boxes) == len(ann_labels) == len(kept)
            assert all(lab == DETECTION_CLASSES.index("pedestrian") for lab in ann_labels)
            for b, k in zip(ann_boxes, kept):
                r = ours[k]
                v = [r["vx"] or 0.0, r["vy"] or 0.0]
                np.testing.assert_allclose(
                    b, [*r["box3d_center"], *r["box3d_size"], r["box3d_yaw"], *v], atol=1e-5
                )
            # get_ann_info: LiDAR-frame boxes; back to base they are ours
            ann = _get_ann_info(info)
            assert ann["gt_bboxes_3d"].shape == (int(info["valid_flag"].sum()), 9)
            assert set(ann["gt_names"]) <= {"pedestrian"}
            for b, k in zip(ann["gt_bboxes_3d"], np.flatnonzero(info["valid_flag"])):
                r = ours[k]
                c = T_base_from_lidar @ np.r_[b[:3], 1.0]
                np.testing.assert_allclose(c[:3], r["box3d_center"], atol=1e-6)
                np.testing.assert_allclose(b[3:6], r["box3d_size"], atol=1e-6)
                yaw_base = b[6] + np.arctan2(T_base_from_lidar[1, 0], T_base_from_lidar[0, 0])
                assert abs(np.angle(np.exp(1j * (yaw_base - r["box3d_yaw"])))) < 1e-6
            seen += len(ours)
    assert seen > 0


def test_gt_export_holds_exact_labels_with_the_dataset_masks(demo):
    work, _ = demo
    ds = open_dataset(work / "demo-out")
    for seq in ds.sequences:
        for r in ds.table("frames", seq).to_pylist():
            tok = sample_token(seq, r["frame"])
            gt = np.load(work / "gt-occ3d" / "gts" / f"coda-{seq}" / tok / "labels.npz")
            ours = np.load(work / "data" / "nuscenes" / "gts" / f"coda-{seq}" / tok / "labels.npz")
            np.testing.assert_array_equal(
                gt["semantics"],
                read_frame_gt(work / "demo-data", int(seq), r["raw_frame"]).occupancy,
            )
            np.testing.assert_array_equal(gt["mask_camera"], ours["mask_camera"])
            np.testing.assert_array_equal(gt["mask_lidar"], ours["mask_lidar"])
    assert (
        json.loads((work / "gt-occ3d" / "occ3d_metadata.json").read_text())["labels"]
        == "ground-truth"
    )
    assert (
        main(
            ["export", "--out", str(work / "demo-out"), "--format", "nuscenes", "--gt", "--to", "x"]
        )
        == 2
    )


# ---- a re-implementation of the field access of the CVPR 2023 occupancy challenge's NuSceneOcc
# (CVPR2023-3D-Occupancy-Prediction, projects/mmdet3d_plugin/datasets/nuscenes_occ.py:
# load_annotations, get_data_info, prepare_train_data, union2one) and its LoadOccGTFromFile
# (datasets/pipelines/loading.py), which BEVFormer-occ trains with; before issue 32 it stopped at
# KeyError 'prev', and without occ_gt_path it silently loads all-zero labels.


def _challenge_get_data_info(infos: list[dict], index: int) -> dict:
    from nuscenes.eval.common.utils import quaternion_yaw
    from nuscenes.utils.geometry_utils import transform_matrix

    info = infos[index]
    d = dict(
        sample_idx=info["token"],
        pts_filename=info["lidar_path"],
        sweeps=info["sweeps"],
        ego2global_translation=info["ego2global_translation"],
        ego2global_rotation=info["ego2global_rotation"],
        prev_idx=info["prev"],
        next_idx=info["next"],
        scene_token=info["scene_token"],
        can_bus=info["can_bus"],
        frame_idx=info["frame_idx"],
        timestamp=info["timestamp"] / 1e6,
    )
    if "occ_gt_path" in info:
        d["occ_gt_path"] = info["occ_gt_path"]
    d["ego2lidar"] = transform_matrix(
        translation=info["lidar2ego_translation"],
        rotation=Quaternion(info["lidar2ego_rotation"]),
        inverse=True,
    )
    lidar2img = []
    for _, cam in info["cams"].items():
        lidar2cam_r = np.linalg.inv(cam["sensor2lidar_rotation"])
        lidar2cam_t = cam["sensor2lidar_translation"] @ lidar2cam_r.T
        rt = np.eye(4)
        rt[:3, :3] = lidar2cam_r.T
        rt[3, :3] = -lidar2cam_t
        intrinsic = cam["cam_intrinsic"]
        viewpad = np.eye(4)
        viewpad[: intrinsic.shape[0], : intrinsic.shape[1]] = intrinsic
        lidar2img.append(viewpad @ rt.T)
    d["lidar2img"] = lidar2img
    rotation = Quaternion(d["ego2global_rotation"])
    can_bus = d["can_bus"]
    can_bus[:3] = d["ego2global_translation"]
    can_bus[3:7] = rotation
    angle = quaternion_yaw(rotation) / np.pi * 180
    if angle < 0:
        angle += 360
    can_bus[-2] = angle / 180 * np.pi
    can_bus[-1] = angle
    return d


def _challenge_union2one(metas: list[dict]) -> list[dict]:
    prev_scene, prev_pos, prev_angle = None, None, None
    for m in metas:
        if m["scene_token"] != prev_scene:
            m["prev_bev_exists"] = False
            prev_scene = m["scene_token"]
            prev_pos, prev_angle = m["can_bus"][:3].copy(), m["can_bus"][-1].copy()
            m["can_bus"][:3] = 0
            m["can_bus"][-1] = 0
        else:
            m["prev_bev_exists"] = True
            pos, angle = m["can_bus"][:3].copy(), m["can_bus"][-1].copy()
            m["can_bus"][:3] -= prev_pos
            m["can_bus"][-1] -= prev_angle
            prev_pos, prev_angle = pos, angle
    return metas


def _load_occ_gt(data_root: Path, d: dict) -> dict:
    if "occ_gt_path" in d:
        labels = np.load(os.path.join(data_root, d["occ_gt_path"]))
        return {k: labels[k] for k in ("semantics", "mask_lidar", "mask_camera")}
    return {
        k: np.zeros((200, 200, 16), np.uint8) for k in ("semantics", "mask_lidar", "mask_camera")
    }


def test_infos_read_like_the_occupancy_challenge(demo):
    pytest.importorskip("nuscenes")
    work, _ = demo
    root = work / "data" / "nuscenes"  # both exports in one folder: occ_gt_data_root = data_root
    ds = open_dataset(work / "demo-out")
    for split in ("train", "val"):
        with open(root / f"mobileocc_infos_{split}.pkl", "rb") as f:  # our own file
            data = pickle.load(f)
        infos = list(sorted(data["infos"], key=lambda e: e["timestamp"]))  # load_annotations
        assert data["metadata"]["version"] == "v1.0-trainval"
        queue_length = 3
        for index in range(len(infos)):
            idx = list(range(index - queue_length, index))  # prepare_train_data, unshuffled
            metas = [_challenge_get_data_info(infos, max(0, i)) for i in [*idx[1:], index]]
            metas = _challenge_union2one(metas)
            d, info = metas[-1], infos[index]
            # the can_bus deltas are the ego moves inside one scene
            if d["prev_bev_exists"]:
                prev = infos[max(0, index - 1)]
                np.testing.assert_allclose(
                    d["can_bus"][:3],
                    np.subtract(info["ego2global_translation"], prev["ego2global_translation"]),
                    atol=1e-9,
                )
            # frame_idx 0 starts a scene: no prev, no previous BEV (index 0 queues itself)
            assert (d["frame_idx"] == 0) == (d["prev_idx"] == "")
            if d["frame_idx"]:
                assert d["prev_idx"] == infos[index - 1]["token"] and d["prev_bev_exists"]
                assert infos[index - 1]["next"] == info["token"]
            elif index:
                assert not d["prev_bev_exists"]
            gt = _load_occ_gt(root, d)  # LoadOccGTFromFile
            seq = info["scene_name"].split("-", 1)[1]
            frame = next(
                r["frame"]
                for r in ds.table("frames", seq).to_pylist()
                if sample_token(seq, r["frame"]) == info["token"]
            )
            ours = np.asarray(ds.arrays(seq, lazy="zarr")["semantics"][frame])
            np.testing.assert_array_equal(gt["semantics"], ours)  # not the all-zero fallback
            assert gt["semantics"].any() and gt["mask_camera"].any()
            assert (gt["semantics"] != C.FREE).any()


def test_export_needs_no_data_after_a_rebuild_from_elsewhere(demo, tmp_path, monkeypatch, capsys):
    """The dataset was built with a relative --data from its own folder; export from another
    folder without --data finds the sources through the recorded root (issue 32: it looked under
    the config's default root); a moved data root is named in the error, --data overrides."""
    work, _ = demo
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    out = str(work / "demo-out")
    assert main(["export", "--out", out, "--format", "nuscenes", "--to", "nus"]) == 0
    assert any((elsewhere / "nus" / "samples" / "CAM_FRONT").iterdir())
    assert main(["export", "--out", out, "--format", "occ3d", "--gt", "--to", "gt"]) == 0
    moved = work / "moved-data"
    os.replace(work / "demo-data", moved)
    try:
        capsys.readouterr()
        assert main(["export", "--out", out, "--format", "nuscenes", "--to", "nus2"]) == 2
        err = capsys.readouterr().err
        assert str((work / "demo-data").resolve()) in err and out in err and "--data" in err
        assert not (elsewhere / "nus2").exists()  # refused before writing
        args = ["export", "--out", out, "--data", str(moved), "--format", "nuscenes"]
        assert main([*args, "--to", "nus3"]) == 0
        assert (
            main(["export", "--out", out, "--data", "nowhere", "--format", "nuscenes", "--to", "x"])
            == 2
        )
        err = capsys.readouterr().err
        assert "nowhere" in err and str((work / "demo-data").resolve()) in err
    finally:
        os.replace(moved, work / "demo-data")
