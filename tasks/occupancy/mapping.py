"""The map stage's work on a sequence, sweep by sweep (paper, "Static Map Generation").

Per sweep: image semantics lifted to the points; points in pedestrian instance masks, in LiDAR
pedestrian boxes, or labelled pedestrian removed; the rest, in the world frame, vote in the static
map and are inserted into the occupancy map (OctoMap semantics) from the sensor origin. Points the
camera sees vote in one count table, points outside the image (labelled by the fallback) in
another; the camera's table decides every voxel it has votes for and the fallback only fills the
rest (with a 360 deg LiDAR and one camera, out-of-view points are ~80 % of a sweep and would
otherwise outvote the camera). Memory grows with the mapped volume, not with the sweeps.
"""

from __future__ import annotations

import numpy as np

from tasks.conventions import PEDESTRIAN, transform_points
from tasks.occupancy.freespace import OccupancyMap
from tasks.occupancy.settings import FreeSpaceParams, MapParams
from tasks.occupancy.static_map import (StaticMap, StaticSemanticMap, lift_image_semantics,
                                        merge_static_maps, pedestrian_boxes_for_masking,
                                        pedestrian_point_mask, project_points)


def new_occupancy_map(p: FreeSpaceParams, threads: int | None = None) -> OccupancyMap:
    """An empty occupancy map with the sensor model ``p``."""
    return OccupancyMap(p.voxel_size_m, p.prob_hit, p.prob_miss, p.clamp_min, p.clamp_max,
                        p.occupancy_threshold, threads=threads)


def load_occupancy_map(p: FreeSpaceParams, keys: np.ndarray, logodds: np.ndarray) -> OccupancyMap:
    """The occupancy map stored as (keys, logodds) (storage.products.OccupancyMapProduct)."""
    return OccupancyMap.from_arrays(p.voxel_size_m, keys, logodds, prob_hit=p.prob_hit, prob_miss=p.prob_miss,
                                    clamp_min=p.clamp_min, clamp_max=p.clamp_max,
                                    occupancy_threshold=p.occupancy_threshold)


class SequenceMapper:
    """The static semantic map and the occupancy map of one sequence, fed sweep by sweep.

    class_lut: (256,) uint8 Cityscapes train id -> class id (UNLABELED: none). K (3, 3),
    T_cam_from_lidar (4, 4), width / height: the camera. assoc_min_iou: see
    :func:`pedestrian_boxes_for_masking`. State lives on the instance; ``add_sweep`` advances it.
    """

    def __init__(self, params: MapParams, freespace: FreeSpaceParams, class_lut: np.ndarray,
                 K: np.ndarray, T_cam_from_lidar: np.ndarray, width: int, height: int,
                 assoc_min_iou: float, threads: int | None = None):
        self.params, self.freespace, self.lut = params, freespace, class_lut
        self.K, self.T_cam, self.size, self.min_iou = K, T_cam_from_lidar, (width, height), assoc_min_iou
        self.seen = StaticSemanticMap(params.voxel_size_m)
        self.unseen = StaticSemanticMap(params.voxel_size_m)
        self.occupancy = new_occupancy_map(freespace, threads)
        self.threads = threads
        self.kept = self.removed = 0

    def add_sweep(self, points_lidar: np.ndarray, T_world_from_lidar: np.ndarray, semantic: np.ndarray,
                  mask_labels: np.ndarray, boxes_xyxy: np.ndarray, lidar_centers: np.ndarray,
                  lidar_sizes: np.ndarray, lidar_yaws: np.ndarray) -> None:
        """One sweep (N, 3) float32 LiDAR frame with its pose and its detections: semantic (H, W)
        Cityscapes train ids, mask_labels (H, W) instance labels (> 0: a person), image boxes
        (D, 4), LiDAR pedestrian boxes (M, 3) / (M,)."""
        p, (width, height) = self.params, self.size
        projection = project_points(points_lidar, self.K, self.T_cam, width, height)  # once per sweep
        in_image = projection[1]
        labels = lift_image_semantics(points_lidar, semantic, self.K, self.T_cam, self.lut,
                                      fallback=p.outside_image_fallback, ground_cell_m=p.ground_cell_m,
                                      ground_tol_m=p.ground_max_deviation_m,
                                      ground_lateral_scale=p.fallback_ground_lateral_scale,
                                      projection=projection, threads=self.threads)
        boxes = pedestrian_boxes_for_masking(boxes_xyxy, lidar_centers, lidar_sizes, lidar_yaws, self.K,
                                             self.T_cam, width, height, self.min_iou)
        people = pedestrian_point_mask(points_lidar, instance_image=mask_labels, boxes_lidar=boxes,
                                       box_margin_m=p.pedestrian_box_margin_m, projection=projection)
        keep = ~people & (labels != PEDESTRIAN)
        world = transform_points(T_world_from_lidar, points_lidar).astype(np.float32)
        self.seen.add_sweep(world, labels, keep=keep & in_image)
        self.unseen.add_sweep(world, labels, keep=keep & ~in_image)
        self.occupancy.insert_scan(world[keep], T_world_from_lidar[:3, 3],
                                   max_range_m=self.freespace.max_range_m,
                                   discretize=self.freespace.discretize)
        self.removed += int((~keep).sum())
        self.kept += int(keep.sum())

    def finish(self, ground_class_ids: tuple[int, ...]) -> tuple[StaticMap, StaticMap]:
        """(the final static map, the camera-labelled part of it) after the ground check and max
        voting; the occupancy map is ``self.occupancy``."""
        p = self.params
        kw = dict(ground_classes=tuple(ground_class_ids), ground_tolerance_m=p.ground_max_deviation_m,
                  ground_cell_m=p.ground_cell_m, ground_neighbourhood=p.ground_neighbourhood_cells,
                  ground_quantile=p.ground_quantile, min_votes=p.min_votes)
        camera = self.seen.finalize(**kw)
        return merge_static_maps(camera, self.unseen.finalize(**kw)), camera
