"""track: OC-SORT ids over a sequence's 2D detections, and each tracked person's LiDAR points.

Ids come from tasks.track.offline.track_offline (OC-SORT, then back-fill and fragment stitching
over the whole sequence, as the track config says).

Product ``tracks.npz`` (one row per tracked detection, frames ascending): frame (R,) int64 raw frame
number, det_index (R,) row in that frame's detect product, track_id (R,) int64 (>= 1),
boxes_xyxy (R, 4), scores (R,), keypoints (R, 17, 3), lidar_box (R,) int64 matched LiDAR box row or
-1, gt_index (R,) int64 (the detection's ground-truth row with the oracle provider, else -2),
points_offsets (R + 1,) int64 and points_index (sum,) int64: the person's points are
``points_index[points_offsets[r]:points_offsets[r + 1]]``, indices into the frame's
``points_lidar`` as the reader returns it.
"""

from __future__ import annotations

import numpy as np

from flows.stages.common import StageContext
from storage.intermediate import labels_to_masks, read_product, write_product
from tasks.perception.person_points import associate_lidar_boxes, person_point_indices
from tasks.track.ocsort import PedestrianTracker
from tasks.track.offline import track_offline


def run_track(ctx: StageContext) -> dict:
    cfg = ctx.config.track
    seq = ctx.open()
    cam = seq.info.calibration.cameras[ctx.config.dataset.camera]
    tracker = PedestrianTracker(det_thresh=cfg.det_thresh, max_age=cfg.max_age, min_hits=cfg.min_hits,
                                iou_threshold=cfg.iou_threshold, delta_t=cfg.delta_t,
                                inertia=cfg.inertia, keep_confirmed_ids=cfg.keep_confirmed_ids)
    # the log is recorded: track the whole sequence first (ids may be back-filled / stitched)
    raw = [seq.info.frame_indices[i] for i in range(len(seq))]
    dets = [read_product(ctx.upstream["detect"], f"frame_{r}", keys=("boxes_xyxy", "scores")) for r in raw]
    all_ids = track_offline([d["boxes_xyxy"] for d in dets], [d["scores"] for d in dets], tracker,
                            cfg.backfill, cfg.stitch_max_gap, cfg.stitch_max_distance, cfg.stitch_max_scale)
    pp = cfg.person_points.model_dump()
    min_iou = pp.pop("assoc_min_iou")
    rows: dict[str, list] = {k: [] for k in ("frame", "det_index", "track_id", "boxes_xyxy", "scores",
                                             "keypoints", "lidar_box", "gt_index")}
    point_sets: list[np.ndarray] = []
    for i in range(len(seq)):
        frame = seq.frame(i)
        det = read_product(ctx.upstream["detect"], f"frame_{frame.index}")
        ids = all_ids[i]
        keep = np.flatnonzero(ids >= 0)
        if keep.size == 0:
            continue
        boxes = det["boxes_xyxy"][keep]
        lidar_box = associate_lidar_boxes(boxes, det["lidar_centers"], det["lidar_sizes"],
                                          det["lidar_yaws"], cam.K, cam.T_cam_from_lidar, min_iou)
        expected = np.full(keep.size, np.nan)
        has = lidar_box >= 0
        if has.any():
            centers = det["lidar_centers"][lidar_box[has]].astype(np.float64)
            cam_xyz = centers @ cam.T_cam_from_lidar[:3, :3].T + cam.T_cam_from_lidar[:3, 3]
            expected[has] = np.linalg.norm(cam_xyz, axis=1)
        masks = labels_to_masks(det["mask_labels"], len(det["scores"]))[keep]
        point_sets += person_point_indices(frame.points_lidar, cam.K, cam.T_cam_from_lidar,
                                           (cam.width, cam.height), boxes, masks, expected, **pp)
        rows["frame"].append(np.full(keep.size, frame.index, np.int64))
        rows["det_index"].append(keep.astype(np.int64))
        rows["track_id"].append(ids[keep].astype(np.int64))
        rows["boxes_xyxy"].append(boxes.astype(np.float32))
        rows["scores"].append(det["scores"][keep].astype(np.float32))
        rows["keypoints"].append(det["keypoints"][keep].astype(np.float32))
        rows["lidar_box"].append(lidar_box.astype(np.int64))
        rows["gt_index"].append(det["gt_index"][keep].astype(np.int64))
    empty = {"frame": (0,), "det_index": (0,), "track_id": (0,), "boxes_xyxy": (0, 4), "scores": (0,),
             "keypoints": (0, 17, 3), "lidar_box": (0,), "gt_index": (0,)}
    arrays = {k: np.concatenate(v) if v else np.zeros(empty[k], np.float32 if k in (
        "boxes_xyxy", "scores", "keypoints") else np.int64) for k, v in rows.items()}
    sizes = np.array([len(p) for p in point_sets], np.int64)
    arrays["points_offsets"] = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    arrays["points_index"] = (np.concatenate(point_sets).astype(np.int64) if point_sets
                              else np.zeros(0, np.int64))
    write_product(ctx.out_dir, "tracks", arrays)
    return {"implemented": True, "tracks": int(np.unique(arrays["track_id"]).size),
            "tracked_detections": int(arrays["track_id"].size),
            "mean_person_points": float(sizes.mean()) if sizes.size else 0.0}
