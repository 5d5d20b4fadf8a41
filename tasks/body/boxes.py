"""Upright 3D boxes around posed body meshes (the dataset's pedestrian boxes)."""

from __future__ import annotations

import numpy as np


def upright_box(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Upright box around one body (any z-up frame): centre (3,), size (l, w, h) with l along the
    footprint's major axis, and the yaw of that axis (rad about z)."""
    v = np.asarray(vertices, np.float64)
    xy = v[:, :2] - v[:, :2].mean(0)
    _, vecs = np.linalg.eigh(xy.T @ xy)
    major = vecs[:, 1]
    yaw = float(np.arctan2(major[1], major[0]))
    R = np.array([[np.cos(yaw), np.sin(yaw)], [-np.sin(yaw), np.cos(yaw)]])
    local = v[:, :2] @ R.T
    lo, hi = local.min(0), local.max(0)
    z0, z1 = v[:, 2].min(), v[:, 2].max()
    centre_xy = R.T @ ((lo + hi) / 2)
    return (np.array([centre_xy[0], centre_xy[1], (z0 + z1) / 2]),
            np.array([hi[0] - lo[0], hi[1] - lo[1], z1 - z0]), yaw)
