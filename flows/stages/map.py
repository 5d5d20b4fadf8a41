"""map: the human-free static semantic map and the free / unknown occupancy map of a sequence.

Sequential over frames (both maps accumulate): tasks/occupancy/mapping.py. Products:
:class:`storage.products.StaticMapProduct` and :class:`storage.products.OccupancyMapProduct`.
"""

from __future__ import annotations

import numpy as np

from flows.stages.common import StageContext, detected_positions
from storage.products import Detections, OccupancyMapProduct, StaticMapProduct
from tasks.conventions import UNLABELED
from tasks.occupancy.mapping import SequenceMapper


def run_map(ctx: StageContext) -> dict:
    inp, seq = ctx.inputs, ctx.open()
    cam = seq.info.calibration.cameras[inp.source.camera]
    lut = np.full(256, UNLABELED, np.uint8)
    lut[[k for k, _ in inp.class_lut]] = [v for _, v in inp.class_lut]
    mapper = SequenceMapper(inp.settings, inp.freespace, lut, cam.K, cam.T_cam_from_lidar, cam.width,
                            cam.height, inp.assoc_min_iou, threads=ctx.runtime.threads)
    for i in detected_positions(ctx, seq):
        frame = seq.frame(i)
        d = Detections.read(ctx.upstream["detect"], Detections.file_name(frame.index))
        mapper.add_sweep(frame.points_lidar, frame.T_world_from_lidar, d.semantic, d.mask_labels,
                         d.boxes_xyxy, d.lidar_centers, d.lidar_sizes, d.lidar_yaws)
    final, camera = mapper.finish(inp.ground_class_ids)
    StaticMapProduct(np.array(final.voxel_size_m, np.float64), final.keys, final.labels, final.counts).write(ctx.out_dir)
    keys, logodds = mapper.occupancy.to_arrays()
    OccupancyMapProduct(np.array(inp.freespace.voxel_size_m, np.float64), keys, logodds).write(ctx.out_dir)
    return {"implemented": True, "static_voxels": int(len(final.keys)),
            "camera_labelled_voxels": int(len(camera.keys)), "occupancy_voxels": int(len(keys)),
            "points_kept": mapper.kept, "points_removed": mapper.removed,
            "ground_votes_rejected": int(final.ground_rejected)}
