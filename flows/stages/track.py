"""track: OC-SORT ids over a sequence's 2D detections, and each tracked person's LiDAR points.

Ids come from tasks.track.offline.track_offline (OC-SORT, then back-fill, and with
``track.world_check`` the tracks cut and re-stitched on each person's world position, the median of
its LiDAR points, over the whole sequence, as the track config says).

Product ``tracks.npz`` (one row per tracked detection, frames ascending): frame (R,) int64 raw frame
number, det_index (R,) row in that frame's detect product, track_id (R,) int64 (>= 1),
boxes_xyxy (R, 4), scores (R,), keypoints (R, 17, 3), lidar_box (R,) int64 matched LiDAR box row or
-1, gt_index (R,) int64 (the detection's ground-truth row with the oracle provider, else -2),
points_offsets (R + 1,) int64 and points_index (sum,) int64: the person's points are
``points_index[points_offsets[r]:points_offsets[r + 1]]``, indices into the frame's
``points_lidar`` as the reader returns it; points_in_image (R,) int64: the first
``points_in_image[r]`` of them project into the image, the rest were found past its left / right
side on LiDAR geometry (tasks.perception.person_points step 4; the body fit takes the first part).
"""

from __future__ import annotations

import numpy as np

from flows.stages.common import StageContext
from storage.intermediate import labels_to_masks, read_product, write_product
from tasks.conventions import transform_points
from tasks.perception.person_points import (
    associate_lidar_boxes,
    in_image_first,
    person_point_indices,
)
from tasks.track.ocsort import PedestrianTracker
from tasks.track.offline import WorldMotion, track_offline


def run_track(ctx: StageContext) -> dict:
    cfg = ctx.config.track
    seq = ctx.open()
    cam = seq.info.calibration.cameras[ctx.config.dataset.camera]
    tracker = PedestrianTracker(det_thresh=cfg.det_thresh, max_age=cfg.max_age, min_hits=cfg.min_hits,
                                iou_threshold=cfg.iou_threshold, delta_t=cfg.delta_t,
                                inertia=cfg.inertia, keep_confirmed_ids=cfg.keep_confirmed_ids)
    pp = cfg.person_points.model_dump()
    min_iou = pp.pop("assoc_min_iou")
    # every detection's person points first: their world positions let the offline refinement
    # check the 2D tracker's identities (a person's points do not depend on its id)
    per_frame = []
    for i in range(len(seq)):
        frame = seq.frame(i)
        det = read_product(ctx.upstream["detect"], f"frame_{frame.index}")
        boxes = det["boxes_xyxy"]
        lidar_box = associate_lidar_boxes(boxes, det["lidar_centers"], det["lidar_sizes"],
                                          det["lidar_yaws"], cam.K, cam.T_cam_from_lidar, min_iou)
        expected = np.full(len(boxes), np.nan)
        has = lidar_box >= 0
        if has.any():
            centers = det["lidar_centers"][lidar_box[has]].astype(np.float64)
            cam_xyz = centers @ cam.T_cam_from_lidar[:3, :3].T + cam.T_cam_from_lidar[:3, 3]
            expected[has] = np.linalg.norm(cam_xyz, axis=1)
        masks = labels_to_masks(det["mask_labels"], len(det["scores"]))
        point_sets = person_point_indices(frame.points_lidar, cam.K, cam.T_cam_from_lidar,
                                          (cam.width, cam.height), boxes, masks, expected, **pp)
        point_sets, in_image = in_image_first(frame.points_lidar, point_sets, cam.K, cam.T_cam_from_lidar,
                                              (cam.width, cam.height), pp["min_depth_m"])
        per_frame.append({
            "index": frame.index, "stamp_s": frame.stamp_ns * 1e-9, "det": det,
            "lidar_box": lidar_box, "point_sets": point_sets, "in_image": in_image,
            "xy": person_world_xy(frame.points_lidar, point_sets, frame.T_world_from_lidar,
                                  cfg.world_check.min_points),
        })
    # the log is recorded: track the whole sequence first (ids back-filled, split, stitched)
    check = cfg.world_check
    all_ids = track_offline(
        [f["det"]["boxes_xyxy"] for f in per_frame], [f["det"]["scores"] for f in per_frame], tracker,
        cfg.backfill, cfg.stitch_max_gap, cfg.stitch_max_distance, cfg.stitch_max_scale,
        positions=[f["xy"] for f in per_frame] if check.enabled else None,
        times_s=np.array([f["stamp_s"] for f in per_frame]),
        motion=WorldMotion(max_speed_mps=check.max_speed_mps, tol_m=check.tol_m,
                           speed_sigma_mps=check.speed_sigma_mps, window=check.window,
                           continuation_gate_scale=check.continuation_gate_scale),
        tentative=check.tentative)
    rows: dict[str, list] = {k: [] for k in ("frame", "det_index", "track_id", "boxes_xyxy", "scores",
                                             "keypoints", "lidar_box", "gt_index", "points_in_image")}
    kept_sets: list[np.ndarray] = []
    for f, ids in zip(per_frame, all_ids):
        keep = np.flatnonzero(ids >= 0)
        if keep.size == 0:
            continue
        det = f["det"]
        kept_sets += [f["point_sets"][k] for k in keep]
        rows["frame"].append(np.full(keep.size, f["index"], np.int64))
        rows["det_index"].append(keep.astype(np.int64))
        rows["track_id"].append(ids[keep].astype(np.int64))
        rows["boxes_xyxy"].append(det["boxes_xyxy"][keep].astype(np.float32))
        rows["scores"].append(det["scores"][keep].astype(np.float32))
        rows["keypoints"].append(det["keypoints"][keep].astype(np.float32))
        rows["lidar_box"].append(f["lidar_box"][keep].astype(np.int64))
        rows["gt_index"].append(det["gt_index"][keep].astype(np.int64))
        rows["points_in_image"].append(f["in_image"][keep].astype(np.int64))
    empty = {"frame": (0,), "det_index": (0,), "track_id": (0,), "boxes_xyxy": (0, 4), "scores": (0,),
             "keypoints": (0, 17, 3), "lidar_box": (0,), "gt_index": (0,),
             "points_in_image": (0,)}
    arrays = {k: np.concatenate(v) if v else np.zeros(empty[k], np.float32 if k in (
        "boxes_xyxy", "scores", "keypoints") else np.int64) for k, v in rows.items()}
    sizes = np.array([len(p) for p in kept_sets], np.int64)
    arrays["points_offsets"] = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    arrays["points_index"] = (np.concatenate(kept_sets).astype(np.int64) if kept_sets
                              else np.zeros(0, np.int64))
    write_product(ctx.out_dir, "tracks", arrays)
    return {"implemented": True, "tracks": int(np.unique(arrays["track_id"]).size),
            "tracked_detections": int(arrays["track_id"].size),
            "mean_person_points": float(sizes.mean()) if sizes.size else 0.0}


def person_world_xy(points_lidar: np.ndarray, point_sets: list[np.ndarray], T_world_from_lidar: np.ndarray,
                    min_points: int) -> np.ndarray:
    """(D, 2) world xy of each person: the median of its LiDAR points; NaN with fewer than
    ``min_points`` (a few points of a mostly hidden person often belong to someone in front)."""
    xy = np.full((len(point_sets), 2), np.nan)
    for k, idx in enumerate(point_sets):
        if len(idx) >= min_points:
            centre = np.median(points_lidar[idx].astype(np.float64), axis=0)
            xy[k] = transform_points(T_world_from_lidar, centre[None])[0, :2]
    return xy
