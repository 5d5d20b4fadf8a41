"""map: the human-free static semantic map and the free / unknown occupancy map of a sequence.

Sequential over frames (both maps accumulate). Per sweep: image semantics lifted to the points;
points in pedestrian instance masks, in LiDAR pedestrian boxes, or labelled pedestrian removed; the
rest, in the world frame, vote in the static map and are inserted into the occupancy map (OctoMap
semantics) from the sensor origin. Memory grows with the mapped volume, not with the frames.

Points the camera sees vote in one count table, points outside the image (labelled by the
configured fallback) in another; the camera's table decides every voxel it has votes for and the
fallback only fills the rest (with a 360 deg LiDAR and one camera, out-of-view points are ~80 % of a
sweep and would otherwise outvote the camera).

Product ``static_map.npz``: voxel_size_m (), keys (K, 3) int64 (voxel [k, k + 1) * voxel_size_m,
world frame), labels (K,) uint8, counts (K, 9) uint16. Product ``occupancy.npz``: voxel_size_m (),
keys (M, 3) int64, logodds (M,) float32 (OctoMap log-odds; unknown voxels are absent).
"""

from __future__ import annotations

import numpy as np

from configs.schema import Config
from flows.stages.common import StageContext
from storage.intermediate import read_product, write_product
from tasks.conventions import PEDESTRIAN, UNLABELED, transform_points
from tasks.occupancy.freespace import OccupancyMap
from tasks.occupancy.static_map import (StaticSemanticMap, lift_image_semantics, merge_static_maps,
                                        pedestrian_boxes_for_masking, pedestrian_point_mask,
                                        project_points)


def class_lut(config: Config) -> np.ndarray:
    """(256,) uint8 Cityscapes train id -> our class id, UNLABELED where the config maps nothing."""
    lut = np.full(256, UNLABELED, np.uint8)
    for cs_id, name in config.map.cityscapes_to_class.items():
        lut[cs_id] = config.class_id(name)
    return lut


def occupancy_params(config: Config) -> dict:
    fs = config.map.freespace
    return {"prob_hit": fs.prob_hit, "prob_miss": fs.prob_miss, "clamp_min": fs.clamp_min,
            "clamp_max": fs.clamp_max, "occupancy_threshold": fs.occupancy_threshold}


def run_map(ctx: StageContext) -> dict:
    cfg = ctx.config.map
    seq = ctx.open()
    cam = seq.info.calibration.cameras[ctx.config.dataset.camera]
    lut = class_lut(ctx.config)
    # camera-labelled votes decide the voxels the camera saw; fallback labels fill the rest
    seen, unseen = StaticSemanticMap(cfg.voxel_size_m), StaticSemanticMap(cfg.voxel_size_m)
    occupancy = OccupancyMap(cfg.freespace.voxel_size_m, **occupancy_params(ctx.config))
    removed = kept = 0
    for i in range(len(seq)):
        frame = seq.frame(i)
        pts = frame.points_lidar
        det = read_product(ctx.upstream["detect"], f"frame_{frame.index}")
        projection = project_points(pts, cam.K, cam.T_cam_from_lidar, cam.width, cam.height)
        in_image = projection[1]
        labels = lift_image_semantics(pts, det["semantic"], cam.K, cam.T_cam_from_lidar, lut,
                                      fallback=cfg.outside_image_fallback, ground_cell_m=cfg.ground_cell_m,
                                      ground_tol_m=cfg.ground_max_deviation_m,
                                      ground_lateral_scale=cfg.fallback_ground_lateral_scale,
                                      projection=projection)
        boxes = pedestrian_boxes_for_masking(
            det["boxes_xyxy"], det["lidar_centers"], det["lidar_sizes"], det["lidar_yaws"], cam.K,
            cam.T_cam_from_lidar, cam.width, cam.height, ctx.config.track.person_points.assoc_min_iou)
        people = pedestrian_point_mask(pts, instance_image=det["mask_labels"], boxes_lidar=boxes,
                                       box_margin_m=cfg.pedestrian_box_margin_m, projection=projection)
        keep = ~people & (labels != PEDESTRIAN)
        T = frame.T_world_from_lidar
        world = transform_points(T, pts).astype(np.float32)
        seen.add_sweep(world, labels, keep=keep & in_image)
        unseen.add_sweep(world, labels, keep=keep & ~in_image)
        occupancy.insert_scan(world[keep], T[:3, 3], max_range_m=cfg.freespace.max_range_m,
                              discretize=cfg.freespace.discretize)
        removed += int((~keep).sum())
        kept += int(keep.sum())
    finalize = dict(
        ground_classes=tuple(ctx.config.class_id(c) for c in cfg.ground_classes),
        ground_tolerance_m=cfg.ground_max_deviation_m, ground_cell_m=cfg.ground_cell_m,
        ground_neighbourhood=cfg.ground_neighbourhood_cells, ground_quantile=cfg.ground_quantile,
        min_votes=cfg.min_votes)
    camera_map = seen.finalize(**finalize)
    final = merge_static_maps(camera_map, unseen.finalize(**finalize))
    write_product(ctx.out_dir, "static_map", {
        "voxel_size_m": np.float64(cfg.voxel_size_m), "keys": final.keys, "labels": final.labels,
        "counts": final.counts})
    keys, logodds = occupancy.to_arrays()
    write_product(ctx.out_dir, "occupancy", {
        "voxel_size_m": np.float64(cfg.freespace.voxel_size_m), "keys": keys, "logodds": logodds})
    return {"implemented": True, "static_voxels": int(len(final.keys)),
            "camera_labelled_voxels": int(len(camera_map.keys)),
            "occupancy_voxels": int(len(keys)), "points_kept": kept, "points_removed": removed,
            "ground_votes_rejected": int(final.ground_rejected)}
