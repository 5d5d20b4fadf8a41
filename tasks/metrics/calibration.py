"""Sanity figures of a camera / LiDAR calibration, from the points of a few sweeps.

- :func:`stereo_row_error_px`: a rectified stereo pair puts a 3D point on the same image row in
  both cameras; the median |v_left - v_right| over LiDAR points seen by both is ~0 px for a correct
  rectification and grows with any error in R, P or the extrinsics.
- :func:`in_image_fraction`: the share of a sweep that projects into the image (a forward camera
  with CODa's 79 deg field of view sees about a fifth of a 360 deg sweep; ~0 means the extrinsic
  points the camera elsewhere).
- :func:`projection_difference_px`: median pixel distance between two projections of the same
  points (e.g. ours and a file's P R T).
- :func:`ground_height_m`: the height of the ground in a frame, the densest 5 cm layer of low
  points near the sensor (checks T_base_from_lidar: the ground lies at z ~ 0 in the base frame).
"""

from __future__ import annotations

import numpy as np

from tasks.geometry import transform_points


def project(
    points: np.ndarray, K: np.ndarray, T_cam_from_lidar: np.ndarray, min_depth_m: float = 0.5
) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) float64 pixels (u, v) and (N,) bool in front (depth > min_depth_m) of points (N, 3)
    in the LiDAR frame, for the pinhole K (3, 3), T_cam_from_lidar (4, 4)."""
    pc = transform_points(T_cam_from_lidar, points)
    front = pc[:, 2] > min_depth_m
    z = np.where(front, pc[:, 2], 1.0)
    uv = (
        pc[:, :2] / z[:, None] @ np.asarray(K, np.float64)[:2, :2].T
        + np.asarray(K, np.float64)[:2, 2]
    )
    return uv, front


def _inside(uv: np.ndarray, front: np.ndarray, width: int, height: int) -> np.ndarray:
    return front & (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)


def in_image_fraction(points: np.ndarray, K, T_cam_from_lidar, width: int, height: int) -> float:
    """Fraction of points (N, 3) LiDAR frame that land inside the width x height image."""
    if len(points) == 0:
        return float("nan")
    uv, front = project(points, K, T_cam_from_lidar)
    return float(np.mean(_inside(uv, front, width, height)))


def stereo_row_error_px(
    points: np.ndarray, left: tuple, right: tuple, min_depth_m: float = 2.0
) -> float:
    """Median |v_left - v_right| (px) of points (N, 3) seen by both cameras, each given as
    (K (3, 3), T_cam_from_lidar (4, 4), width, height) of its rectified image; NaN if none."""
    (K0, T0, w0, h0), (K1, T1, w1, h1) = left, right
    uv0, f0 = project(points, K0, T0, min_depth_m)
    uv1, f1 = project(points, K1, T1, min_depth_m)
    both = _inside(uv0, f0, w0, h0) & _inside(uv1, f1, w1, h1)
    return float(np.median(np.abs(uv0[both, 1] - uv1[both, 1]))) if both.any() else float("nan")


def projection_difference_px(
    points: np.ndarray, K, T_cam_from_lidar, P_lidar_to_image: np.ndarray, width: int, height: int
) -> float:
    """Median pixel distance between the pinhole (K, T) and a 3 x 4 matrix projecting LiDAR points
    straight to pixels, over points (N, 3) that land in the image; NaN if none."""
    uv, front = project(points, K, T_cam_from_lidar)
    ok = _inside(uv, front, width, height)
    if not ok.any():
        return float("nan")
    h = (
        np.c_[np.asarray(points, np.float64)[ok], np.ones(int(ok.sum()))]
        @ np.asarray(P_lidar_to_image, np.float64).T
    )
    other = h[:, :2] / h[:, 2:3]
    return float(np.median(np.linalg.norm(other - uv[ok], axis=1)))


def ground_height_m(
    points: np.ndarray,
    T_base_from_lidar: np.ndarray,
    inner_m: float = 2.0,
    outer_m: float = 15.0,
    bin_m: float = 0.05,
) -> float:
    """Height (m, base frame) of the ground seen in a sweep: the most populated ``bin_m`` layer among
    points (N, 3) LiDAR frame within inner_m..outer_m horizontally and in the lower half of their
    heights; ~0 when T_base_from_lidar (4, 4) is right. NaN with too few points."""
    T = np.asarray(T_base_from_lidar, np.float64)
    pb = transform_points(T, points)
    r = np.hypot(pb[:, 0] - T[0, 3], pb[:, 1] - T[1, 3])
    z = pb[(r >= inner_m) & (r <= outer_m), 2]
    if z.size < 100:
        return float("nan")
    z = z[z <= np.median(z)]
    edges = np.arange(z.min(), z.max() + 2 * bin_m, bin_m)
    counts, edges = np.histogram(z, bins=edges)
    k = int(np.argmax(counts))
    return float(np.median(z[(z >= edges[k]) & (z <= edges[k + 1])]))
