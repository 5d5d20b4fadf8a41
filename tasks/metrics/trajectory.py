"""Trajectory accuracy: absolute trajectory error (ATE) after a rigid alignment.

ATE (Sturm et al., IROS 2012): the estimated positions are aligned to the ground truth with the
rigid transform minimising the squared position error (Umeyama / Horn, no scale), then the RMSE
of the remaining position differences. Also the final drift: the error of the last pose relative
to the first (frame-independent) as a share of the distance travelled.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TrajectoryError:
    """ate_rmse_m, ate_max_m: metres after alignment; rotation_rmse_deg: of the rotations
    relative to the first pose; final_drift_pct: last position error / path length x 100; length_m: path length
    of the ground truth; poses: how many were compared."""

    ate_rmse_m: float
    ate_max_m: float
    rotation_rmse_deg: float
    final_drift_pct: float
    length_m: float
    poses: int


def align_rigid(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4, 4) T minimising sum |T source_i - target_i|^2 over positions (N, 3) (no scale)."""
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    H = (source - mu_s).T @ (target - mu_t)
    U, _, Vt = np.linalg.svd(H)
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ D @ U.T
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = mu_t - R @ mu_s
    return T


def trajectory_error(estimated: np.ndarray, ground_truth: np.ndarray) -> TrajectoryError:
    """ATE of estimated vs ground-truth poses, both (N, 4, 4) float64 at the same stamps."""
    est, gt = np.asarray(estimated, np.float64), np.asarray(ground_truth, np.float64)
    if est.shape != gt.shape or est.ndim != 3 or est.shape[1:] != (4, 4):
        raise ValueError(f"poses {est.shape} vs {gt.shape}: expected the same (N, 4, 4)")
    n = len(est)
    if n == 0:
        return TrajectoryError(0.0, 0.0, 0.0, 0.0, 0.0, 0)
    T = align_rigid(est[:, :3, 3], gt[:, :3, 3]) if n >= 3 else np.eye(4)
    aligned = T @ est
    err = np.linalg.norm(aligned[:, :3, 3] - gt[:, :3, 3], axis=1)
    # rotations relative to the first pose (a near-straight path leaves the alignment's
    # rotation about it undetermined; relative rotations do not depend on it)
    R_gt = np.einsum("ji,njk->nik", gt[0, :3, :3], gt[:, :3, :3])
    R_est = np.einsum("ji,njk->nik", est[0, :3, :3], est[:, :3, :3])
    rel = np.einsum("nji,njk->nik", R_gt, R_est)
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    length = float(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum())
    # the end pose relative to the start (independent of either world frame)
    end_est = np.linalg.inv(est[0]) @ est[-1]
    end_gt = np.linalg.inv(gt[0]) @ gt[-1]
    drift = float(np.linalg.norm(end_est[:3, 3] - end_gt[:3, 3]))
    return TrajectoryError(
        ate_rmse_m=float(np.sqrt(np.mean(err**2))),
        ate_max_m=float(err.max()),
        rotation_rmse_deg=float(np.degrees(np.sqrt(np.mean(np.arccos(cos) ** 2)))),
        final_drift_pct=float(100.0 * drift / length) if length > 0 else 0.0,
        length_m=length,
        poses=n,
    )
