"""Coarse rigid alignment of the visible mesh to the person's LiDAR points (paper Sec. LiDAR-Mesh
Alignment), and the rule that moves SMPL parameters by a rigid transform.

SMPL's root rotation acts about the root joint J_0(beta), not the origin, so a rigid motion
(R, t) of the posed mesh maps parameters as
    R_glob' = R R_glob,   transl' = R (J_0 + transl) + t - J_0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d


def rigid_update_params(global_orient_R, transl, root_rest, R, t) -> tuple[np.ndarray, np.ndarray]:
    """Apply a rigid motion to SMPL global parameters.

    global_orient_R (..., 3, 3); transl (..., 3) m; root_rest (..., 3) = J_0(beta), the rest-pose
    root joint (model frame, m); R (..., 3, 3), t (..., 3). Returns (R_glob', transl').
    """
    Rg = np.asarray(global_orient_R, dtype=np.float64)
    tr = np.asarray(transl, dtype=np.float64)
    j0 = np.asarray(root_rest, dtype=np.float64)
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    new_R = R @ Rg
    new_t = np.einsum("...ij,...j->...i", R, j0 + tr) + t - j0
    return new_R, new_t


@dataclass(frozen=True)
class IcpResult:
    """T (4, 4) float64: maps the initial mesh onto the points (cam frame). fitness: inlier
    fraction of open3d; rmse_m: inlier RMSE; used_icp: False when the fallback (centroid
    translation, or identity for too few points) was kept."""

    T: np.ndarray
    fitness: float
    rmse_m: float
    used_icp: bool


def icp_align(
    vertices,
    points,
    max_correspondence_m: tuple[float, ...] = (0.3, 0.1),
    max_iterations: int = 30,
    center_init: bool = True,
    max_rotation_deg: float = 30.0,
    min_points: int = 10,
) -> IcpResult:
    """Rigid point-to-point ICP (open3d) of visible vertices onto LiDAR points, one person.

    vertices (N, 3) visible model vertices, points (M, 3) the person's points, same frame (m).
    The estimate is the initialisation; with center_init the visible-vertex centroid is first
    translated onto the point centroid (absorbs the monocular depth error). ICP runs once per
    correspondence radius, coarse to fine. If the result rotates by more than max_rotation_deg
    (a partial front view can make ICP spin the body) the translation-only start is kept.
    """
    V = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    T0 = np.eye(4)
    if len(P) < min_points or len(V) < 3:
        return IcpResult(T0, 0.0, float("inf"), False)
    if center_init:
        T0[:3, 3] = P.mean(0) - V.mean(0)
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(V))
    dst = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
    T = T0
    reg = None
    for radius in max_correspondence_m:
        reg = o3d.pipelines.registration.registration_icp(
            src,
            dst,
            radius,
            T,
            o3d.pipelines.registration.TransformationEstimationPointToPoint(),
            o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=max_iterations),
        )
        if reg.fitness > 0:
            T = np.asarray(reg.transformation).copy()
    cos = np.clip((np.trace(T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    if reg is None or reg.fitness == 0 or np.degrees(np.arccos(cos)) > max_rotation_deg:
        return IcpResult(T0, 0.0, float("inf"), False)
    return IcpResult(T, float(reg.fitness), float(reg.inlier_rmse), True)
