"""Warm start along a track (beyond the paper): a person fitted in the previous frame starts this
frame's fit from that fit, moved into this frame's camera frame by the robot's ego-motion."""

from __future__ import annotations

import numpy as np

from tasks.body.params import BodyParams
from tasks.fit.reframe import reframe_params


def warm_started(
    model,
    init: BodyParams,
    previous: list[BodyParams | None],
    T_cam_from_lidar: np.ndarray,
    T_world_from_lidar_now: np.ndarray,
    T_world_from_lidar_prev: np.ndarray,
) -> BodyParams:
    """The estimates ``init`` (B persons, cam frame of this frame) with row k replaced by
    ``previous[k]`` (one body in the LiDAR frame of the previous frame, or None: keep init) moved
    into this frame's cam frame: T = T_cam_from_lidar inv(T_world_from_lidar_now)
    T_world_from_lidar_prev. Poses: (4, 4) float64."""
    T = T_cam_from_lidar @ np.linalg.inv(T_world_from_lidar_now) @ T_world_from_lidar_prev
    fields = {k: np.array(getattr(init, k), copy=True) for k in BodyParams.FIELDS}
    for k, prev in enumerate(previous):
        if prev is None:
            continue
        moved = reframe_params(model, prev, T)
        for key in fields:
            fields[key][k] = getattr(moved, key)[0]
    return BodyParams(**fields)
