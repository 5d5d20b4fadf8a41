"""export: publish the sequence into the dataset (Zarr arrays + Parquet tables, atomically).

The fused store is hard-linked (copied across file systems) from the fuse stage's key-named output
into ``OUT/occupancy/<sequence>/<version>.zarr``; the three table partitions are written aside and
published together (storage/occupancy_store.py, storage/tables.py). Dataset-level exports (Occ3D,
nuScenes) run after all sequences (flows/pipeline.py, ``mobileocc export``).
"""

from __future__ import annotations

import os
import shutil

import numpy as np
import torch

from configs.schema import config_hash
from flows.plan import CODE_VERSIONS
from flows.stages.common import StageContext, is_night
from flows.stages.fit import body_model
from storage.export.common import source_relative
from storage.intermediate import read_product
from storage.manifest import FileHasher, sequence_fingerprint
from storage.occupancy_store import sequence_writer
from storage.tables import stage_table
from tasks.body.boxes import upright_box
from tasks.fit.init_oracle import BodyParams
from tasks.fit.reframe import reframe_params


def _link_tree(src, dst) -> None:
    def link(a, b):
        try:
            os.link(a, b)
        except OSError:
            shutil.copy2(a, b)
    shutil.copytree(src, dst, copy_function=link, dirs_exist_ok=True)


def instance_rows(ctx: StageContext, frame_pos: dict[int, int], T_base_from_lidar: np.ndarray) -> list[dict]:
    """One row per tracked person and frame: 2D box and keypoints from track; body parameters,
    3D box and velocity (base frame) from the fit where that person was fitted."""
    tracks = read_product(ctx.upstream["track"], "tracks")
    fit_path = ctx.upstream.get("fit")
    bodies = (read_product(fit_path, "bodies")
              if fit_path is not None and (fit_path / "bodies.npz").exists() else None)
    fitted: dict[tuple[int, int], int] = {}
    if bodies is not None and len(bodies["frame"]):
        fitted = {(int(f), int(d)): r for r, (f, d) in enumerate(zip(bodies["frame"], bodies["det_index"]))}
        model = body_model(ctx.config)
        lidar = BodyParams(bodies["betas"], bodies["global_orient"], bodies["body_pose"], bodies["transl"])
        base = reframe_params(model, lidar, T_base_from_lidar)
        with torch.no_grad():
            verts = model(*(torch.as_tensor(a) for a in (base.betas, base.global_orient,
                                                          base.body_pose, base.transl))).vertices.numpy()
    rows = []
    for r in range(len(tracks["track_id"])):
        row = {"track_id": int(tracks["track_id"][r]), "frame": frame_pos[int(tracks["frame"][r])],
               "box2d_xyxy": tracks["boxes_xyxy"][r].tolist(),
               "keypoints": tracks["keypoints"][r].reshape(-1).tolist()}
        b = fitted.get((int(tracks["frame"][r]), int(tracks["det_index"][r])))
        if b is not None:
            vel = np.asarray(bodies["velocity_base"][b], np.float64)
            known = bool(np.all(np.isfinite(vel)))  # unknown (e.g. across a track gap): null, never NaN
            box = upright_box(verts[b], base.global_orient[b], vel if known else None)
            row.update({"box3d_center": box.center.tolist(), "box3d_size": box.size.tolist(), "box3d_yaw": box.yaw,
                        "betas": base.betas[b].tolist(), "global_orient": base.global_orient[b].tolist(),
                        "body_pose": base.body_pose[b].tolist(), "transl": base.transl[b].tolist(),
                        "vx": float(vel[0]) if known else None, "vy": float(vel[1]) if known else None})
        rows.append(row)
    return rows


def run_export(ctx: StageContext) -> dict:
    seq = ctx.open()
    info = seq.info
    calib = info.calibration
    cam = calib.cameras[ctx.config.dataset.camera]
    fused = read_product(ctx.upstream["fuse"], "frames")
    night = is_night(seq)
    version = ctx.key
    frames = []
    for k, raw in enumerate(fused["frame"].tolist()):
        # source paths relative to the dataset root (SCHEMA.md): the export joins its source root
        frame_paths = {c: source_relative(seq.image_path(c, raw), seq.root) for c in calib.cameras}
        frames.append({
            "frame": k, "raw_frame": raw, "stamp_ns": int(fused["stamp_ns"][k]),
            "T_world_from_lidar": info.poses[k].reshape(-1).tolist(),
            "T_world_from_base": fused["T_world_from_base"][k].reshape(-1).tolist(),
            "lidar_path": source_relative(seq.path(seq.lidar_source, "os1", raw, ".bin"), seq.root),
            "cam0_path": frame_paths.get("cam0", ""),
            "cam1_path": frame_paths.get("cam1"),
            "class_counts": fused["class_counts"][k].tolist(), "is_night": night})
    sequences = [{
        "fingerprint": sequence_fingerprint(info.root, info.files, FileHasher(None)),
        "config_hash": config_hash(ctx.config, content_only=True), "code_version": CODE_VERSIONS["export"],
        "status": "ok", "error": None, "num_frames": len(frames), "occupancy_version": version,
        "K": cam.K.reshape(-1).tolist(), "T_cam0_from_lidar": cam.T_cam_from_lidar.reshape(-1).tolist(),
        "T_base_from_lidar": calib.T_base_from_lidar.reshape(-1).tolist(),
        "image_width": cam.width, "image_height": cam.height}]
    instances = instance_rows(ctx, {int(raw): k for k, raw in enumerate(fused["frame"].tolist())},
                              calib.T_base_from_lidar)
    with sequence_writer(ctx.out_root, ctx.sequence, version) as staged:
        _link_tree(ctx.upstream["fuse"] / "occupancy.zarr", staged.store_path)
        stage_table(staged, "frames", frames)
        stage_table(staged, "sequences", sequences)
        stage_table(staged, "instances", instances)
    return {"implemented": True, "frames": len(frames), "instances": len(instances),
            "occupancy_version": version}
