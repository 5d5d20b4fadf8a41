"""map: the human-free static semantic map and the free / unknown occupancy map of a sequence.

Sequential over frames (both maps accumulate). Per sweep: image semantics lifted to the points;
points in pedestrian instance masks, in LiDAR pedestrian boxes, or labelled pedestrian removed; the
rest, in the world frame, vote in the static map and are inserted into the occupancy map (OctoMap
semantics) from the sensor origin. Memory grows with the mapped volume, not with the frames.

Product ``static_map.npz``: voxel_size_m (), keys (K, 3) int64 (voxel [k, k + 1) * voxel_size_m,
world frame), labels (K,) uint8, counts (K, 9) uint16. Product ``occupancy.npz``: voxel_size_m (),
keys (M, 3) int64, logodds (M,) float32 (OctoMap log-odds; unknown voxels are absent).
"""

from __future__ import annotations

import numpy as np

from configs.schema import Config
from flows.stages.common import StageContext
from storage.intermediate import read_product, write_product
from tasks.conventions import PEDESTRIAN, UNLABELED
from tasks.occupancy.freespace import OccupancyMap
from tasks.occupancy.static_map import (StaticSemanticMap, lift_image_semantics,
                                        pedestrian_point_mask)


def class_lut(config: Config) -> np.ndarray:
    """(256,) uint8 Cityscapes train id -> our class id, UNLABELED where the config maps nothing."""
    lut = np.full(256, UNLABELED, np.uint8)
    for cs_id, name in config.map.cityscapes_to_class.items():
        lut[cs_id] = config.class_id(name)
    return lut


def occupancy_map(config: Config) -> OccupancyMap:
    fs = config.map.freespace
    return OccupancyMap(config.map.voxel_size_m, prob_hit=fs.prob_hit, prob_miss=fs.prob_miss,
                        clamp_min=fs.clamp_min, clamp_max=fs.clamp_max)


def run_map(ctx: StageContext) -> dict:
    cfg = ctx.config.map
    seq = ctx.open()
    cam = seq.info.calibration.cameras[ctx.config.dataset.camera]
    lut = class_lut(ctx.config)
    static = StaticSemanticMap(cfg.voxel_size_m)
    occupancy = occupancy_map(ctx.config)
    removed = kept = 0
    for i in range(len(seq)):
        frame = seq.frame(i)
        det = read_product(ctx.upstream["detect"], f"frame_{frame.index}")
        labels = lift_image_semantics(frame.points_lidar, det["semantic"], cam.K, cam.T_cam_from_lidar,
                                      lut, fallback=cfg.outside_image_fallback)
        boxes = np.column_stack([det["lidar_centers"], det["lidar_sizes"], det["lidar_yaws"]])
        people = pedestrian_point_mask(frame.points_lidar, K=cam.K, T_cam_from_lidar=cam.T_cam_from_lidar,
                                       instance_image=det["mask_labels"], boxes_lidar=boxes,
                                       box_margin_m=cfg.pedestrian_box_margin_m)
        keep = ~people & (labels != PEDESTRIAN)
        T = frame.T_world_from_lidar
        world = (frame.points_lidar.astype(np.float64) @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
        static.add_sweep(world, labels, keep=keep)
        occupancy.insert_scan(world[keep], T[:3, 3], max_range_m=cfg.freespace.max_range_m)
        removed += int((~keep).sum())
        kept += int(keep.sum())
    final = static.finalize(ground_tolerance_m=cfg.ground_max_deviation_m)
    write_product(ctx.out_dir, "static_map", {
        "voxel_size_m": np.float64(cfg.voxel_size_m), "keys": final.keys, "labels": final.labels,
        "counts": final.counts})
    keys, logodds = occupancy.to_arrays()
    write_product(ctx.out_dir, "occupancy", {
        "voxel_size_m": np.float64(cfg.voxel_size_m), "keys": keys, "logodds": logodds})
    return {"implemented": True, "static_voxels": int(len(final.keys)),
            "occupancy_voxels": int(len(keys)), "points_kept": kept, "points_removed": removed,
            "ground_votes_rejected": int(final.ground_rejected)}
