"""export: publish the sequence into the dataset (Zarr arrays + Parquet tables, atomically).

The fused store is hard-linked (copied across file systems) from the fuse stage's key-named output
into ``OUT/occupancy/<sequence>/<version>.zarr``; the three table partitions are written aside and
published together (storage/publish.py). Dataset-level exports (Occ3D, nuScenes) run after all
sequences (flows/pipeline/run.py, ``mobileocc export``).
"""

from __future__ import annotations

import numpy as np

from flows.pipeline.inputs import ExportInputs
from flows.stages.common import StageContext, body_model, is_night
from storage.export.common import source_relative
from storage.products import Bodies, FusedFrames, Tracks
from storage.publish import sequence_writer, stage_store, stage_table
from tasks.body.boxes import upright_box
from tasks.body.params import BodyParams
from tasks.body.posing import posed_vertices
from tasks.fit.reframe import reframe_params


def instance_rows(
    ctx: StageContext[ExportInputs], frame_pos: dict[int, int], T_base_from_lidar: np.ndarray
) -> list[dict]:
    """One row per tracked person and frame: 2D box and keypoints from track; body parameters,
    3D box and velocity (base frame) from the fit where that person was fitted."""
    tracks = Tracks.read(ctx.upstream["track"])
    bodies = Bodies.read(ctx.upstream["fit"]) if "fit" in ctx.upstream else Bodies.empty()
    fitted = {(int(f), int(d)): r for r, (f, d) in enumerate(zip(bodies.frame, bodies.det_index))}
    base = reframe_params(
        body_model(ctx.inputs.body, ctx.out_root),
        BodyParams.of(bodies),
        T_base_from_lidar,
    )
    verts = posed_vertices(
        body_model(ctx.inputs.body, ctx.out_root),
        base.betas,
        base.global_orient,
        base.body_pose,
        base.transl,
    )
    rows = []
    for r in range(len(tracks.track_id)):
        row = {
            "track_id": int(tracks.track_id[r]),
            "frame": frame_pos[int(tracks.frame[r])],
            "box2d_xyxy": tracks.boxes_xyxy[r].tolist(),
            "keypoints": tracks.keypoints[r].reshape(-1).tolist(),
        }
        b = fitted.get((int(tracks.frame[r]), int(tracks.det_index[r])))
        if b is not None:
            vel = np.asarray(bodies.velocity_base[b], np.float64)
            known = bool(
                np.all(np.isfinite(vel))
            )  # unknown (e.g. across a track gap): null, never NaN
            box = upright_box(verts[b], base.global_orient[b], vel if known else None)
            row.update(
                {
                    "box3d_center": box.center.tolist(),
                    "box3d_size": box.size.tolist(),
                    "box3d_yaw": box.yaw,
                    "betas": base.betas[b].tolist(),
                    "global_orient": base.global_orient[b].tolist(),
                    "body_pose": base.body_pose[b].tolist(),
                    "transl": base.transl[b].tolist(),
                    "chamfer_m": float(bodies.chamfer_m[b]),
                    "reproj_px": float(bodies.reproj_px[b]),
                    "vx": float(vel[0]) if known else None,
                    "vy": float(vel[1]) if known else None,
                }
            )
        rows.append(row)
    return rows


def frame_rows(ctx: StageContext[ExportInputs], seq, fused: FusedFrames) -> list[dict]:
    """One row per frame of the fused store (the frames detect produced); source paths relative
    to the dataset root."""
    night, cams = is_night(seq), seq.info.calibration.cameras

    def rel(path):
        return source_relative(path, seq.root)

    return [
        {
            "frame": k,
            "raw_frame": raw,
            "stamp_ns": int(fused.stamp_ns[k]),
            "T_world_from_lidar": seq.info.poses[seq.position(raw)].reshape(-1).tolist(),
            "T_world_from_base": fused.T_world_from_base[k].reshape(-1).tolist(),
            "lidar_path": rel(seq.path(seq.lidar_source, "os1", raw, ".bin")),
            "cam0_path": rel(seq.image_path("cam0", raw)) if "cam0" in cams else "",
            "cam1_path": rel(seq.image_path("cam1", raw)) if "cam1" in cams else None,
            "class_counts": fused.class_counts[k].tolist(),
            "is_night": night,
        }
        for k, raw in enumerate(fused.frame.tolist())
    ]


def run_export(ctx: StageContext[ExportInputs]) -> dict:
    seq = ctx.open()
    calib = seq.info.calibration
    cam = calib.cameras[ctx.inputs.source.camera]
    fused = FusedFrames.read(ctx.upstream["fuse"])
    frames = frame_rows(ctx, seq, fused)
    sequences = [
        {
            "fingerprint": ctx.fingerprint,
            "config_hash": ctx.inputs.content_hash,
            "code_version": ctx.inputs.code_version,
            "status": "ok",
            "error": None,
            "num_frames": len(frames),
            "occupancy_version": ctx.key,
            "K": cam.K.reshape(-1).tolist(),
            "T_cam0_from_lidar": cam.T_cam_from_lidar.reshape(-1).tolist(),
            "T_base_from_lidar": calib.T_base_from_lidar.reshape(-1).tolist(),
            "image_width": cam.width,
            "image_height": cam.height,
        }
    ]
    instances = instance_rows(
        ctx, {int(raw): k for k, raw in enumerate(fused.frame.tolist())}, calib.T_base_from_lidar
    )
    with sequence_writer(ctx.out_root, ctx.sequence, ctx.key) as staged:
        stage_store(staged, ctx.upstream["fuse"] / "occupancy.zarr")
        stage_table(staged, "frames", frames)
        stage_table(staged, "sequences", sequences)
        stage_table(staged, "instances", instances)
    return {
        "implemented": True,
        "frames": len(frames),
        "instances": len(instances),
        "occupancy_version": ctx.key,
    }
