"""Per detection the person's LiDAR points and world position; the rows of the track product.

The track stage first finds every detection's person points (whose world positions let the
offline refinement check the 2D tracker's identities: a person's points do not depend on its id),
then tracks the whole sequence, then packs one row per tracked detection.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tasks.geometry import transform_points
from tasks.perception.person_points import (
    PersonPointParams,
    associate_lidar_boxes,
    in_image_first,
    person_point_indices,
)
from tasks.track.offline import WorldCheck


@dataclass(frozen=True)
class FramePersons:
    """One frame's detections with their LiDAR points.

    lidar_box: (D,) int64 matched LiDAR box row, -1 none. point_sets: D int64 index arrays into the
    sweep, in-image points first. in_image: (D,) int64 how many of each set are in the image.
    world_xy: (D, 2) float64 world xy of each person (NaN: too few points).
    """

    lidar_box: np.ndarray
    point_sets: list[np.ndarray]
    in_image: np.ndarray
    world_xy: np.ndarray


def person_world_xy(
    points_lidar: np.ndarray,
    point_sets: list[np.ndarray],
    T_world_from_lidar: np.ndarray,
    min_points: int,
) -> np.ndarray:
    """(D, 2) world xy of each person: the median of its LiDAR points; NaN with fewer than
    ``min_points`` (a few points of a mostly hidden person often belong to someone in front)."""
    xy = np.full((len(point_sets), 2), np.nan)
    for k, idx in enumerate(point_sets):
        if len(idx) >= min_points:
            centre = np.median(points_lidar[idx].astype(np.float64), axis=0)
            xy[k] = transform_points(T_world_from_lidar, centre[None])[0, :2]
    return xy


def frame_persons(
    points_lidar: np.ndarray,
    T_world_from_lidar: np.ndarray,
    boxes_xyxy: np.ndarray,
    masks: np.ndarray,
    lidar_centers: np.ndarray,
    lidar_sizes: np.ndarray,
    lidar_yaws: np.ndarray,
    K: np.ndarray,
    T_cam_from_lidar: np.ndarray,
    image_size: tuple[int, int],
    params: PersonPointParams,
    check: WorldCheck,
) -> FramePersons:
    """Each detection's LiDAR points (tasks.perception.person_points) and world position (none
    with fewer than ``check.min_points`` points: tasks.track.offline.WorldCheck).

    points_lidar: (N, 3) float32, LiDAR frame. boxes_xyxy (D, 4) pixels, masks (D, H, W) bool.
    lidar_*: the frame's LiDAR boxes (M, 3) / (M,), LiDAR frame. A LiDAR box matched to a detection
    gives the expected range of its points (its centre's distance from the camera).
    """
    lidar_box = associate_lidar_boxes(
        boxes_xyxy,
        lidar_centers,
        lidar_sizes,
        lidar_yaws,
        K,
        T_cam_from_lidar,
        params.assoc_min_iou,
    )
    expected = np.full(len(boxes_xyxy), np.nan)
    has = lidar_box >= 0
    if has.any():
        cam = transform_points(T_cam_from_lidar, lidar_centers[lidar_box[has]].astype(np.float64))
        expected[has] = np.linalg.norm(cam, axis=1)
    sets = person_point_indices(
        points_lidar, K, T_cam_from_lidar, image_size, boxes_xyxy, masks, expected, params
    )
    sets, in_image = in_image_first(
        points_lidar, sets, K, T_cam_from_lidar, image_size, params.min_depth_m
    )
    return FramePersons(
        lidar_box,
        sets,
        in_image,
        person_world_xy(points_lidar, sets, T_world_from_lidar, check.min_points),
    )


def track_rows(
    frames: list[int],
    ids: list[np.ndarray],
    persons: list[FramePersons],
    boxes_xyxy: list[np.ndarray],
    scores: list[np.ndarray],
    keypoints: list[np.ndarray],
    gt_index: list[np.ndarray],
) -> dict[str, np.ndarray]:
    """The rows of the track product (storage.products.Tracks), one per tracked detection.

    Per frame f: its raw number frames[f], ids[f] (D_f,) int64 (-1 untracked), persons[f], and the
    detections' boxes (D_f, 4), scores (D_f,), keypoints (D_f, 17, 3), gt_index (D_f,).
    """
    keep = [np.flatnonzero(np.asarray(i) >= 0) for i in ids]
    sets = [persons[f].point_sets[k] for f, rows in enumerate(keep) for k in rows]
    sizes = np.array([len(s) for s in sets], np.int64)

    def pick(per_frame, dtype, shape):
        parts = [np.asarray(a)[rows].astype(dtype) for a, rows in zip(per_frame, keep)]
        return np.concatenate(parts) if parts else np.zeros((0, *shape), dtype)

    return {
        "frame": np.concatenate(
            [np.full(k.size, f, np.int64) for f, k in zip(frames, keep)] or [np.zeros(0, np.int64)]
        ),
        "det_index": pick([np.arange(len(i)) for i in ids], np.int64, ()),
        "track_id": pick(ids, np.int64, ()),
        "boxes_xyxy": pick(boxes_xyxy, np.float32, (4,)),
        "scores": pick(scores, np.float32, ()),
        "keypoints": pick(keypoints, np.float32, (17, 3)),
        "lidar_box": pick([p.lidar_box for p in persons], np.int64, ()),
        "gt_index": pick(gt_index, np.int64, ()),
        "points_in_image": pick([p.in_image for p in persons], np.int64, ()),
        "points_offsets": np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
        "points_index": np.concatenate(sets).astype(np.int64) if sets else np.zeros(0, np.int64),
    }
