"""Initial body estimates: an ``oracle`` that errs like a monocular regressor, and the conversion
of ``precomputed`` CLIFF outputs to our parameters. All outputs are in the cam frame (OpenCV).
"""

from __future__ import annotations

import numpy as np
import torch

from tasks.body.params import BodyParams
from tasks.body.rotations import axis_angle_to_matrix, matrix_to_axis_angle


def _rest_root(model, betas: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return (
            model.rest_joints(torch.as_tensor(betas, dtype=torch.float32))[:, 0]
            .numpy()
            .astype(np.float64)
        )


def oracle_initial_estimate(
    model,
    truth: BodyParams,
    rng: np.random.Generator,
    depth_std_m: float = 0.3,
    pose_std_rad: float = 0.12,
    orient_std_deg: float = 6.0,
    betas_std: float = 0.6,
) -> BodyParams:
    """Perturb true bodies the way a monocular regressor errs.

    The root joint slides along its camera ray by N(0, depth_std_m) (the image position stays
    right, the depth does not), every body joint gets N(0, pose_std_rad) axis-angle noise, the
    global orientation a random rotation of N(0, orient_std_deg), the shape N(0, betas_std).
    model: a BodyModel (for the root joint J_0(beta)); truth: true parameters (cam frame).
    """
    B = len(truth)
    betas = truth.betas + rng.normal(0.0, betas_std, truth.betas.shape)
    body_pose = truth.body_pose + rng.normal(0.0, pose_std_rad, truth.body_pose.shape)
    axis = rng.normal(size=(B, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    noise_R = axis_angle_to_matrix(
        torch.as_tensor(axis * np.radians(rng.normal(0.0, orient_std_deg, (B, 1))))
    )
    R_true = axis_angle_to_matrix(torch.as_tensor(truth.global_orient, dtype=torch.float64))
    global_orient = matrix_to_axis_angle(noise_R @ R_true).numpy()
    root = _rest_root(model, truth.betas) + truth.transl  # posed root joint, cam frame
    dist = np.linalg.norm(root, axis=1, keepdims=True)
    root_new = root * (1.0 + rng.normal(0.0, depth_std_m, (B, 1)) / dist)
    transl = root_new - _rest_root(model, betas)
    f32 = np.float32
    return BodyParams(
        betas.astype(f32), global_orient.astype(f32), body_pose.astype(f32), transl.astype(f32)
    )


def cliff_to_params(
    rotmats, betas, pred_cam_crop, bbox_center, bbox_size, K, transl=None, use_transl=None
) -> BodyParams:
    """Convert CLIFF outputs of N persons to our parameters (pure function, no file reading).

    rotmats (N, 24, 3, 3) joint rotations (cam frame for the root); betas (N, 10);
    pred_cam_crop (N, 3) weak-perspective (s, tx, ty) of the crop; bbox_center (N, 2) pixels;
    bbox_size (N,) pixels (side of the square crop); K (3, 3) calibrated intrinsics. The
    full-image translation follows CLIFF's crop-to-full conversion with the true focal length
    and principal point: tz = 2 f / (s b), tx' = tx + 2 (cx - px) / (s b), ty' = ty + 2 (cy - py) / (s b).
    transl (N, 3) m with use_transl (N,) bool: rows whose translation is given directly (cam
    frame); their crop camera is ignored.
    """
    R = torch.as_tensor(np.asarray(rotmats, dtype=np.float64))
    cam = np.asarray(pred_cam_crop, dtype=np.float64)
    c = np.asarray(bbox_center, dtype=np.float64)
    b = np.asarray(bbox_size, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    if R.dim() != 4 or R.shape[1:] != (24, 3, 3) or cam.shape != (R.shape[0], 3):
        raise ValueError(
            f"cliff_to_params: expected rotmats (N, 24, 3, 3) and cam (N, 3), got {tuple(R.shape)}, {cam.shape}"
        )
    aa = matrix_to_axis_angle(R).numpy()
    f = K[0, 0]
    sb = cam[:, 0] * b + 1e-9
    tz = 2.0 * f / sb
    tx = cam[:, 1] + 2.0 * (c[:, 0] - K[0, 2]) / sb
    ty = cam[:, 2] + 2.0 * (c[:, 1] - K[1, 2]) / sb
    t = np.stack([tx, ty, tz], 1)
    if transl is not None:
        use = np.ones(len(t), bool) if use_transl is None else np.asarray(use_transl, bool)
        t[use] = np.asarray(transl, dtype=np.float64)[use]
    f32 = np.float32
    return BodyParams(
        np.asarray(betas, dtype=f32),
        aa[:, 0].astype(f32),
        aa[:, 1:].reshape(-1, 69).astype(f32),
        t.astype(f32),
    )


def params_to_cliff_camera(transl, bbox_center, bbox_size, K) -> np.ndarray:
    """Inverse of the camera part of :func:`cliff_to_params`: the crop camera (N, 3) = (s, tx, ty)
    that places a body at transl (N, 3) m (cam frame, tz > 0) for crops bbox_center (N, 2) px,
    bbox_size (N,) px, intrinsics K (3, 3). For writing estimates in CLIFF's native form."""
    t = np.asarray(transl, dtype=np.float64)
    c = np.asarray(bbox_center, dtype=np.float64)
    b = np.asarray(bbox_size, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    sb = 2.0 * K[0, 0] / t[:, 2]
    return np.stack(
        [
            sb / b,
            t[:, 0] - 2.0 * (c[:, 0] - K[0, 2]) / sb,
            t[:, 1] - 2.0 * (c[:, 1] - K[1, 2]) / sb,
        ],
        1,
    )
