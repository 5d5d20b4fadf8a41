"""Person boxes for the image models from the LiDAR pedestrian boxes (no image detector needed).

The bundled setup has no usable image detector (BlazePose's detector is trained for one nearby
person; measured on our synthetic street frames it finds under 20 % of the people), so its person
boxes come from the LiDAR detector: each 3D box's eight corners projected into the camera.
"""

from __future__ import annotations

import numpy as np

from tasks.geometry import transform_points
from tasks.perception.types import box_corners


def project_lidar_boxes(
    centers: np.ndarray,
    sizes: np.ndarray,
    yaws: np.ndarray,
    T_cam_from_lidar: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    min_depth_m: float = 0.3,
    min_side_px: float = 4.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Image boxes of 3D boxes (LiDAR frame: centers (M, 3), sizes (M, 3), yaws (M,)).

    A box counts when all eight corners are at least ``min_depth_m`` in front of the camera
    (T_cam_from_lidar (4, 4), OpenCV axes; K (3, 3)) and its projection, clipped to the image
    (width x height, pixel centres at integers), is at least ``min_side_px`` on both sides.
    Returns boxes (B, 4) float32 xyxy px and the indices (B,) int64 of the 3D boxes they come from.
    """
    corners = box_corners(
        np.asarray(centers).reshape(-1, 3),
        np.asarray(sizes).reshape(-1, 3),
        np.asarray(yaws).reshape(-1),
    )
    cam = transform_points(T_cam_from_lidar, corners)  # (B, 8, 3)
    z = cam[..., 2]
    front = (z >= min_depth_m).all(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * cam[..., 0] / z + K[0, 2]
        v = K[1, 1] * cam[..., 1] / z + K[1, 2]
    box = np.stack([u.min(1), v.min(1), u.max(1), v.max(1)], 1)
    box = np.clip(box, 0, [width - 1, height - 1, width - 1, height - 1])
    keep = front & (box[:, 2] - box[:, 0] >= min_side_px) & (box[:, 3] - box[:, 1] >= min_side_px)
    return box[keep].astype(np.float32), np.flatnonzero(keep).astype(np.int64)
