"""Mesh and joint accuracy metrics (numpy, float64 inside). Inputs in metres, outputs in mm.

- PVE / MPJPE: mean Euclidean error over vertices / joints in the sensor frame, no alignment
  (what occupancy needs), and pelvis-aligned (root joint translated onto the ground truth).
- PA-MPJPE: after a similarity Procrustes (Umeyama) alignment, computed in float64.
- MPERE: per face, mean over its 3 edges of |l_pred - l_gt| / l_gt; mean over faces (unitless).
"""

from __future__ import annotations

import numpy as np


def _as64(x) -> np.ndarray:
    return np.asarray(x, dtype=np.float64)


def mean_error_mm(pred, gt) -> np.ndarray:
    """Mean point error per person. pred, gt (B, N, 3) metres -> (B,) mm."""
    return np.linalg.norm(_as64(pred) - _as64(gt), axis=-1).mean(-1) * 1000.0


def pelvis_aligned_error_mm(pred, gt, pred_root, gt_root) -> np.ndarray:
    """Mean error after moving pred_root (B, 3) onto gt_root (B, 3). pred, gt (B, N, 3) m -> (B,) mm."""
    shift = (_as64(gt_root) - _as64(pred_root))[:, None, :]
    return mean_error_mm(_as64(pred) + shift, gt)


def umeyama_align(pred, gt) -> np.ndarray:
    """Similarity transform (s, R, t) minimising ||s R pred + t - gt||, applied to pred.

    pred, gt (B, N, 3) float -> aligned pred (B, N, 3) float64 (Umeyama 1991, reflection-safe).
    """
    X, Y = _as64(pred), _as64(gt)
    mx, my = X.mean(1, keepdims=True), Y.mean(1, keepdims=True)
    Xc, Yc = X - mx, Y - my
    cov = np.einsum("bni,bnj->bij", Yc, Xc) / X.shape[1]
    U, S, Vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.ones_like(S)
    D[:, -1] = d
    R = U @ (D[:, :, None] * Vt)
    var_x = (Xc**2).sum((1, 2)) / X.shape[1]
    s = (S * D).sum(1) / np.maximum(var_x, 1e-300)
    return s[:, None, None] * np.einsum("bij,bnj->bni", R, Xc) + my


def pa_mpjpe_mm(pred_joints, gt_joints) -> np.ndarray:
    """Procrustes-aligned MPJPE. (B, J, 3) m -> (B,) mm."""
    return mean_error_mm(umeyama_align(pred_joints, gt_joints), gt_joints)


def mpere(pred_vertices, gt_vertices, faces) -> np.ndarray:
    """Mean per-edge relative error. vertices (B, V, 3), faces (F, 3) int -> (B,) unitless."""
    P, G = _as64(pred_vertices), _as64(gt_vertices)
    f = np.asarray(faces, dtype=np.int64)
    errs = []
    for a, b in ((0, 1), (1, 2), (2, 0)):
        lp = np.linalg.norm(P[:, f[:, a]] - P[:, f[:, b]], axis=-1)
        lg = np.linalg.norm(G[:, f[:, a]] - G[:, f[:, b]], axis=-1)
        errs.append(np.abs(lp - lg) / np.maximum(lg, 1e-12))
    return np.mean(errs, axis=0).mean(-1)


def fit_metrics(pred_vertices, pred_joints, gt_vertices, gt_joints, faces) -> dict[str, np.ndarray]:
    """All metrics per person. vertices (B, V, 3), joints (B, 24, 3) in one frame (m).

    Returns dict of (B,) arrays: pve, mpjpe (no alignment, mm), pve_root / mpjpe_root
    (pelvis-aligned, mm), pa_mpjpe (mm), mpere (unitless).
    """
    pr, gr = _as64(pred_joints)[:, 0], _as64(gt_joints)[:, 0]
    return {
        "pve": mean_error_mm(pred_vertices, gt_vertices),
        "mpjpe": mean_error_mm(pred_joints, gt_joints),
        "pve_root": pelvis_aligned_error_mm(pred_vertices, gt_vertices, pr, gr),
        "mpjpe_root": pelvis_aligned_error_mm(pred_joints, gt_joints, pr, gr),
        "pa_mpjpe": pa_mpjpe_mm(pred_joints, gt_joints),
        "mpere": mpere(pred_vertices, gt_vertices, faces),
    }
