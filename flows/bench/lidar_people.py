"""The weight-free LiDAR people detector against the simulator's people, with and without
multipath returns below the road.

``mobileocc bench lidar-people --data DATA [--config CFG] [--set k=v ...] [--multipath N]
[--json J]``

For every frame (10 Hz) of every sequence under DATA (written by ``mobileocc simulate``): the
detector (tasks.perception.lidar_clusters, the config's ``detect.lidar_clusters``) on the sweep,
optionally with N multipath returns added (copies of random ground returns 1-6 m below them, seeded
by the frame). A person counts when at least ``detect.lidar_clusters.min_points`` of the sweep's
returns hit it within ``max_range_m``; a box matches a person (Hungarian, one to one) when its
centre lies within ``MATCH_M`` horizontally of the person's ground-truth box centre. Reported:
recall, precision (also of the persons and boxes whose centre lies in the benchmark grid's
x-y extent, ``fuse.grid``, base frame: ``in_grid``; a matched box outside it counts as a box
outside), the false boxes by the class of the thing they sit on (the ground truth's
point classes), the height error of the matched boxes, and for the ground model the fraction of
ground returns taken for ground and of non-ground returns taken for ground (``--ground linefit``
adds the linefit library's segmentation, if it is installed, for comparison).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

from flows.pipeline.inputs import open_sequence
from flows.pipeline.plan import selected_sequences
from storage.gt import read_frame_gt
from tasks.conventions import CLASS_NAMES
from tasks.geometry import transform_points
from tasks.perception.lidar_clusters import (
    LidarClusterParams,
    detect_pedestrians_lidar,
    ground_height,
    robust_ground_height,
)

#: a box matches a person whose ground-truth box centre is this close (horizontally), metres
MATCH_M = 0.5
#: point_class of a beam without a return (storage/GT_FORMAT.md)
NO_RETURN = 255
#: ground-truth ground: no instance (point_instance 0) and one of these classes
GROUND_CLASS_NAMES = ("road", "terrain")


def add_multipath(
    points_lidar: np.ndarray, is_ground: np.ndarray, count: int, seed: int
) -> np.ndarray:
    """points_lidar (N, 3) with ``count`` returns 1-6 m below random ground returns appended."""
    rng = np.random.default_rng(seed)
    rows = np.flatnonzero(is_ground)
    if count == 0 or rows.size == 0:
        return points_lidar
    picked = points_lidar[rng.choice(rows, count)].astype(np.float64)
    picked[:, 2] -= rng.uniform(1.0, 6.0, count)
    return np.concatenate([points_lidar, picked.astype(points_lidar.dtype)])


def _linefit(seq, seq_id: str):
    """linefit's segmenter (measurement only: not a dependency of the project) told the sensor's
    height above the ground (its one essential setting: from the first frame's ground-truth
    ground returns within 8 m)."""
    import tempfile

    from linefit import ground_seg

    from storage.atomic import atomic_write_text

    frame = seq.frame(0)
    gt = read_frame_gt(seq.root, seq_id, frame.index)
    pts = np.asarray(frame.points_lidar, np.float64)
    returned = gt.point_class != NO_RETURN
    ground_ids = [CLASS_NAMES.index(n) for n in GROUND_CLASS_NAMES]
    is_ground = (gt.point_instance[returned] == 0) & np.isin(gt.point_class[returned], ground_ids)
    near = is_ground & (np.linalg.norm(pts[:, :2], axis=1) < 8.0)
    height = -float(np.median(pts[near, 2]))
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "linefit.toml"
        atomic_write_text(path, f"[important]\nheight = {height:.3f}\n")
        return ground_seg(str(path))  # reads the file here


def _ground_rates(points, truth_ground, ground_z, tol_m):
    taken = points[:, 2] - ground_z < tol_m
    return int((taken & truth_ground).sum()), int((taken & ~truth_ground).sum())


def bench_lidar_people(config, multipath: int = 0, ground: str = "robust") -> dict:
    p: LidarClusterParams = config.detect.lidar_clusters.to(LidarClusterParams)
    ground_ids = [CLASS_NAMES.index(n) for n in GROUND_CLASS_NAMES]
    persons = matched = boxes = 0
    grid = {"persons": 0, "boxes": 0, "matched": 0}
    lo, hi = np.asarray(config.fuse.grid.range_min), np.asarray(config.fuse.grid.range_max)
    false_on: dict[str, int] = {}
    height_err: list[float] = []
    rates = {"robust": [0, 0], "minimum": [0, 0], "linefit": [0, 0]}
    ground_total = other_total = 0
    segmenter = None
    for seq_id in selected_sequences(config):
        seq = open_sequence(config, seq_id)
        if ground == "linefit":
            segmenter = _linefit(seq, seq_id)
        for i in range(seq.info.num_frames):
            frame = seq.frame(i)
            gt = read_frame_gt(seq.root, seq_id, frame.index)
            pts = np.asarray(frame.points_lidar, np.float32)
            n_real = pts.shape[0]
            returned = gt.point_class != NO_RETURN  # the reader drops the organised no-returns
            if int(returned.sum()) != n_real:
                raise ValueError(
                    f"{seq_id} frame {frame.index}: {n_real} points but the ground truth has "
                    f"{int(returned.sum())} returns"
                )
            inst, cls = gt.point_instance[returned], gt.point_class[returned]
            is_ground = (inst == 0) & np.isin(cls, ground_ids)
            pts = add_multipath(pts, is_ground, multipath, seed=[i, *seq_id.encode()])
            det = detect_pedestrians_lidar(pts, p)
            # ground model: the real returns only, within the detector's range
            near = np.linalg.norm(pts[:n_real, :2], axis=1) <= p.max_range_m
            truth = is_ground[near]
            ground_total += int(truth.sum())
            other_total += int((~truth).sum())
            for name, z in (
                (
                    "robust",
                    robust_ground_height(
                        pts, p.ground_cell_m, p.ground_percentile, p.ground_max_drop_m
                    ),
                ),
                ("minimum", ground_height(pts, p.ground_cell_m)),
            ):
                sel = np.flatnonzero(near)
                a, b = _ground_rates(pts[sel], truth, z[sel], p.ground_tol_m)
                rates[name][0] += a
                rates[name][1] += b
            if segmenter is not None:
                labels = np.asarray(segmenter.run(pts)).reshape(-1)[:n_real][near].astype(bool)
                rates["linefit"][0] += int((labels & truth).sum())
                rates["linefit"][1] += int((labels & ~truth).sum())
            # the people the sweep sees
            ids, counts = np.unique(inst[(inst > 0) & (inst < 1000) & near], return_counts=True)
            seen = ids[counts >= p.min_points]
            rows = np.flatnonzero(np.isin(gt.track_id, seen))
            persons += rows.size
            boxes += len(det)
            used = np.zeros(len(det), bool)
            T_base_from_lidar = np.linalg.inv(gt.T_world_from_base) @ gt.T_world_from_lidar

            def in_grid(centres_lidar):
                base = transform_points(T_base_from_lidar, np.asarray(centres_lidar, np.float64))
                return np.all((base[:, :2] >= lo[:2]) & (base[:, :2] < hi[:2]), axis=1)

            person_in = in_grid(gt.box_center[rows].reshape(-1, 3))
            box_in = in_grid(det.centers.reshape(-1, 3))
            grid["persons"] += int(person_in.sum())
            grid["boxes"] += int(box_in.sum())
            if rows.size and len(det):
                d = np.linalg.norm(gt.box_center[rows, None, :2] - det.centers[None, :, :2], axis=2)
                r, c = linear_sum_assignment(np.where(d <= MATCH_M, d, 1e6))
                ok = d[r, c] <= MATCH_M
                matched += int(ok.sum())
                grid["matched"] += int((ok & person_in[r]).sum())
                used[c[ok]] = True
                height_err.extend((det.sizes[c[ok], 2] - gt.box_size[rows[r[ok]], 2]).tolist())
            for k in np.flatnonzero(~used):  # what the false box sits on
                centre = det.centers[k, :2]
                close = np.linalg.norm(pts[:n_real, :2] - centre, axis=1) < 0.3
                close &= inst != 0
                name = CLASS_NAMES[np.bincount(cls[close]).argmax()] if close.any() else "nothing"
                false_on[name] = false_on.get(name, 0) + 1
    err = np.abs(np.asarray(height_err))
    return {
        "multipath_per_sweep": multipath,
        "persons": persons,
        "boxes": boxes,
        "matched": matched,
        "recall": matched / max(persons, 1),
        "precision": matched / max(boxes, 1),
        "false_boxes_on": dict(sorted(false_on.items())),
        "height_abs_err_median_m": float(np.median(err)) if err.size else float("nan"),
        "in_grid": {
            **grid,
            "recall": grid["matched"] / max(grid["persons"], 1),
            "precision": grid["matched"] / max(grid["boxes"], 1),
        },
        "ground": {
            name: {
                "ground_taken": v[0] / max(ground_total, 1),
                "non_ground_taken": v[1] / max(other_total, 1),
            }
            for name, v in rates.items()
            if name != "linefit" or segmenter is not None
        },
    }
