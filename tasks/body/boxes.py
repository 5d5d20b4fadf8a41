"""Upright 3D boxes around posed bodies, heading from the body's forward axis.

A pedestrian box (nuScenes / mmdet3d convention) is upright (rotation about z only) with its x
axis, the length ``l``, along the person's heading. The heading of a fitted body is its forward
axis: the global orientation applied to the template's forward direction (+z of the SMPL
canonical frame, :mod:`tasks.body.model`), projected on the ground plane. When that projection is
too short to define a direction (a body lying or bent over along its forward axis), the heading is
the direction of the velocity; when the person does not move either, the normal of the footprint's
major axis (the shoulder line of an upright body), and 0 for a footprint without a major axis.
The box never holds NaN.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: the forward direction of the SMPL template (y up, facing +z), template frame
TEMPLATE_FORWARD = np.array([0.0, 0.0, 1.0])

HEADING_FROM_BODY, HEADING_FROM_VELOCITY, HEADING_FROM_FOOTPRINT = "body", "velocity", "footprint"


@dataclass(frozen=True)
class UprightBox:
    """center (3,) float64 m and size (3,) = (l, w, h) m, l along the heading; yaw: rad about z,
    in (-pi, pi]; heading_source: which cue gave the yaw (body / velocity / footprint). All in the
    frame of the vertices given (z up)."""

    center: np.ndarray
    size: np.ndarray
    yaw: float
    heading_source: str


def _rotvec_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """(3,) axis-angle -> (3, 3) rotation (Rodrigues), float64."""
    r = np.asarray(rotvec, dtype=np.float64).reshape(3)
    angle = float(np.linalg.norm(r))
    if angle < 1e-12:
        return np.eye(3)
    k = r / angle
    Kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * Kx + (1.0 - np.cos(angle)) * (Kx @ Kx)


def body_forward(global_orient: np.ndarray) -> np.ndarray:
    """(3,) unit forward axis of a body whose root rotation is the axis-angle ``global_orient``
    (3,), in the frame global_orient is expressed in."""
    return _rotvec_to_matrix(global_orient) @ TEMPLATE_FORWARD


def upright_box(
    vertices: np.ndarray,
    global_orient: np.ndarray | None = None,
    velocity_xy: np.ndarray | None = None,
    min_horizontal: float = 0.25,
    min_speed_mps: float = 0.1,
) -> UprightBox:
    """The tight upright box around ``vertices`` with l along the body's heading.

    vertices: (V, 3) float metres, z up (e.g. the base frame), V >= 1, finite.
    global_orient: (3,) axis-angle of the body's root in the same frame, or None.
    velocity_xy: (2,) m/s in the same frame, or None / non-finite (unknown).
    min_horizontal: the forward axis defines the heading when its ground-plane part is at least
    this long (unit vector; 0.25 = more than ~14 deg away from vertical).
    min_speed_mps: below this speed the velocity gives no heading.
    """
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    if len(v) == 0 or not np.all(np.isfinite(v)):
        raise ValueError(
            f"upright_box: need finite vertices, got {len(v)} with "
            f"{int((~np.isfinite(v)).any(axis=1).sum())} non-finite"
        )
    direction, source = None, HEADING_FROM_FOOTPRINT
    if global_orient is not None and np.all(np.isfinite(global_orient)):
        f = body_forward(global_orient)
        if np.hypot(f[0], f[1]) >= min_horizontal:
            direction, source = f[:2], HEADING_FROM_BODY
    if direction is None and velocity_xy is not None:
        vel = np.asarray(velocity_xy, dtype=np.float64).reshape(2)
        if np.all(np.isfinite(vel)) and np.hypot(*vel) >= min_speed_mps:
            direction, source = vel, HEADING_FROM_VELOCITY
    if direction is None:
        xy = v[:, :2] - v[:, :2].mean(0)
        vals, vecs = np.linalg.eigh(xy.T @ xy)
        # the footprint's major axis is the shoulder line; facing is its normal (sign unknown)
        direction = (
            np.array([-vecs[1, 1], vecs[0, 1]])
            if vals[1] > vals[0] * (1 + 1e-9)
            else np.array([1.0, 0.0])
        )
    yaw = float(np.arctan2(direction[1], direction[0]))
    c, s = np.cos(yaw), np.sin(yaw)
    # box-local coordinates: x along the heading, y to its left
    local = np.stack([c * v[:, 0] + s * v[:, 1], -s * v[:, 0] + c * v[:, 1]], axis=1)
    lo, hi = local.min(0), local.max(0)
    mid = (lo + hi) / 2
    z0, z1 = v[:, 2].min(), v[:, 2].max()
    center = np.array([c * mid[0] - s * mid[1], s * mid[0] + c * mid[1], (z0 + z1) / 2])
    size = np.array([hi[0] - lo[0], hi[1] - lo[1], z1 - z0])
    return UprightBox(center, size, yaw, source)
