"""fuse: per frame, the robot-local grid: pedestrians over static, free / unknown, masks, velocity.

Frames fan out in chunks aligned to the Zarr store's write units (one writer per chunk). Output:
``occupancy.zarr`` (storage/occupancy_store.py, documented in storage/SCHEMA.md) and product
``frames.npz``: frame (F,) int64 raw frame numbers, stamp_ns (F,), class_counts (F, 10) int64,
T_world_from_base (F, 4, 4).

mask_lidar is the union of this frame's LiDAR rays (traversed or hit voxels) and the voxels the
sequence's occupancy map has observed (known free or occupied), so "unknown" means never observed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from configs.schema import Config, config_hash
from flows.parallel import fan_out
from flows.plan import CODE_VERSIONS, open_sequence
from flows.stages.common import StageContext
from flows.stages.fit import body_model
from flows.stages.map import occupancy_params
from storage.gt import read_frame_gt, read_sequence_gt
from storage.intermediate import read_product, write_product
from storage.occupancy_store import create_store, write_frames
from tasks.occupancy.freespace import OccupancyMap
from tasks.occupancy.fuse import CameraView, PedestrianMesh, fuse_frame
from tasks.occupancy.grid import GridSpec
from tasks.conventions import transform_points
from tasks.occupancy.resample import static_in_grid
from tasks.occupancy.static_map import StaticMap


def grid_spec(config: Config) -> GridSpec:
    g = config.fuse.grid
    return GridSpec(tuple(g.range_min), tuple(g.range_max), g.voxel_size_m)


def _gt_people(root: Path, sequence: str, frame: int, faces: np.ndarray,
               T_base_from_lidar: np.ndarray, min_points: int) -> list[PedestrianMesh]:
    gt = read_frame_gt(root, int(sequence), frame)
    returns = np.array([(gt.point_instance == t).sum() for t in gt.track_id], np.int64)
    observed = (returns >= min_points) & (gt.visible_fraction > 0) if min_points else returns >= 0
    return [PedestrianMesh(int(tid), transform_points(T_base_from_lidar, gt.vertices[k]), faces,
                           gt.velocity_base[k]) for k, tid in enumerate(gt.track_id) if observed[k]]


def _fit_people(model, bodies: dict, frame: int, T_base_from_lidar: np.ndarray) -> list[PedestrianMesh]:
    rows = np.flatnonzero(bodies["frame"] == frame)
    if rows.size == 0:
        return []
    t = {k: torch.as_tensor(bodies[k][rows]) for k in ("betas", "global_orient", "body_pose", "transl")}
    with torch.no_grad():
        vertices = model(t["betas"], t["global_orient"], t["body_pose"], t["transl"]).vertices.numpy()
    faces = np.asarray(model.faces)
    return [PedestrianMesh(int(bodies["track_id"][r]), transform_points(T_base_from_lidar, vertices[k]), faces,
                           bodies["velocity_base"][r]) for k, r in enumerate(rows)]


def fuse_chunk(config: Config, sequence: str, positions: list[int], store: Path,
               map_dir: Path, fit_dir: Path | None) -> list[dict]:
    seq = open_sequence(config, sequence)
    calib = seq.info.calibration
    cam = calib.cameras[config.dataset.camera]
    T_base_from_lidar = calib.T_base_from_lidar
    spec = grid_spec(config)
    static = read_product(map_dir, "static_map")
    smap = StaticMap(float(static["voxel_size_m"]), static["keys"], static["labels"], static["counts"], 0)
    occ = read_product(map_dir, "occupancy")
    occupancy = OccupancyMap.from_arrays(float(occ["voxel_size_m"]), occ["keys"], occ["logodds"],
                                         **occupancy_params(config))
    camera = CameraView(cam.K, cam.width, cam.height, T_base_from_lidar @ np.linalg.inv(cam.T_cam_from_lidar))
    if config.fuse.body_source == "ground-truth":
        faces = read_sequence_gt(seq.root, int(sequence)).person_faces
    else:
        bodies = read_product(fit_dir, "bodies") if fit_dir is not None else None
        model = body_model(config)
    reach = float(np.linalg.norm(np.abs(np.array([spec.range_min, spec.range_max])).max(axis=0)[:2])) + 1.0
    stacks: dict[str, list] = {k: [] for k in ("semantics", "instances", "mask_lidar", "mask_camera", "velocity")}
    rows = []
    for i in positions:
        frame = seq.frame(i)
        T_world_from_base = frame.T_world_from_lidar @ np.linalg.inv(T_base_from_lidar)
        static_pts, static_labels = static_in_grid(smap, spec, T_world_from_base, reach)
        if config.fuse.body_source == "ground-truth":
            people = _gt_people(seq.root, sequence, frame.index, faces, T_base_from_lidar,
                                config.fuse.gt_min_points)
        else:
            people = (_fit_people(model, bodies, frame.index, T_base_from_lidar)
                      if bodies is not None else [])
        grids = fuse_frame(spec, T_world_from_base, static_points_world=static_pts,
                           static_labels=static_labels, pedestrians=people, occupancy=occupancy,
                           lidar_points_base=transform_points(T_base_from_lidar, frame.points_lidar),
                           lidar_origin_base=T_base_from_lidar[:3, 3],
                           camera=camera if config.fuse.camera_mask else None,
                           pixel_stride=config.fuse.camera_pixel_stride,
                           camera_method=config.fuse.camera_method)
        mask_lidar = (grids.mask_lidar.astype(bool) | (grids.occupancy_state >= 0)).astype(np.uint8)
        for name, value in (("semantics", grids.semantics), ("instances", grids.instances),
                            ("mask_lidar", mask_lidar), ("mask_camera", grids.mask_camera),
                            ("velocity", grids.velocity.astype(np.float16))):
            stacks[name].append(value)
        rows.append({"frame": frame.index, "stamp_ns": frame.stamp_ns,
                     "counts": np.bincount(grids.semantics.reshape(-1), minlength=10).tolist(),
                     "T_world_from_base": T_world_from_base.tolist(), "people": len(people)})
    write_frames(store, positions[0], {k: np.stack(v) for k, v in stacks.items()})
    return rows


def run_fuse(ctx: StageContext) -> dict:
    cfg = ctx.config
    n = len(ctx.open())
    spec = grid_spec(cfg)
    fit_dir = ctx.upstream.get("fit")
    fit_ready = fit_dir is not None and (fit_dir / "bodies.npz").exists()
    store = ctx.out_dir / "occupancy.zarr"
    layout = create_store(store, n, spec.shape, cfg.output.frames_per_chunk, {
        "range_min": list(spec.range_min), "range_max": list(spec.range_max),
        "voxel_size_m": spec.voxel_size_m, "config_hash": config_hash(cfg, content_only=True),
        "code_version": CODE_VERSIONS["fuse"], "sequence": ctx.sequence,
        "body_source": cfg.fuse.body_source})
    units = [list(range(a, b)) for a, b in layout.write_units()]
    parts = fan_out(fuse_chunk, [(cfg, ctx.sequence, u, store, ctx.upstream["map"],
                                  fit_dir if fit_ready else None) for u in units])
    rows = [r for part in parts for r in part]
    write_product(ctx.out_dir, "frames", {
        "frame": np.array([r["frame"] for r in rows], np.int64),
        "stamp_ns": np.array([r["stamp_ns"] for r in rows], np.int64),
        "class_counts": np.array([r["counts"] for r in rows], np.int64),
        "T_world_from_base": np.array([r["T_world_from_base"] for r in rows], np.float64)})
    summary = {"implemented": True, "frames": len(rows), "grid_shape": list(spec.shape),
               "voxel_size_m": spec.voxel_size_m, "body_source": cfg.fuse.body_source,
               "pedestrian_meshes": sum(r["people"] for r in rows)}
    if cfg.fuse.body_source == "fit" and not fit_ready:
        summary["note"] = "no pedestrian bodies: the fit stage produced none"
    return summary
