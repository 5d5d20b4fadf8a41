"""nuScenes export: ``<out>/<version>/<table>.json`` (all 13 tables), sweeps, images, a map mask,
training infos for FlashOcc / BEVDet and ``nuscenes_metadata.json``.

- One nuScenes scene and log per sequence, one sample per frame (every frame is a key frame).
- ``sample_data``: CAM_FRONT (the cam0 image, hard-linked or copied under ``samples/CAM_FRONT/``)
  and LIDAR_TOP (``samples/LIDAR_TOP/*.pcd.bin``, float32 x y z intensity ring, LiDAR frame,
  no-return points dropped; ring = beam row of the organised scan).
- ``calibrated_sensor`` relative to the ego (= our ``base`` frame); ``ego_pose`` = T_world_from_base.
- ``sample_annotation``: pedestrians of the instances table with a 3D box; translation and rotation
  (w, x, y, z) in the world frame, size (w, l, h) with l along the heading; an extra ``velocity``
  field [vx, vy, 0] in m/s, world frame, null where unknown (the devkit ignores extra fields);
  attribute pedestrian.moving / .standing (standing where the velocity is unknown);
  ``visibility_token`` from the visible fraction of the person in cam0
  (:mod:`tasks.occupancy.instance_visibility`) in nuScenes' bins.
- ``<infos_prefix>_infos_{train,val}.pkl``: one record per sample in the layout mmdet3d's nuScenes
  converter + BEVDet's ``add_ann_adj_info`` write, which FlashOcc / BEVDet datasets read, split by
  ``val_sequences`` (storage/SCHEMA.md lists every field). Plain pickles (storage/plain_pickle.py).
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

from storage.atomic import atomic_write_bytes, atomic_write_text, write_atomically
from storage.dataset import open_dataset
from storage.export.common import (
    CAM_CHANNEL,
    DETECTION_CLASSES,
    LIDAR_CHANNEL,
    from_log,
    grid_metadata,
    link_or_copy,
    mat4,
    pose_record,
    quat_wxyz_from_matrix,
    recorded_source_root,
    resolve,
    sample_file_name,
    sample_token,
    scene_name,
    sequence_info,
    token,
    write_json,
)
from storage.occupancy_store import open_layout, read_frames
from storage.plain_pickle import dumps_plain
from storage.sources.log.refs import parse_ref, read_ref_sweep, ref_image
from tasks.conventions import CLASS_NAMES, FREE, PEDESTRIAN, ROAD, TERRAIN
from tasks.geometry import points_in_boxes, rot_z
from tasks.occupancy.instance_visibility import box_lattice, visible_fractions

TABLES = (
    "category",
    "attribute",
    "visibility",
    "instance",
    "sensor",
    "calibrated_sensor",
    "ego_pose",
    "log",
    "scene",
    "sample",
    "sample_data",
    "sample_annotation",
    "map",
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
    "static.others",  # unclassified: occupied, class unknown (Occ3D's "others")
)
VERSIONS = ("v1.0-trainval", "v1.0-mini", "v1.0-test")
#: nuScenes visibility levels: (token, level, lower bound of the visible fraction)
VISIBILITY_LEVELS = (
    ("1", "v0-40", 0.0),
    ("2", "v40-60", 0.4),
    ("3", "v60-80", 0.6),
    ("4", "v80-100", 0.8),
)
#: length of the ``can_bus`` vector of the occupancy challenge's infos (position 3, orientation 4,
#: acceleration 3, rotation rate 3, velocity 3, 2 zeros); ours are zeros (no CAN bus on a robot):
#: its dataset class writes position, orientation and yaw from ego2global itself
CAN_BUS_LENGTH = 18
#: where FlashOcc's configs keep the nuScenes data (``data_root``), relative to its checkout
INFOS_DATA_ROOT = "./data/nuscenes"
INFOS_PREFIX = "mobileocc"
#: classes that never occlude a person in the visible fraction (flat ground under them)
FLAT_GROUND = (ROAD, TERRAIN)
#: grid spec, class names, free id, splits, infos files (beside the Occ3D export's own, same folder)
METADATA_FILE = "nuscenes_metadata.json"


def visibility_token(fraction: float) -> str:
    """The nuScenes visibility token of a visible fraction in [0, 1] (bins 0-40, 40-60, 60-80,
    80-100 %; a bound belongs to the bin above it)."""
    tok = VISIBILITY_LEVELS[0][0]
    for t, _, lower in VISIBILITY_LEVELS:
        if fraction >= lower:
            tok = t
    return tok


def read_sweep(path: Path, min_range_m: float, frame: int) -> np.ndarray:
    """(N, 5) float32 x y z intensity ring of a CODa .bin (no-returns dropped), LiDAR frame."""
    from storage.sources.coda import read_lidar_bin

    sweep = read_lidar_bin(path, min_range_m=min_range_m, frame=frame)
    out = np.empty((len(sweep.points), 5), dtype=np.float32)
    out[:, :3] = sweep.points
    out[:, 3] = sweep.intensity
    out[:, 4] = sweep.ring
    return out


def _static_tables(log_tokens: list[str], map_token: str) -> dict[str, list]:
    category = [
        {
            "token": token("category", name),
            "name": name,
            "description": f"mobileocc class {CLASS_NAMES[i]}",
            "index": i,
        }
        for i, name in enumerate(CATEGORY_NAMES)
    ]
    attribute = [
        {"token": token("attribute", name), "name": name, "description": desc}
        for name, desc in (
            ("pedestrian.moving", "speed above the moving threshold"),
            ("pedestrian.standing", "speed at or below the moving threshold, or unknown"),
        )
    ]
    visibility = [
        {
            "token": tok,
            "level": level,
            "description": f"visibility of the instance is {level} % (visible fraction of its cam0 silhouette)",
        }
        for tok, level, _ in VISIBILITY_LEVELS
    ]
    sensor = [
        {"token": token("sensor", CAM_CHANNEL), "channel": CAM_CHANNEL, "modality": "camera"},
        {"token": token("sensor", LIDAR_CHANNEL), "channel": LIDAR_CHANNEL, "modality": "lidar"},
    ]
    maps = [
        {
            "token": map_token,
            "category": "semantic_prior",
            "filename": f"maps/{map_token}.png",
            "log_tokens": log_tokens,
        }
    ]
    return {
        "category": category,
        "attribute": attribute,
        "visibility": visibility,
        "sensor": sensor,
        "map": maps,
    }


def visible_fractions_of_boxes(
    ds, seq: str, info, rows: list[dict]
) -> dict[tuple[int, int], float]:
    """(frame, track_id) -> visible fraction in cam0 of each instances-table row with a box
    (``rows``), from the published grids of ``seq`` (``info``: its :func:`sequence_info`); a person
    with no voxel in the grid is drawn as the voxel centres of its box."""
    store = ds.store_path(seq)
    attrs = ds.attrs(seq)
    vs = float(attrs["voxel_size_m"])
    by_frame: dict[int, list[dict]] = {}
    for r in rows:
        by_frame.setdefault(int(r["frame"]), []).append(r)
    out: dict[tuple[int, int], float] = {}
    for start, stop in open_layout(store).write_units():
        wanted = [f for f in range(start, stop) if f in by_frame]
        if not wanted:
            continue
        grids = read_frames(store, slice(start, stop), ("semantics", "instances"))
        for f in wanted:
            sem, inst = grids["semantics"][f - start], grids["instances"][f - start]
            ids = [int(r["track_id"]) for r in by_frame[f]]
            present = set(np.unique(inst).tolist())
            outside = {
                int(r["track_id"]): box_lattice(
                    r["box3d_center"], r["box3d_size"], float(r["box3d_yaw"] or 0.0), vs
                )
                for r in by_frame[f]
                if int(r["track_id"]) not in present
            }
            # flat ground (road, terrain) lies under people: its voxels stand for a surface at z ~ 0
            # and would hide their feet; it does not occlude them
            occluders = ~np.isin(sem, (FREE, *FLAT_GROUND))
            frac = visible_fractions(
                attrs["range_min"],
                vs,
                occluders,
                inst,
                ids,
                info.K,
                info.width,
                info.height,
                info.T_base_from_cam0,
                outside=outside,
            )
            out.update({(f, i): float(v) for i, v in zip(ids, frac)})
    return out


def export_nuscenes(
    dataset_root: str | os.PathLike,
    out_dir: str | os.PathLike,
    version: str = "v1.0-trainval",
    scene_prefix: str = "coda",
    source_root: str | os.PathLike | None = None,
    sequences: Iterable[str] | None = None,
    min_range_m: float = 0.1,
    moving_speed_mps: float = 0.2,
    val_sequences: Iterable[str] = (),
    infos_data_root: str = INFOS_DATA_ROOT,
) -> Path:
    """Export the published dataset at ``dataset_root`` as a nuScenes ``version`` under ``out_dir``.

    source_root: the raw data root the frames table's paths are relative to (default: the one
    recorded in the dataset's manifest, else ``dataset_root``).
    min_range_m: LiDAR points closer than this are no-returns and dropped from the sweeps.
    moving_speed_mps: pedestrians faster than this get the attribute pedestrian.moving.
    val_sequences: sequences of the val infos (the rest are train).
    infos_data_root: prefix of the file paths in the training infos (where the trainer finds
    ``out_dir``; FlashOcc's configs use ``./data/nuscenes``).
    Returns the table directory ``out_dir/version``.
    """
    if version not in VERSIONS and not version.startswith("v1.0-"):
        raise ValueError(
            f"export_nuscenes: version {version!r} must look like v1.0-<name>, e.g. one of {VERSIONS}"
        )
    ds = open_dataset(dataset_root)
    out = Path(out_dir)
    built_from = recorded_source_root(dataset_root)
    if source_root is None:
        source_root = built_from or dataset_root
    src_root = Path(source_root)
    chosen = list(ds.sequences if sequences is None else sequences)
    for seq in chosen:  # a moved data root fails here, before anything is written
        for row in ds.table("frames", seq).to_pylist()[:1]:
            for key, what in (("cam0_path", "cam0 image"), ("lidar_path", "LiDAR")):
                if parse_ref(row[key]) is None:  # a robot log's message: read where it is used
                    resolve(row[key], src_root, what, seq, row["frame"], built_from)
    val = set(val_sequences)
    if val - set(chosen):
        raise ValueError(
            f"export_nuscenes: val_sequences {sorted(val - set(chosen))} are not among the "
            f"exported sequences {chosen}"
        )
    metadata = grid_metadata(ds, chosen)
    map_token = token("map", scene_prefix)
    log_tokens = [token("log", seq) for seq in chosen]
    t = {name: [] for name in TABLES}
    t.update(_static_tables(log_tokens, map_token))
    ped_category = token("category", CATEGORY_NAMES[PEDESTRIAN])
    attr_moving, attr_standing = (
        token("attribute", "pedestrian.moving"),
        token("attribute", "pedestrian.standing"),
    )
    infos: dict[str, list] = {"train": [], "val": []}
    prefix = infos_data_root.rstrip("/")

    scenes: dict[str, str] = {}
    for seq, log_tok in zip(chosen, log_tokens):
        info = sequence_info(ds, seq)
        log = from_log(info.frames)
        scene = scenes[seq] = scene_name(scene_prefix, seq, log)
        cs_cam = token("calibrated_sensor", seq, CAM_CHANNEL)
        cs_lidar = token("calibrated_sensor", seq, LIDAR_CHANNEL)
        t["calibrated_sensor"] += [
            {
                "token": cs_cam,
                "sensor_token": token("sensor", CAM_CHANNEL),
                **pose_record(info.T_base_from_cam0),
                "camera_intrinsic": info.K.tolist(),
            },
            {
                "token": cs_lidar,
                "sensor_token": token("sensor", LIDAR_CHANNEL),
                **pose_record(info.T_base_from_lidar),
                "camera_intrinsic": [],
            },
        ]
        first_stamp = int(info.frames[0]["stamp_ns"]) if info.frames else 0
        date = np.datetime64(first_stamp, "ns").astype("datetime64[D]")
        t["log"].append(
            {
                "token": log_tok,
                "logfile": seq if log else f"{scene_prefix}_{seq}",
                "vehicle": "mobile-robot",
                "date_captured": str(date),
                "location": "ut-campus",
            }
        )
        frames = info.frames
        samples = [sample_token(seq, r["frame"]) for r in frames]
        sd_cam = [token("sample_data", seq, r["frame"], CAM_CHANNEL) for r in frames]
        sd_lidar = [token("sample_data", seq, r["frame"], LIDAR_CHANNEL) for r in frames]
        base_by_frame: dict[int, np.ndarray] = {}
        points_by_frame: dict[int, np.ndarray] = {}
        files_by_frame: dict[int, tuple[str, str]] = {}
        for i, row in enumerate(frames):
            f = int(row["frame"])
            stamp_us = int(row["stamp_ns"]) // 1000
            prev_s, next_s = (
                (samples[i - 1] if i else ""),
                (samples[i + 1] if i + 1 < len(samples) else ""),
            )
            t["sample"].append(
                {
                    "token": samples[i],
                    "timestamp": stamp_us,
                    "prev": prev_s,
                    "next": next_s,
                    "scene_token": token("scene", seq),
                }
            )
            T_wb = mat4(row["T_world_from_base"])
            base_by_frame[f] = T_wb
            # one ego pose per sample_data, as nuScenes does (both share the sweep stamp here)
            for sd_list in (sd_cam, sd_lidar):
                t["ego_pose"].append(
                    {"token": sd_list[i], "timestamp": stamp_us, **pose_record(T_wb)}
                )
            img_ref, lidar_ref = parse_ref(row["cam0_path"]), parse_ref(row["lidar_path"])
            if img_ref is None:  # a file of the CODa layout
                img_src = resolve(row["cam0_path"], src_root, "cam0 image", seq, f, built_from)
                img_rel = sample_file_name(scene, CAM_CHANNEL, stamp_us, img_src.suffix)
                link_or_copy(img_src, out / img_rel)
                img_suffix = img_src.suffix
            else:  # a message of a robot log
                data, img_suffix = ref_image(img_ref, src_root)
                img_rel = sample_file_name(scene, CAM_CHANNEL, stamp_us, img_suffix)
                atomic_write_bytes(out / img_rel, data)
            if lidar_ref is None:
                lidar_src = resolve(row["lidar_path"], src_root, "LiDAR", seq, f, built_from)
                sweep = read_sweep(lidar_src, min_range_m, f)
            else:
                sweep = read_ref_sweep(lidar_ref, src_root, min_range_m)
            lidar_rel = sample_file_name(scene, LIDAR_CHANNEL, stamp_us, ".pcd.bin")
            (out / lidar_rel).parent.mkdir(parents=True, exist_ok=True)
            sweep.tofile(out / lidar_rel)
            files_by_frame[f] = (img_rel, lidar_rel)
            pts_h = np.c_[sweep[:, :3].astype(np.float64), np.ones(len(sweep))]
            points_by_frame[f] = (pts_h @ info.T_base_from_lidar.T)[:, :3]
            for sd_list, cs, rel, fmt, w, h in (
                (sd_cam, cs_cam, img_rel, img_suffix.lstrip("."), info.width, info.height),
                (sd_lidar, cs_lidar, lidar_rel, "pcd", 0, 0),
            ):
                t["sample_data"].append(
                    {
                        "token": sd_list[i],
                        "sample_token": samples[i],
                        "ego_pose_token": sd_list[i],
                        "calibrated_sensor_token": cs,
                        "timestamp": stamp_us,
                        "fileformat": fmt,
                        "is_key_frame": True,
                        "height": h,
                        "width": w,
                        "filename": rel,
                        "prev": sd_list[i - 1] if i else "",
                        "next": sd_list[i + 1] if i + 1 < len(sd_list) else "",
                    }
                )
        t["scene"].append(
            {
                "token": token("scene", seq),
                "log_token": log_tok,
                "nbr_samples": len(samples),
                "first_sample_token": samples[0] if samples else "",
                "last_sample_token": samples[-1] if samples else "",
                "name": scene,
                "description": f"mobileocc sequence {seq}",
            }
        )
        rows = [
            r
            for r in ds.table("instances", seq).to_pylist()
            if r["box3d_center"] is not None
            and r["box3d_size"] is not None
            and r["frame"] in base_by_frame
        ]
        visible = visible_fractions_of_boxes(ds, seq, info, rows)
        boxes = _annotations(
            t,
            rows,
            seq,
            base_by_frame,
            points_by_frame,
            visible,
            ped_category,
            attr_moving,
            attr_standing,
            moving_speed_mps,
        )
        split = "val" if seq in val else "train"
        for i, row in enumerate(frames):
            f = int(row["frame"])
            rec = _info(
                info, scene, seq, row, sd_cam[i], files_by_frame[f], boxes.get(f, []), prefix
            )
            # the occupancy challenge's / BEVFormer-occ's temporal fields (NuSceneOcc.get_data_info)
            rec.update(
                prev=samples[i - 1] if i else "",
                next=samples[i + 1] if i + 1 < len(samples) else "",
                frame_idx=i,
                can_bus=np.zeros(CAN_BUS_LENGTH),
                occ_gt_path=f"gts/{scene}/{samples[i]}/labels.npz",
            )
            infos[split].append(rec)

    # a tiny all-zero semantic prior: the devkit needs the file, nothing reads its content here
    with write_atomically(out / t["map"][0]["filename"]) as mask:
        Image.fromarray(np.zeros((8, 8), np.uint8)).save(mask, format="PNG")
    for name in TABLES:
        atomic_write_text(
            out / version / f"{name}.json",
            json.dumps(t[name], indent=0, sort_keys=True, allow_nan=False),
        )
    meta = {
        **metadata,
        "version": version,
        "scene_prefix": scene_prefix,
        "train_scenes": [scenes[s] for s in chosen if s not in val],
        "val_scenes": [scenes[s] for s in chosen if s in val],
        "infos": {split: f"{INFOS_PREFIX}_infos_{split}.pkl" for split in infos},
        "infos_data_root": prefix,
    }
    for split, records in infos.items():
        records = time_ordered(records, split)
        atomic_write_bytes(
            out / meta["infos"][split], dumps_plain({"infos": records, "metadata": meta})
        )
    write_json(out / METADATA_FILE, meta)
    return out / version


def time_ordered(records: list[dict], split: str) -> list[dict]:
    """The infos sorted by timestamp, as mmdet3d's NuScenesDataset and the occupancy challenge's
    NuSceneOcc sort them on loading; ValueError when two scenes overlap in time (sorting would
    interleave their frames, and temporal models would pair frames of different scenes)."""
    spans: dict[str, list[int]] = {}
    for r in records:
        lo_hi = spans.setdefault(r["scene_name"], [r["timestamp"], r["timestamp"]])
        lo_hi[0], lo_hi[1] = min(lo_hi[0], r["timestamp"]), max(lo_hi[1], r["timestamp"])
    ordered = sorted(spans.items(), key=lambda kv: kv[1][0])
    for (a, (_, a_end)), (b, (b_start, _)) in zip(ordered, ordered[1:]):
        if b_start <= a_end:
            raise ValueError(
                f"export_nuscenes: scenes {a!r} and {b!r} of the {split} split overlap in time "
                f"({b!r} starts at {b_start} us, before {a!r} ends at {a_end} us): trainers that "
                "sort samples by timestamp would interleave them; put them in different splits"
            )
    return sorted(records, key=lambda r: r["timestamp"])


def _annotations(
    t,
    rows,
    seq,
    base_by_frame,
    points_by_frame,
    visible,
    ped_category,
    attr_moving,
    attr_standing,
    moving_speed_mps,
) -> dict[int, list[dict]]:
    """Append instance / sample_annotation records; returns per frame the boxes in the base frame
    (for the training infos)."""
    tracks: dict[int, list[dict]] = {}
    for r in rows:
        tracks.setdefault(int(r["track_id"]), []).append(r)
    boxes: dict[int, list[dict]] = {}
    for track_id in sorted(tracks):
        track = sorted(tracks[track_id], key=lambda r: r["frame"])
        inst = token("instance", seq, track_id)
        anns = [token("sample_annotation", seq, track_id, r["frame"]) for r in track]
        t["instance"].append(
            {
                "token": inst,
                "category_token": ped_category,
                "nbr_annotations": len(anns),
                "first_annotation_token": anns[0],
                "last_annotation_token": anns[-1],
            }
        )
        for k, r in enumerate(track):
            f = int(r["frame"])
            T_wb = base_by_frame[f]
            yaw = float(r["box3d_yaw"] or 0.0)
            center_w = T_wb[:3, :3] @ np.asarray(r["box3d_center"]) + T_wb[:3, 3]
            R_w = T_wb[:3, :3] @ rot_z(yaw)
            l, w, h = (float(v) for v in r["box3d_size"])
            v_base = None
            if (
                r["vx"] is not None
                and r["vy"] is not None
                and np.isfinite([r["vx"], r["vy"]]).all()
            ):
                v_base = np.array([float(r["vx"]), float(r["vy"]), 0.0])
            moving = v_base is not None and np.hypot(v_base[0], v_base[1]) > moving_speed_mps
            n_pts = int(
                points_in_boxes(
                    points_by_frame[f], [r["box3d_center"]], [(l, w, h)], [rot_z(yaw)]
                ).sum()
            )
            fraction = visible.get((f, track_id), 0.0)
            t["sample_annotation"].append(
                {
                    "token": anns[k],
                    "sample_token": sample_token(seq, f),
                    "instance_token": inst,
                    "visibility_token": visibility_token(fraction),
                    "attribute_tokens": [attr_moving if moving else attr_standing],
                    "translation": [float(v) for v in center_w],
                    "size": [w, l, h],
                    "rotation": quat_wxyz_from_matrix(R_w),
                    "prev": anns[k - 1] if k else "",
                    "next": anns[k + 1] if k + 1 < len(anns) else "",
                    "num_lidar_pts": n_pts,
                    "num_radar_pts": 0,
                    "velocity": None
                    if v_base is None
                    else [float(v) for v in T_wb[:3, :3] @ v_base],
                }
            )
            boxes.setdefault(f, []).append(
                {
                    "center": np.asarray(r["box3d_center"], np.float64),
                    "lwh": (l, w, h),
                    "yaw": yaw,
                    "velocity": v_base,
                    "num_lidar_pts": n_pts,
                }
            )
    return boxes


def _info(
    info,
    scene: str,
    seq: str,
    row: dict,
    cam_sd_token: str,
    files: tuple[str, str],
    boxes: list[dict],
    prefix: str,
) -> dict:
    """One training-info record (mmdet3d nuScenes converter + BEVDet's ann_infos / occ_path)."""
    img_rel, lidar_rel = files
    T_wb = mat4(row["T_world_from_base"])
    T_bl = info.T_base_from_lidar
    T_lidar_from_cam = np.linalg.inv(T_bl) @ info.T_base_from_cam0
    R_lb = T_bl[:3, :3].T  # lidar from base
    stamp_us = int(row["stamp_ns"]) // 1000
    ego, lidar2ego, cam2ego = (
        pose_record(T_wb),
        pose_record(T_bl),
        pose_record(info.T_base_from_cam0),
    )
    n = len(boxes)
    gt_boxes = np.zeros((n, 7))
    gt_velocity = np.zeros((n, 2))
    ann_boxes, ann_labels = [], []
    num_pts = np.zeros(n, np.int64)
    for k, b in enumerate(boxes):
        c_lidar = R_lb @ (b["center"] - T_bl[:3, 3])
        R = R_lb @ rot_z(b["yaw"])
        v = (
            b["velocity"] if b["velocity"] is not None else np.zeros(3)
        )  # unknown: 0, as the loaders make NaN
        gt_boxes[k] = [*c_lidar, *b["lwh"], np.arctan2(R[1, 0], R[0, 0])]
        gt_velocity[k] = (R_lb @ v)[:2]
        num_pts[k] = b["num_lidar_pts"]
        if b["num_lidar_pts"] > 0:  # BEVDet's get_gt keeps boxes with points
            ann_boxes.append(np.array([*b["center"], *b["lwh"], b["yaw"], v[0], v[1]], np.float64))
            ann_labels.append(DETECTION_CLASSES.index("pedestrian"))
    token_ = sample_token(seq, row["frame"])
    return {
        "token": token_,
        "timestamp": stamp_us,
        "lidar_path": f"{prefix}/{lidar_rel}",
        "sweeps": [],
        "lidar2ego_translation": lidar2ego["translation"],
        "lidar2ego_rotation": lidar2ego["rotation"],
        "ego2global_translation": ego["translation"],
        "ego2global_rotation": ego["rotation"],
        "cams": {
            CAM_CHANNEL: {
                "data_path": f"{prefix}/{img_rel}",
                "type": CAM_CHANNEL,
                "sample_data_token": cam_sd_token,
                "sensor2ego_translation": cam2ego["translation"],
                "sensor2ego_rotation": cam2ego["rotation"],
                "ego2global_translation": ego["translation"],
                "ego2global_rotation": ego["rotation"],
                "timestamp": stamp_us,
                "sensor2lidar_rotation": np.ascontiguousarray(T_lidar_from_cam[:3, :3]),
                "sensor2lidar_translation": T_lidar_from_cam[:3, 3].copy(),
                "cam_intrinsic": info.K.copy(),
            }
        },
        "gt_boxes": gt_boxes,
        "gt_names": np.array(["pedestrian"] * n, dtype="<U10"),
        "gt_velocity": gt_velocity,
        "num_lidar_pts": num_pts,
        "num_radar_pts": np.zeros(n, np.int64),
        "valid_flag": num_pts > 0,
        "ann_infos": (ann_boxes, ann_labels),
        "scene_token": token("scene", seq),
        "scene_name": scene,
        "occ_path": f"{prefix}/gts/{scene}/{token_}",
    }
