"""export: publish the sequence into the dataset (Zarr arrays + Parquet tables, atomically).

The fused store is hard-linked (copied across file systems) from the fuse stage's key-named output
into ``OUT/occupancy/<sequence>/<version>.zarr``; the three table partitions are written aside and
published together (storage/occupancy_store.py, storage/tables.py). Dataset-level exports (Occ3D,
nuScenes) run after all sequences (flows/pipeline.py, ``mobileocc export``).
"""

from __future__ import annotations

import os
import shutil

from configs.schema import config_hash
from flows.plan import CODE_VERSIONS
from flows.stages.common import StageContext, is_night
from storage.intermediate import read_product
from storage.manifest import FileHasher, sequence_fingerprint
from storage.occupancy_store import sequence_writer
from storage.tables import stage_table


def _link_tree(src, dst) -> None:
    def link(a, b):
        try:
            os.link(a, b)
        except OSError:
            shutil.copy2(a, b)
    shutil.copytree(src, dst, copy_function=link, dirs_exist_ok=True)


def instance_rows(ctx: StageContext, frame_pos: dict[int, int]) -> list[dict]:
    """One row per tracked person and frame; body fields stay null until the fit stage fills them."""
    tracks = read_product(ctx.upstream["track"], "tracks")
    rows = []
    for r in range(len(tracks["track_id"])):
        rows.append({
            "track_id": int(tracks["track_id"][r]), "frame": frame_pos[int(tracks["frame"][r])],
            "box2d_xyxy": tracks["boxes_xyxy"][r].tolist(),
            "keypoints": tracks["keypoints"][r].reshape(-1).tolist()})
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
        frame_paths = {c: seq.image_path(c, raw) for c in calib.cameras}
        frames.append({
            "frame": k, "raw_frame": raw, "stamp_ns": int(fused["stamp_ns"][k]),
            "T_world_from_lidar": info.poses[k].reshape(-1).tolist(),
            "T_world_from_base": fused["T_world_from_base"][k].reshape(-1).tolist(),
            "lidar_path": str(seq.path(seq.lidar_source, "os1", raw, ".bin")),
            "cam0_path": str(frame_paths.get("cam0", "")),
            "cam1_path": str(frame_paths["cam1"]) if "cam1" in frame_paths else None,
            "class_counts": fused["class_counts"][k].tolist(), "is_night": night})
    sequences = [{
        "fingerprint": sequence_fingerprint(info.root, info.files, FileHasher(None)),
        "config_hash": config_hash(ctx.config, content_only=True), "code_version": CODE_VERSIONS["export"],
        "status": "ok", "error": None, "num_frames": len(frames), "occupancy_version": version,
        "K": cam.K.reshape(-1).tolist(), "T_cam0_from_lidar": cam.T_cam_from_lidar.reshape(-1).tolist(),
        "T_base_from_lidar": calib.T_base_from_lidar.reshape(-1).tolist(),
        "image_width": cam.width, "image_height": cam.height}]
    instances = instance_rows(ctx, {int(raw): k for k, raw in enumerate(fused["frame"].tolist())})
    with sequence_writer(ctx.out_root, ctx.sequence, version) as staged:
        _link_tree(ctx.upstream["fuse"] / "occupancy.zarr", staged.store_path)
        stage_table(staged, "frames", frames)
        stage_table(staged, "sequences", sequences)
        stage_table(staged, "instances", instances)
    return {"implemented": True, "frames": len(frames), "instances": len(instances),
            "occupancy_version": version}
