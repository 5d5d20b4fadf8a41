"""Posed meshes of fitted bodies, for fusion and boxes."""

from __future__ import annotations

import numpy as np
import torch


def posed_vertices(
    model, betas: np.ndarray, global_orient: np.ndarray, body_pose: np.ndarray, transl: np.ndarray
) -> np.ndarray:
    """Vertices (B, V, 3) float32 of B bodies (SMPL parameters (B, 10), (B, 3), (B, 69), (B, 3)),
    in the frame the parameters are expressed in."""
    return posed_vertices_and_root(model, betas, global_orient, body_pose, transl)[0]


def posed_vertices_and_root(
    model, betas: np.ndarray, global_orient: np.ndarray, body_pose: np.ndarray, transl: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`posed_vertices` and the pelvis joints (B, 1, 3) float32 of the same bodies."""
    if len(betas) == 0:
        nv = model.v_template.shape[0]
        return np.zeros((0, nv, 3), np.float32), np.zeros((0, 1, 3), np.float32)
    with torch.no_grad():
        out = model(
            *(torch.as_tensor(np.asarray(a)) for a in (betas, global_orient, body_pose, transl))
        )
    return out.vertices.numpy(), out.joints[:, :1].numpy()
