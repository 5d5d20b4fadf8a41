"""Express body parameters in another frame (camera <-> LiDAR): the root rotates about J_0(beta)."""

from __future__ import annotations

import numpy as np
import torch

from tasks.body.model import rigid_transform_params
from tasks.body.params import BodyParams
from tasks.body.rotations import axis_angle_to_matrix, matrix_to_axis_angle


def reframe_params(model, params: BodyParams, T_new_from_old: np.ndarray) -> BodyParams:
    """Bodies posed in frame ``old`` -> the same bodies in frame ``new``.

    params: B bodies (betas (B, 10), global_orient (B, 3), body_pose (B, 69), transl (B, 3)) in
    ``old``; T_new_from_old: (4, 4) float64 rigid transform. The body pose and shape are unchanged;
    global_orient' = R global_orient and transl' = R (J0 + transl) + t - J0.
    """
    if len(params) == 0:
        return params
    T = torch.as_tensor(np.asarray(T_new_from_old, np.float64))
    betas = torch.as_tensor(params.betas, dtype=torch.float32)
    with torch.no_grad():
        J0 = model.rest_joints(betas)[:, 0].double()
    R_go = axis_angle_to_matrix(torch.as_tensor(params.global_orient, dtype=torch.float64))
    new_R, new_t = rigid_transform_params(
        R_go, torch.as_tensor(params.transl, dtype=torch.float64), J0, T[:3, :3], T[:3, 3]
    )
    f32 = np.float32
    return BodyParams(
        params.betas.astype(f32),
        matrix_to_axis_angle(new_R).numpy().astype(f32),
        params.body_pose.astype(f32),
        new_t.numpy().astype(f32),
    )
