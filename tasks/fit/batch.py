"""From a batch of persons to the fit's inputs, and from its result to the rows the stage keeps."""

from __future__ import annotations

import numpy as np
import torch

from tasks.body.params import BodyParams
from tasks.fit.optimize import FitResult, model_keypoints
from tasks.fit.quality import fit_residuals
from tasks.fit.reframe import reframe_params
from tasks.geometry import transform_points


def concat_point_sets(points: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """B point sets (N_b, 3) -> the fit's ragged layout: points (sum N_b, 3) float32 one set after
    another, and counts (B,) int64."""
    flat = np.concatenate(
        [np.asarray(p, np.float32).reshape(-1, 3) for p in points] or [np.zeros((0, 3), np.float32)]
    )
    return flat, np.array([len(p) for p in points], np.int64)


def fit_rows(
    model,
    result: FitResult,
    init: BodyParams,
    points_lidar: list[np.ndarray],
    keypoints: np.ndarray,
    K: np.ndarray,
    T_cam_from_lidar: np.ndarray,
    min_confidence: float,
) -> dict[str, np.ndarray]:
    """A batch's fits as rows in the LiDAR frame: parameters, pelvis (R, 3) float64, the final
    loss terms, chamfer_m / reproj_px (:func:`tasks.fit.quality.fit_residuals`), num_points and
    shift_m (how far the fit moved the root translation from the initial estimate, m)."""
    T_lidar_from_cam = np.linalg.inv(T_cam_from_lidar)
    lidar = reframe_params(model, result.params(), T_lidar_from_cam)
    points_cam = [transform_points(T_cam_from_lidar, p) for p in points_lidar]
    kp_model = model_keypoints(
        torch.as_tensor(result.joints), torch.as_tensor(result.vertices), model.keypoint_vertex_ids
    ).numpy()
    chamfer, reproj = fit_residuals(
        result.vertices, kp_model, points_cam, keypoints, K, min_confidence
    )
    res = result.residuals
    return {
        "betas": lidar.betas,
        "global_orient": lidar.global_orient,
        "body_pose": lidar.body_pose,
        "transl": lidar.transl,
        "pelvis_lidar": transform_points(T_lidar_from_cam, result.joints[:, 0]),
        "loss_j": np.asarray(res["L_J"], np.float32),
        "loss_3d": np.asarray(res["L_3D"], np.float32),
        "loss_total": np.asarray(res["total"], np.float32),
        "chamfer_m": chamfer,
        "reproj_px": reproj,
        "num_points": np.array([len(p) for p in points_lidar], np.int64),
        "shift_m": np.linalg.norm(
            np.asarray(result.transl, np.float64) - np.asarray(init.transl, np.float64), axis=1
        ).astype(np.float32),
    }


def drop_far_fits(out: dict, max_shift_m: float | None) -> tuple[dict, int]:
    """The fit arrays ``out`` (one row per fit) without the rows whose ``shift_m`` exceeds
    ``max_shift_m`` (None keeps all), and how many were dropped."""
    if max_shift_m is None:
        return out, 0
    keep = np.asarray(out["shift_m"]) <= max_shift_m
    return {k: np.asarray(v)[keep] for k, v in out.items()}, int((~keep).sum())
