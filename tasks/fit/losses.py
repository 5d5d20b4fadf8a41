"""Loss terms of the fitting objective (paper Eq. total), torch, batched over persons.

All functions return one value per person, shape ``(B,)``, so that a batch of persons is
optimised by summing them (persons do not interact). Ragged point sets are padded to a common
length and come with boolean masks. Units: pixels for L_J, metres^2 for L_3D, radians for the
pose terms.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

#: 69-d body-pose indices (left elbow y, right elbow y, left knee x, right knee x) and the sign
#: that makes the unnatural bending direction positive (SMPLify's hyperextension prior).
HYPEREXTENSION_IDS: tuple[int, ...] = (52, 55, 9, 12)
HYPEREXTENSION_SIGNS: tuple[float, ...] = (1.0, -1.0, -1.0, -1.0)


@dataclass(frozen=True)
class FitWeights:
    """Scalar weights and thresholds of the objective (paper appendix B table).

    rho_px: Geman-McClure scale of L_J (pixels). lambda_*: term weights. w: backface threshold
    (see :func:`tasks.fit.visibility.visibility_masks`). j_conf: keypoint-confidence threshold
    of the part filter. conf_power: L_J weights are ``confidence ** conf_power``.
    square_lambdas: multiply the terms by ``lambda ** 2`` instead of ``lambda`` (the paper does
    not say which; SMPLify squares its prior weights). Default True: on the synthetic benchmark
    (Ouster-128, 3DPW preset, 16 persons, vertex cap 3 cm) squared weights gave MPJPE 22 mm vs
    119 mm unsquared, because with L_J in pixels^2 and L_3D in m^2 the unsquared lambda_3D = 800
    leaves L_3D too weak.
    """

    rho_px: float
    lambda_theta: float
    lambda_a: float
    lambda_beta: float
    lambda_3d: float
    lambda_occ: float
    w: float
    j_conf: float
    conf_power: float = 2.0
    square_lambdas: bool = True

    def scale(self, name: str) -> float:
        """The multiplier of term ``name`` ('theta', 'a', 'beta', '3d', 'occ')."""
        value = float(getattr(self, f"lambda_{name}"))
        return value * value if self.square_lambdas else value

    def with_(self, **changes) -> "FitWeights":
        """A copy with some fields changed (ablations: ``weights.with_(lambda_3d=0.0)``)."""
        return replace(self, **changes)


#: Presets from the paper's appendix table (rho, lambda_theta, lambda_a, lambda_beta,
#: lambda_3D, lambda_occ, w, J_conf), one per dataset; the config chooses one by name
#: (``fit.preset``) and may add its own (``fit.presets``).
FIT_PRESETS: dict[str, FitWeights] = {
    "3dpw": FitWeights(100.0, 2.2, 11.0, 5.0, 800.0, 35.0, 0.2, 0.6),
    "sloper4d": FitWeights(100.0, 0.75, 8.5, 1.0, 500.0, 55.0, 0.2, 0.7),
    "humanm3": FitWeights(100.0, 1.0, 3.0, 17.5, 600.0, 135.0, -1.0, 0.6),
    "ut_campus": FitWeights(100.0, 1.4, 10.0, 10.0, 300.0, 50.0, 0.2, 0.7),
}


def project_points(points_cam: torch.Tensor, K: torch.Tensor, min_depth_m: float = 1e-3) -> torch.Tensor:
    """Pinhole projection. points_cam (B, N, 3) float, cam frame, m; K (B, 3, 3) or (3, 3).

    Returns pixels (B, N, 2) (u right, v down). Depth is clamped at ``min_depth_m`` so that a
    point behind the camera gives a large finite residual instead of inf / NaN.
    """
    if K.dim() == 2:
        K = K.expand(points_cam.shape[0], 3, 3)
    z = points_cam[..., 2:3].clamp(min=min_depth_m)
    xy = points_cam[..., :2] / z
    fx, fy = K[:, 0, 0, None], K[:, 1, 1, None]
    cx, cy = K[:, 0, 2, None], K[:, 1, 2, None]
    skew = K[:, 0, 1, None]
    u = fx * xy[..., 0] + skew * xy[..., 1] + cx
    v = fy * xy[..., 1] + cy
    return torch.stack([u, v], dim=-1)


def geman_mcclure(residual: torch.Tensor, rho: float) -> torch.Tensor:
    """Geman-McClure penalty rho^2 x^2 / (rho^2 + x^2), elementwise; same unit as rho^2."""
    sq = residual * residual
    r2 = rho * rho
    return r2 * sq / (r2 + sq)


def reprojection_loss(
    keypoints_cam: torch.Tensor,
    keypoints_2d: torch.Tensor,
    K: torch.Tensor,
    rho_px: float = 100.0,
    conf_power: float = 2.0,
    keypoint_weights: torch.Tensor | None = None,
) -> torch.Tensor:
    """L_J: confidence-weighted Geman-McClure reprojection error, per person (B,), pixels^2.

    keypoints_cam (B, 17, 3) model COCO-17 keypoints in the cam frame (m); keypoints_2d
    (B, 17, 3) detections (u, v, confidence in [0, 1]); K (B, 3, 3) or (3, 3) intrinsics;
    keypoint_weights optional (17,) extra per-keypoint factors (e.g. to down-weight hips).
    """
    uv = project_points(keypoints_cam, K)
    conf = keypoints_2d[..., 2].clamp(min=0.0) ** conf_power
    if keypoint_weights is not None:
        conf = conf * keypoint_weights
    pen = geman_mcclure(uv - keypoints_2d[..., :2], rho_px).sum(-1)
    return (conf * pen).sum(-1)


def masked_centroid(points: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    m = mask.to(points.dtype)[..., None]
    return (points * m).sum(1) / m.sum(1).clamp(min=1.0)


@torch.no_grad()
def nearest_indices(
    a: torch.Tensor,
    a_mask: torch.Tensor,
    b: torch.Tensor,
    b_mask: torch.Tensor,
    chunk: int = 8,
    method: str = "auto",
) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest neighbours both ways between padded sets (no gradient).

    a (B, N, 3), a_mask (B, N) bool, b (B, M, 3), b_mask (B, M) bool. Returns idx_ab (B, N)
    (index into b of the nearest valid b for each a) and idx_ba (B, M). Rows without any valid
    partner get index 0 (they are masked out by the caller). On the CPU a k-d tree per person;
    elsewhere a brute-force distance matrix in chunks of persons ('brute', memory chunk * N * M floats).
    """
    B, N, _ = a.shape
    M = b.shape[1]
    idx_ab = torch.zeros(B, N, dtype=torch.long, device=a.device)
    idx_ba = torch.zeros(B, M, dtype=torch.long, device=a.device)
    if N == 0 or M == 0:
        return idx_ab, idx_ba
    if method == "kdtree" or (method == "auto" and a.device.type == "cpu"):
        return _nearest_kdtree(a, a_mask, b, b_mask, idx_ab, idx_ba)
    # Padding is parked far away (1e4 m, opposite corners) instead of masking the distance
    # matrix: a valid row never picks it while any valid partner exists.
    a = torch.where(a_mask[..., None], a, torch.full_like(a, 1e4))
    b = torch.where(b_mask[..., None], b, torch.full_like(b, -1e4))
    for s in range(0, B, chunk):
        e = min(B, s + chunk)
        d = torch.cdist(a[s:e], b[s:e])  # only compared, never differentiated
        idx_ab[s:e] = d.argmin(2)
        idx_ba[s:e] = d.argmin(1)
    return idx_ab, idx_ba


def _nearest_kdtree(a, a_mask, b, b_mask, idx_ab, idx_ba):
    """CPU path of nearest_indices: a k-d tree per person (cheaper than the B x N x M matrix)."""
    from scipy.spatial import cKDTree

    an, bn = a.numpy(), b.numpy()
    am, bm = a_mask.numpy(), b_mask.numpy()
    for i in range(an.shape[0]):
        ia, ib = np.flatnonzero(am[i]), np.flatnonzero(bm[i])
        if len(ia) == 0 or len(ib) == 0:
            continue
        _, j = cKDTree(bn[i, ib]).query(an[i], k=1)
        idx_ab[i] = torch.from_numpy(ib[j])
        _, j = cKDTree(an[i, ia]).query(bn[i], k=1)
        idx_ba[i] = torch.from_numpy(ia[j])
    return idx_ab, idx_ba


def chamfer_loss(
    vertices: torch.Tensor,
    vertex_mask: torch.Tensor,
    points: torch.Tensor,
    point_mask: torch.Tensor,
    indices: tuple[torch.Tensor, torch.Tensor] | None = None,
    vertex_max_m: float | None = None,
) -> torch.Tensor:
    """L_3D: symmetric, size-normalised squared Chamfer distance per person (B,), m^2.

    vertices (B, V, 3) model vertices, vertex_mask (B, V) bool (the visible set), points
    (B, P, 3) LiDAR points in the same frame, point_mask (B, P) bool. Both sets are shifted by
    the person's point centroid first (precision at long range). Squared distances are formed
    from coordinate differences of nearest pairs (found without gradient), so the gradient is
    finite at zero distance. A person with no valid vertex or point contributes 0.
    indices: the nearest pairs (idx_vp (B, V), idx_pv (B, P)) from an earlier call of
    :func:`nearest_indices`, to reuse correspondences for a few steps (they change slowly); None =
    search now.
    vertex_max_m: cap of the vertex -> point distance (the term then contributes the constant
    vertex_max_m^2 and no gradient); None = the paper's uncapped form. Why: the visible set of
    backface culling over-approximates what the LiDAR saw (self-occlusion, grazing faces, gaps
    between scan lines); pulling such vertices onto the nearest return drags the mesh towards the
    sensor and thins it (measured: -31 mm depth bias starting from the true body, Ouster-128).
    The point -> vertex direction is never capped: every return lies on the body.
    """
    c = masked_centroid(points, point_mask).detach()[:, None, :]
    v = vertices - c
    p = points - c
    if indices is None:
        indices = nearest_indices(v.detach(), vertex_mask, p, point_mask)
    idx_vp, idx_pv = indices
    p_near = torch.gather(p, 1, idx_vp[..., None].expand(-1, -1, 3))
    v_near = torch.gather(v, 1, idx_pv[..., None].expand(-1, -1, 3))
    d_vp = ((v - p_near) ** 2).sum(-1)
    if vertex_max_m is not None:
        d_vp = d_vp.clamp(max=float(vertex_max_m) ** 2)
    d_pv = ((p - v_near) ** 2).sum(-1)
    vm = vertex_mask.to(v.dtype)
    pm = point_mask.to(v.dtype)
    both = (vm.sum(1) > 0) & (pm.sum(1) > 0)
    term_v = (d_vp * vm).sum(1) / vm.sum(1).clamp(min=1.0)
    term_p = (d_pv * pm).sum(1) / pm.sum(1).clamp(min=1.0)
    return torch.where(both, term_v + term_p, torch.zeros_like(term_v))


def hyperextension_loss(body_pose: torch.Tensor) -> torch.Tensor:
    """L_a: sum_k exp(sign_k * theta_k) over elbows and knees. body_pose (B, 69) axis-angle, rad."""
    ids = torch.tensor(HYPEREXTENSION_IDS, device=body_pose.device)
    signs = torch.tensor(HYPEREXTENSION_SIGNS, device=body_pose.device, dtype=body_pose.dtype)
    return torch.exp(body_pose[:, ids] * signs).sum(-1)


def shape_loss(betas: torch.Tensor) -> torch.Tensor:
    """L_beta = beta^T Sigma^-1 beta with Sigma = I (SMPL shape space is whitened). betas (B, 10)."""
    return (betas * betas).sum(-1)


def occlusion_pose_loss(
    rotmats: torch.Tensor, rotmats_init: torch.Tensor, occluded: torch.Tensor
) -> torch.Tensor:
    """L_theta,occ = sum over occluded joints of 1 - <q0, q>^2 = (3 - trace(R0^T R)) / 4.

    rotmats, rotmats_init (B, J, 3, 3) current and initial joint rotations; occluded (B, J) bool.
    """
    trace = (rotmats_init * rotmats).sum((-1, -2))  # trace(R0^T R) = sum_ij R0_ij R_ij
    return (((3.0 - trace) / 4.0) * occluded.to(rotmats.dtype)).sum(-1)


def gmm_pose_loss(prior, body_pose: torch.Tensor) -> torch.Tensor:
    """L_theta: the GMM pose prior's negative log-likelihood (B,). prior: callable (B, 69) -> (B,)."""
    return prior(body_pose)
