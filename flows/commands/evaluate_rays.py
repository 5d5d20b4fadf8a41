"""RayIoU / OccScore for ``mobileocc evaluate`` (tasks/metrics/rayiou.py has the definition).

Per published frame: the query rays from the LiDAR positions of the sequence's published frames
(frames table ``T_world_from_lidar``) around the frame (``ray_origins``), cast through the
published ``semantics`` and the ground-truth occupancy (full grids, no masks, as the reference),
flow = the store's ``velocity`` against each GT person's velocity on its voxels. Counts add over
frames and sequences; the results sections are ``ray_iou`` ({sequence and "all": RayIoU,
RayIoU@1/2/4 m, mAVE, OccScore, rays}), ``ray_iou_per_class`` and ``ray_ave_per_class``.
"""

from __future__ import annotations

import numpy as np

from tasks.metrics.rayiou import (
    RayCounts,
    RayIoUSettings,
    frame_ray_counts,
    lidar_ray_directions,
    ray_origins,
)


class SequenceRays:
    """Ray counts of one sequence: ``add`` per frame, ``counts`` summed."""

    def __init__(self, frames_table, range_min, range_max, voxel_size_m: float):
        rows = frames_table.to_pylist()
        self.T_world_from_base = [np.asarray(r["T_world_from_base"]).reshape(4, 4) for r in rows]
        self.sensors_world = np.array(
            [np.asarray(r["T_world_from_lidar"]).reshape(4, 4)[:3, 3] for r in rows]
        ).reshape(-1, 3)
        self.range_min, self.range_max = range_min, range_max
        self.voxel_size_m = voxel_size_m
        self.settings = RayIoUSettings()
        self.directions = lidar_ray_directions(self.settings.azimuth_step_deg)
        self.counts = RayCounts(self.settings.thresholds_m)

    def add(self, k: int, pred, gt, pred_flow, gt_flow) -> None:
        """Frame position ``k`` of the sequence: (X, Y, Z) class grids and (X, Y, Z, 2) flows."""
        origins = ray_origins(
            self.T_world_from_base[k],
            self.sensors_world,
            k,
            self.range_min,
            self.range_max,
            self.settings,
        )
        self.counts = self.counts + frame_ray_counts(
            pred,
            gt,
            origins,
            self.range_min,
            self.voxel_size_m,
            pred_flow,
            gt_flow,
            self.settings,
            self.directions,
        )


def ray_sections(per_sequence: dict[str, SequenceRays]) -> dict:
    """The results sections (module doc); {} when no sequence was evaluated."""
    if not per_sequence:
        return {}
    total = RayCounts(RayIoUSettings().thresholds_m)
    for s in per_sequence.values():
        total = total + s.counts
    scores = {name: s.counts.scores() for name, s in per_sequence.items()}
    scores["all"] = total.scores()
    brief = {
        name: {k: v for k, v in sc.items() if not isinstance(v, dict)}
        for name, sc in scores.items()
    }
    return {
        "ray_iou": brief,
        "ray_iou_per_class": scores["all"]["per_class_iou"],
        "ray_ave_per_class": {
            "all": {f"{c} (m/s)": v for c, v in scores["all"]["per_class_ave"].items()}
        },
    }
