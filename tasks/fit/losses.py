"""Loss terms of the fitting objective (paper Eq. total), torch, batched over persons.

All functions return one value per person, shape ``(B,)``, so that a batch of persons is
optimised by summing them (persons do not interact). Vertex sets are padded to a common length
and come with boolean masks; LiDAR points are ragged: (P, 3) with the person of each point (P,).
Units: pixels for L_J, metres^2 for L_3D, radians for the pose terms.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

#: 69-d body-pose indices (left elbow y, right elbow y, left knee x, right knee x) and the sign
#: that makes the unnatural bending direction positive (SMPLify's hyperextension prior).
HYPEREXTENSION_IDS: tuple[int, ...] = (52, 55, 9, 12)
HYPEREXTENSION_SIGNS: tuple[float, ...] = (1.0, -1.0, -1.0, -1.0)


def project_points(
    points_cam: torch.Tensor, K: torch.Tensor, depth_floor_m: float = 1e-3
) -> torch.Tensor:
    """Pinhole projection. points_cam (B, N, 3) float, cam frame, m; K (B, 3, 3) or (3, 3).

    Returns pixels (B, N, 2) (u right, v down). Depth is clamped at ``depth_floor_m`` so that a
    point behind the camera gives a large finite residual instead of inf / NaN.
    """
    if K.dim() == 2:
        K = K.expand(points_cam.shape[0], 3, 3)
    z = points_cam[..., 2:3].clamp(min=depth_floor_m)
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
    rho_px: float,
    conf_power: float,
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


@dataclass(frozen=True)
class ChamferTargets:
    """The nearest pairs of L_3D for fixed correspondences, reduced to per-vertex targets.

    For K persons with N (padded) model vertices each: vertex_mask (K, N) bool, the vertices that
    take part (visible, person with points); vertex_target (K, N, 3) the nearest point of each
    vertex; point_count (K, N) how many points have this vertex as their nearest, point_mean
    (K, N, 3) their mean and point_rest (K,) the sum over the person's points of
    |p - point_mean[nearest(p)]|^2; num_points (K,) float. With these, the point -> vertex sum
    sum_p |p - v_n(p)|^2 = sum_n count_n |v_n - mean_n|^2 + rest is a dense per-vertex term:
    no gather and no scatter per step, and no order-dependent atomic adds on a GPU.
    """

    vertex_mask: torch.Tensor
    vertex_target: torch.Tensor
    point_count: torch.Tensor
    point_mean: torch.Tensor
    point_rest: torch.Tensor
    num_points: torch.Tensor

    def take(self, rows: torch.Tensor) -> ChamferTargets:
        """The targets of some persons, rows (k,) int64."""
        return ChamferTargets(
            self.vertex_mask[rows],
            self.vertex_target[rows],
            self.point_count[rows],
            self.point_mean[rows],
            self.point_rest[rows],
            self.num_points[rows],
        )


@torch.no_grad()
def chamfer_targets(
    vertices: torch.Tensor,
    vertex_mask: torch.Tensor,
    points: torch.Tensor,
    point_person: torch.Tensor,
    method: str = "auto",
    chunk_elements: int = 2**27,
) -> ChamferTargets:
    """Nearest pairs both ways between each person's vertices and points (no gradient).

    vertices (K, N, 3) and vertex_mask (K, N) bool: model vertices (padded); points (P, 3) in
    the same frame (m) and point_person (P,) int64 in [0, K): ragged LiDAR points. A person
    takes part when it has a vertex and a point. method: 'grid' (exact grid search per person,
    numba, float64: :mod:`tasks.fit.nearest`), 'brute' (distance matrices for chunks of persons of at most
    ``chunk_elements`` entries; used on GPUs) or 'auto' (grid on the CPU).
    """
    K = vertex_mask.shape[0]
    dev = vertices.device
    num_points = torch.bincount(point_person, minlength=K)[:K]
    active = (vertex_mask.sum(1) > 0) & (num_points > 0)
    vm = vertex_mask & active[:, None]
    pm = active[point_person]
    if method == "grid" or (method == "auto" and dev.type == "cpu"):
        target, count, mean, rest = _targets_grid(vertices, vm, points, point_person, pm)
    else:
        target, count, mean, rest = _targets_brute(
            vertices, vm, points, point_person, pm, chunk_elements
        )
    f = vertices.dtype
    return ChamferTargets(vm, target.to(f), count.to(f), mean.to(f), rest.to(f), num_points.to(f))


def _targets_grid(vertices, vm, points, point_person, pm):
    """CPU path of chamfer_targets: exact grid search per person (tasks.fit.nearest), float64."""
    from tasks.fit.nearest import chamfer_pairs

    K = vm.shape[0]
    dev = vertices.device
    person = point_person.cpu().numpy()
    order = np.argsort(person, kind="stable")
    keep = pm.cpu().numpy()[order]
    order = order[keep]
    bounds = np.searchsorted(person[order], np.arange(K + 1))
    out = chamfer_pairs(
        vertices.detach().cpu().double().numpy(),
        vm.cpu().numpy(),
        np.ascontiguousarray(points.cpu().double().numpy()[order]),
        bounds,
    )
    return tuple(torch.from_numpy(a).to(dev) for a in out)


def _targets_brute(vertices, vm, points, point_person, pm, chunk_elements):
    """Device path of chamfer_targets: per chunk of persons, the (N x P_max) distance matrix of
    each; the point -> vertex sums as a one-hot matrix product (dense, order-fixed)."""
    K, N = vm.shape
    dev, f = vertices.device, vertices.dtype
    counts = torch.bincount(point_person, minlength=K)[:K]
    pmax = max(int(counts.max().item()) if K else 0, 1)
    starts = torch.cumsum(counts, 0) - counts
    slot = torch.arange(len(point_person), device=dev) - starts[point_person]
    pad = torch.zeros(K, pmax, 3, dtype=f, device=dev)
    pad_mask = torch.zeros(K, pmax, dtype=torch.bool, device=dev)
    pad[point_person, slot] = points.to(f)
    pad_mask[point_person, slot] = pm
    # Padding is parked far away (1e4 m, opposite corners) instead of masking the distance
    # matrix: a valid row never picks it while any valid partner exists. Both sets are shifted
    # by the person's point centroid first: cdist expands |a - b|^2, which loses precision at
    # long range.
    c = (pad * pad_mask[..., None]).sum(1) / pad_mask.sum(1).clamp(min=1)[:, None]
    a = torch.where(vm[..., None], vertices.detach() - c[:, None], torch.full_like(vertices, 1e4))
    b = torch.where(pad_mask[..., None], pad - c[:, None], torch.full_like(pad, -1e4))
    target = torch.zeros(K, N, 3, dtype=f, device=dev)
    count = torch.zeros(K, N, dtype=f, device=dev)
    mean = torch.zeros(K, N, 3, dtype=f, device=dev)
    rest = torch.zeros(K, dtype=f, device=dev)
    step = max(1, chunk_elements // (N * pmax))
    ar = torch.arange(N, device=dev)
    for s in range(0, K, step):
        e = min(K, s + step)
        d = torch.cdist(a[s:e], b[s:e])  # only compared, never differentiated
        target[s:e] = torch.gather(pad[s:e], 1, d.argmin(2)[..., None].expand(-1, -1, 3))
        near = d.argmin(1)  # (k, P_max) nearest vertex of each point
        onehot = ((near[:, None, :] == ar[None, :, None]) & pad_mask[s:e, None, :]).to(
            f
        )  # (k, N, P_max)
        count[s:e] = onehot.sum(2)
        mean[s:e] = (onehot @ pad[s:e]) / count[s:e].clamp(min=1.0)[..., None]
        near_mean = torch.gather(mean[s:e], 1, near[..., None].expand(-1, -1, 3))
        rest[s:e] = (((pad[s:e] - near_mean) ** 2).sum(-1) * pad_mask[s:e]).sum(1)
    target = torch.where(vm[..., None], target, torch.zeros_like(target))
    return target, count, mean, rest


def chamfer_loss(
    vertices: torch.Tensor,
    targets: ChamferTargets,
    vertex_max_m: float | None = None,
) -> torch.Tensor:
    """L_3D: symmetric, size-normalised squared Chamfer distance per person (K,), m^2.

    vertices (K, N, 3) model vertices (the rows of :func:`chamfer_targets`, same frame);
    targets: the nearest pairs, found without gradient by :func:`chamfer_targets` and reused for
    a few steps (they change slowly). Squared distances are formed from coordinate differences,
    so the gradient is finite at zero distance. A person with no vertex or no point
    contributes 0.
    vertex_max_m: cap of the vertex -> point distance (the term then contributes the constant
    vertex_max_m^2 and no gradient); None = the paper's uncapped form. Why: the visible set of
    backface culling over-approximates what the LiDAR saw (self-occlusion, grazing faces, gaps
    between scan lines); pulling such vertices onto the nearest return drags the mesh towards the
    sensor and thins it (measured: -31 mm depth bias starting from the true body, Ouster-128).
    The point -> vertex direction is never capped: every return lies on the body.
    """
    t = targets
    vm = t.vertex_mask.to(vertices.dtype)
    d_vp = _sq_norm(vertices - t.vertex_target)
    if vertex_max_m is not None:
        d_vp = d_vp.clamp(max=float(vertex_max_m) ** 2)
    nv = vm.sum(1)
    term_v = (d_vp * vm).sum(1) / nv.clamp(min=1.0)
    term_p = (
        (_sq_norm(vertices - t.point_mean) * t.point_count).sum(1) + t.point_rest
    ) / t.num_points.clamp(min=1.0)
    return torch.where((nv > 0) & (t.num_points > 0), term_v + term_p, torch.zeros_like(term_v))


def _sq_norm(d: torch.Tensor) -> torch.Tensor:
    """|d|^2 over the last axis of 3 (written out: a reduction over 3 is slow on the CPU)."""
    x, y, z = d.unbind(-1)
    return x * x + y * y + z * z


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
