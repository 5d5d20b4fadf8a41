"""export: publish the sequence into the dataset (Zarr arrays + Parquet tables, atomically).

The fused store is hard-linked (copied across file systems) from the fuse stage's key-named output
into ``OUT/occupancy/<sequence>/<version>.zarr``; the three table partitions are written aside and
published together (storage/publish.py). Dataset-level exports (Occ3D, nuScenes) run after all
sequences (flows/pipeline/run.py, ``mobileocc export``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flows.pipeline.inputs import ExportInputs
from flows.stages.common import StageContext, body_model, is_night
from storage.products import Bodies, FusedFrames, PersonVoxels, Tracks
from storage.publish import sequence_writer, stage_store, stage_table
from tasks.body.boxes import upright_box
from tasks.body.params import BodyParams
from tasks.body.posing import posed_vertices
from tasks.conventions import UNCLASSIFIED
from tasks.fit.reframe import reframe_params


def instance_rows(
    ctx: StageContext[ExportInputs], frame_pos: dict[int, int], T_base_from_lidar: np.ndarray
) -> list[dict]:
    """One row per tracked person and frame: 2D box and keypoints from track; body parameters,
    3D box and velocity (base frame) from the fit where that person was fitted; and one row per
    body the fit interpolated for a frame the track coasted over (``gap_filled``: no 2D box, no
    keypoints)."""
    tracks = Tracks.read(ctx.upstream["track"])
    fuse_dir = Path(ctx.upstream["fuse"])
    person = (
        PersonVoxels.read(fuse_dir) if (fuse_dir / f"{PersonVoxels.NAME}.npz").exists() else None
    )
    voxels = (
        {}
        if person is None
        else {
            (int(f), int(d)): (int(u), int(p))
            for f, d, u, p in zip(
                person.frame,
                person.det_index,
                person.unclassified_voxels,
                person.pedestrian_voxels_without_body,
            )
        }
    )
    bodies = Bodies.read(ctx.upstream["fit"]) if "fit" in ctx.upstream else Bodies.empty()
    fitted = {
        (int(f), int(d)): r
        for r, (f, d) in enumerate(zip(bodies.frame, bodies.det_index))
        if not bodies.gap_filled[r]
    }
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

    def body_fields(b: int) -> dict:
        vel = np.asarray(bodies.velocity_base[b], np.float64)
        known = bool(np.all(np.isfinite(vel)))  # unknown (e.g. across a track gap): null, never NaN
        box = upright_box(verts[b], base.global_orient[b], vel if known else None)
        finite = lambda x: float(x) if np.isfinite(x) else None  # noqa: E731
        return {
            "box3d_center": box.center.tolist(),
            "box3d_size": box.size.tolist(),
            "box3d_yaw": box.yaw,
            "betas": base.betas[b].tolist(),
            "global_orient": base.global_orient[b].tolist(),
            "body_pose": base.body_pose[b].tolist(),
            "transl": base.transl[b].tolist(),
            "chamfer_m": finite(bodies.chamfer_m[b]),
            "reproj_px": float(bodies.reproj_px[b]),
            "vx": float(vel[0]) if known else None,
            "vy": float(vel[1]) if known else None,
            "keypoints_mirrored": bool(bodies.mirrored[b]),
            "gap_filled": bool(bodies.gap_filled[b]),
        }

    rows = []
    for r in range(len(tracks.track_id)):
        row = {
            "track_id": int(tracks.track_id[r]),
            "frame": frame_pos[int(tracks.frame[r])],
            "box2d_xyxy": tracks.boxes_xyxy[r].tolist(),
            "keypoints": tracks.keypoints[r].reshape(-1).tolist(),
            "gap_filled": False,
        }
        counts = voxels.get((int(tracks.frame[r]), int(tracks.det_index[r])))
        if counts is not None:
            row["unclassified_voxels"], row["pedestrian_voxels_without_body"] = counts
        b = fitted.get((int(tracks.frame[r]), int(tracks.det_index[r])))
        if b is not None:
            row.update(body_fields(b))
        rows.append(row)
    for b in np.flatnonzero(bodies.gap_filled):
        if int(bodies.frame[b]) in frame_pos:
            rows.append(
                {
                    "track_id": int(bodies.track_id[b]),
                    "frame": frame_pos[int(bodies.frame[b])],
                    **body_fields(int(b)),
                }
            )
    return rows


def frame_rows(ctx: StageContext[ExportInputs], seq, fused: FusedFrames) -> list[dict]:
    """One row per frame of the fused store (the frames detect produced); where its raw data are
    (the source's ``source_paths``: files relative to the dataset root, or a log's messages)."""
    night, rows = is_night(seq), []
    for k, raw in enumerate(fused.frame.tolist()):
        paths = seq.source_paths(raw)
        rows.append(
            {
                "frame": k,
                "raw_frame": raw,
                "stamp_ns": int(fused.stamp_ns[k]),
                "T_world_from_lidar": seq.info.poses[seq.position(raw)].reshape(-1).tolist(),
                "T_world_from_base": fused.T_world_from_base[k].reshape(-1).tolist(),
                "lidar_path": paths["lidar"],
                "cam0_path": paths["cam0"],
                "cam1_path": paths["cam1"],
                "class_counts": fused.class_counts[k].tolist(),
                "unclassified_voxels": int(fused.class_counts[k][UNCLASSIFIED]),
                "is_night": night,
            }
        )
    return rows


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
