"""nuScenes export: ``<out>/<version>/<table>.json`` (all 13 tables), sweeps, images, a map mask.

- One nuScenes scene and log per sequence, one sample per frame (every frame is a key frame).
- ``sample_data``: CAM_FRONT (the cam0 image, hard-linked or copied under ``samples/CAM_FRONT/``)
  and LIDAR_TOP (``samples/LIDAR_TOP/*.pcd.bin``, float32 x y z intensity ring, LiDAR frame,
  no-return points dropped; ring = beam row of the organised scan).
- ``calibrated_sensor`` relative to the ego (= our ``base`` frame); ``ego_pose`` = T_world_from_base.
- ``sample_annotation``: pedestrians of the instances table with a 3D box; translation and rotation
  (w, x, y, z) in the world frame, size (w, l, h); an extra ``velocity`` field [vx, vy, 0] in m/s,
  world frame (the devkit ignores extra fields); attribute pedestrian.moving / .standing.
- Timestamps in integer microseconds. Tokens are sha1-derived (storage.export.common.token):
  identical across runs.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np
from PIL import Image

from storage.dataset import open_dataset
from storage.export.common import (
    CAM_CHANNEL,
    LIDAR_CHANNEL,
    link_or_copy,
    mat4,
    pose_record,
    quat_wxyz_from_matrix,
    resolve,
    sample_file_name,
    sample_token,
    scene_name,
    sequence_info,
    token,
)
from tasks.conventions import CLASS_NAMES, PEDESTRIAN

TABLES = (
    "category", "attribute", "visibility", "instance", "sensor", "calibrated_sensor", "ego_pose",
    "log", "scene", "sample", "sample_data", "sample_annotation", "map",
)
#: our class id -> nuScenes-style category name (index = our class id)
CATEGORY_NAMES = (
    "human.pedestrian.adult",
    "vehicle.car",
    "static.other_structure",
    "static.pole",
    "flat.driveable_surface",
    "flat.terrain",
    "vehicle.truck",
    "vehicle.two_wheeler",
    "static.vegetation",
)
VERSIONS = ("v1.0-trainval", "v1.0-mini", "v1.0-test")


def _rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def read_sweep(path: Path, min_range_m: float, frame: int) -> np.ndarray:
    """(N, 5) float32 x y z intensity ring of a CODa .bin (no-returns dropped), LiDAR frame."""
    from storage.coda import read_lidar_bin

    sweep = read_lidar_bin(path, min_range_m=min_range_m, frame=frame)
    out = np.empty((len(sweep.points), 5), dtype=np.float32)
    out[:, :3] = sweep.points
    out[:, 3] = sweep.intensity
    out[:, 4] = sweep.ring
    return out


def _points_in_box(points_base: np.ndarray, center, size_lwh, yaw: float) -> int:
    local = (points_base - np.asarray(center)) @ _rot_z(yaw)  # R^T applied to rows
    half = np.asarray(size_lwh) / 2.0
    return int(np.all(np.abs(local) <= half, axis=1).sum())


def _static_tables(log_tokens: list[str], map_token: str) -> dict[str, list]:
    category = [
        {"token": token("category", name), "name": name, "description": f"mobileocc class {CLASS_NAMES[i]}", "index": i}
        for i, name in enumerate(CATEGORY_NAMES)
    ]
    attribute = [
        {"token": token("attribute", name), "name": name, "description": desc}
        for name, desc in (
            ("pedestrian.moving", "speed above the moving threshold"),
            ("pedestrian.standing", "speed at or below the moving threshold"),
        )
    ]
    visibility = [
        {"token": str(i + 1), "level": level, "description": f"visibility of the instance is {level}"}
        for i, level in enumerate(("v0-40", "v40-60", "v60-80", "v80-100"))
    ]
    sensor = [
        {"token": token("sensor", CAM_CHANNEL), "channel": CAM_CHANNEL, "modality": "camera"},
        {"token": token("sensor", LIDAR_CHANNEL), "channel": LIDAR_CHANNEL, "modality": "lidar"},
    ]
    maps = [{"token": map_token, "category": "semantic_prior", "filename": f"maps/{map_token}.png", "log_tokens": log_tokens}]
    return {"category": category, "attribute": attribute, "visibility": visibility, "sensor": sensor, "map": maps}


def export_nuscenes(
    dataset_root: str | os.PathLike,
    out_dir: str | os.PathLike,
    version: str = "v1.0-trainval",
    scene_prefix: str = "coda",
    source_root: str | os.PathLike | None = None,
    sequences: Iterable[str] | None = None,
    min_range_m: float = 0.1,
    moving_speed_mps: float = 0.2,
) -> Path:
    """Export the published dataset at ``dataset_root`` as a nuScenes ``version`` under ``out_dir``.

    source_root: base of relative source paths in the frames table (default ``dataset_root``).
    min_range_m: LiDAR points closer than this are no-returns and dropped from the sweeps.
    moving_speed_mps: pedestrians faster than this get the attribute pedestrian.moving.
    Returns the table directory ``out_dir/version``.
    """
    if version not in VERSIONS and not version.startswith("v1.0-"):
        raise ValueError(f"export_nuscenes: version {version!r} must look like v1.0-<name>, e.g. one of {VERSIONS}")
    ds = open_dataset(dataset_root)
    out = Path(out_dir)
    src_root = Path(source_root) if source_root is not None else Path(dataset_root)
    chosen = list(ds.sequences if sequences is None else sequences)
    map_token = token("map", scene_prefix)
    log_tokens = [token("log", seq) for seq in chosen]
    t = {name: [] for name in TABLES}
    t.update(_static_tables(log_tokens, map_token))
    ped_category = token("category", CATEGORY_NAMES[PEDESTRIAN])
    attr_moving, attr_standing = token("attribute", "pedestrian.moving"), token("attribute", "pedestrian.standing")

    for seq, log_tok in zip(chosen, log_tokens):
        info = sequence_info(ds, seq)
        scene = scene_name(scene_prefix, seq)
        cs_cam = token("calibrated_sensor", seq, CAM_CHANNEL)
        cs_lidar = token("calibrated_sensor", seq, LIDAR_CHANNEL)
        t["calibrated_sensor"] += [
            {"token": cs_cam, "sensor_token": token("sensor", CAM_CHANNEL), **pose_record(info.T_base_from_cam0),
             "camera_intrinsic": info.K.tolist()},
            {"token": cs_lidar, "sensor_token": token("sensor", LIDAR_CHANNEL), **pose_record(info.T_base_from_lidar),
             "camera_intrinsic": []},
        ]
        first_stamp = int(info.frames[0]["stamp_ns"]) if info.frames else 0
        date = np.datetime64(first_stamp, "ns").astype("datetime64[D]")
        t["log"].append({"token": log_tok, "logfile": f"{scene_prefix}_{seq}", "vehicle": "mobile-robot",
                         "date_captured": str(date), "location": "ut-campus"})
        frames = info.frames
        samples = [sample_token(seq, r["frame"]) for r in frames]
        sd_cam = [token("sample_data", seq, r["frame"], CAM_CHANNEL) for r in frames]
        sd_lidar = [token("sample_data", seq, r["frame"], LIDAR_CHANNEL) for r in frames]
        base_by_frame: dict[int, np.ndarray] = {}
        points_by_frame: dict[int, np.ndarray] = {}
        for i, row in enumerate(frames):
            f = int(row["frame"])
            stamp_us = int(row["stamp_ns"]) // 1000
            prev_s, next_s = (samples[i - 1] if i else ""), (samples[i + 1] if i + 1 < len(samples) else "")
            t["sample"].append({"token": samples[i], "timestamp": stamp_us, "prev": prev_s, "next": next_s,
                                "scene_token": token("scene", seq)})
            T_wb = mat4(row["T_world_from_base"])
            base_by_frame[f] = T_wb
            # one ego pose per sample_data, as nuScenes does (both share the sweep stamp here)
            for sd_list, channel in ((sd_cam, CAM_CHANNEL), (sd_lidar, LIDAR_CHANNEL)):
                t["ego_pose"].append({"token": sd_list[i], "timestamp": stamp_us, **pose_record(T_wb)})
            img_src = resolve(row["cam0_path"], src_root, "cam0 image", seq, f)
            img_rel = sample_file_name(scene, CAM_CHANNEL, stamp_us, img_src.suffix)
            link_or_copy(img_src, out / img_rel)
            lidar_src = resolve(row["lidar_path"], src_root, "LiDAR", seq, f)
            sweep = read_sweep(lidar_src, min_range_m, f)
            lidar_rel = sample_file_name(scene, LIDAR_CHANNEL, stamp_us, ".pcd.bin")
            (out / lidar_rel).parent.mkdir(parents=True, exist_ok=True)
            sweep.tofile(out / lidar_rel)
            pts_h = np.c_[sweep[:, :3].astype(np.float64), np.ones(len(sweep))]
            points_by_frame[f] = (pts_h @ info.T_base_from_lidar.T)[:, :3]
            for sd_list, channel, cs, rel, fmt, w, h in (
                (sd_cam, CAM_CHANNEL, cs_cam, img_rel, img_src.suffix.lstrip("."), info.width, info.height),
                (sd_lidar, LIDAR_CHANNEL, cs_lidar, lidar_rel, "pcd", 0, 0),
            ):
                t["sample_data"].append({
                    "token": sd_list[i], "sample_token": samples[i], "ego_pose_token": sd_list[i],
                    "calibrated_sensor_token": cs, "timestamp": stamp_us, "fileformat": fmt,
                    "is_key_frame": True, "height": h, "width": w, "filename": rel,
                    "prev": sd_list[i - 1] if i else "", "next": sd_list[i + 1] if i + 1 < len(sd_list) else "",
                })
        t["scene"].append({
            "token": token("scene", seq), "log_token": log_tok, "nbr_samples": len(samples),
            "first_sample_token": samples[0] if samples else "", "last_sample_token": samples[-1] if samples else "",
            "name": scene, "description": f"mobileocc sequence {seq}",
        })
        _annotations(t, ds.table("instances", seq).to_pylist(), seq, base_by_frame, points_by_frame,
                     ped_category, attr_moving, attr_standing, moving_speed_mps)

    # a tiny all-zero semantic prior: the devkit needs the file, nothing reads its content here
    mask = out / t["map"][0]["filename"]
    mask.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.zeros((8, 8), np.uint8)).save(mask)
    table_dir = out / version
    table_dir.mkdir(parents=True, exist_ok=True)
    for name in TABLES:
        tmp = table_dir / f".tmp-{name}.json"
        tmp.write_text(json.dumps(t[name], indent=0, sort_keys=True))
        os.replace(tmp, table_dir / f"{name}.json")
    return table_dir


def _annotations(t, rows, seq, base_by_frame, points_by_frame, ped_category, attr_moving, attr_standing,
                 moving_speed_mps) -> None:
    tracks: dict[int, list[dict]] = {}
    for r in rows:
        if r["box3d_center"] is None or r["box3d_size"] is None or r["frame"] not in base_by_frame:
            continue
        tracks.setdefault(int(r["track_id"]), []).append(r)
    for track_id in sorted(tracks):
        track = sorted(tracks[track_id], key=lambda r: r["frame"])
        inst = token("instance", seq, track_id)
        anns = [token("sample_annotation", seq, track_id, r["frame"]) for r in track]
        t["instance"].append({"token": inst, "category_token": ped_category, "nbr_annotations": len(anns),
                              "first_annotation_token": anns[0], "last_annotation_token": anns[-1]})
        for k, r in enumerate(track):
            T_wb = base_by_frame[r["frame"]]
            yaw = float(r["box3d_yaw"] or 0.0)
            center_w = T_wb[:3, :3] @ np.asarray(r["box3d_center"]) + T_wb[:3, 3]
            R_w = T_wb[:3, :3] @ _rot_z(yaw)
            l, w, h = (float(v) for v in r["box3d_size"])
            vx, vy = float(r["vx"] or 0.0), float(r["vy"] or 0.0)
            v_w = T_wb[:3, :3] @ np.array([vx, vy, 0.0])
            n_pts = _points_in_box(points_by_frame[r["frame"]], r["box3d_center"], (l, w, h), yaw)
            t["sample_annotation"].append({
                "token": anns[k], "sample_token": sample_token(seq, r["frame"]), "instance_token": inst,
                "visibility_token": "4", "attribute_tokens": [attr_moving if np.hypot(vx, vy) > moving_speed_mps else attr_standing],
                "translation": [float(v) for v in center_w], "size": [w, l, h], "rotation": quat_wxyz_from_matrix(R_w),
                "prev": anns[k - 1] if k else "", "next": anns[k + 1] if k + 1 < len(anns) else "",
                "num_lidar_pts": n_pts, "num_radar_pts": 0, "velocity": [float(v) for v in v_w],
            })
