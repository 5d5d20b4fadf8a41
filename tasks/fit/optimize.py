"""Batched fitting of SMPL bodies to keypoints + LiDAR (paper Sec. Human Mesh Optimization).

Frame: the fit works in the OpenCV camera frame (x right, y down, z forward, metres): L_J needs
only K there, and the monocular initial estimate lives there. LiDAR points arrive in the lidar
frame and are moved into the cam frame with ``T_cam_from_lidar``; every returned array is in the
cam frame (use :func:`tasks.body.model.rigid_transform_params` to express a fit elsewhere).

Steps per chunk of B persons (all batched except ICP, which is per person on the CPU):
1. visibility filter on the initial mesh (appendix A) -> visible vertices, occluded joints;
2. rigid ICP of the visible vertices onto the person's points; (R, t) moves the global
   orientation and translation about the root joint;
3. visibility again on the aligned mesh, then Adam on (beta, theta, t) minimising
   L_J + l_3D L_3D + l_theta L_theta + l_a L_a + l_beta L_beta + l_occ L_theta,occ.
Persons do not interact: the batch loss is the sum of per-person losses, so a person's fit does
not depend on which chunk it was in.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
import torch

from tasks.body.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from tasks.conventions import COCO_TO_SMPL_JOINT
from tasks.fit import losses as L
from tasks.fit.icp import icp_align, rigid_update_params
from tasks.fit.init_oracle import BodyParams
from tasks.fit.settings import FitSettings
from tasks.fit.visibility import Visibility, vertex_parts, visibility_masks

_COCO_JOINT_IDX = [COCO_TO_SMPL_JOINT[i] for i in range(5, 17)]


@dataclass(frozen=True)
class FitResult:
    """Fitted bodies, cam frame, numpy float32. betas (B, 10); global_orient (B, 3) and body_pose
    (B, 69) axis-angle (rad); transl (B, 3) m; vertices (B, V, 3) m; joints (B, 24, 3) m;
    residuals: dict of (B,) float64 final term values ('L_J', 'L_3D', 'L_theta', 'L_a',
    'L_beta', 'L_occ', 'total', 'icp_fitness', 'visible_vertices')."""

    betas: np.ndarray
    global_orient: np.ndarray
    body_pose: np.ndarray
    transl: np.ndarray
    vertices: np.ndarray
    joints: np.ndarray
    residuals: dict

    def params(self) -> BodyParams:
        """The fitted parameters (e.g. to warm-start the track's next frame)."""
        return BodyParams(self.betas, self.global_orient, self.body_pose, self.transl)


def model_keypoints(joints: torch.Tensor, vertices: torch.Tensor, keypoint_vertex_ids) -> torch.Tensor:
    """COCO-17 keypoints of the model (B, 17, 3): face points from vertices, body from joints."""
    ids = torch.as_tensor(np.asarray(keypoint_vertex_ids), device=vertices.device, dtype=torch.long)
    return torch.cat([vertices[:, ids], joints[:, _COCO_JOINT_IDX]], dim=1)


def _visible_index(mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Padded indices (B, N) of True entries of mask (B, V), and their validity (B, N)."""
    counts = mask.sum(1)
    n = max(int(counts.max().item()) if mask.numel() else 0, 1)
    order = torch.argsort((~mask).to(torch.int8), dim=1, stable=True)[:, :n]
    valid = torch.arange(n, device=mask.device)[None, :] < counts[:, None]
    return order, valid


def _gather_rows(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    return torch.gather(x, 1, idx[..., None].expand(-1, -1, x.shape[-1]))


def fit_persons(
    model,
    prior,
    init: BodyParams,
    keypoints,
    K,
    T_cam_from_lidar,
    points,
    point_mask,
    weights: L.FitWeights = L.FIT_PRESETS["3dpw"],
    iterations: int = FitSettings.iterations,
    lr: float = 0.02,
    device: str = "cpu",
    seed: int = 0,
    use_visibility: bool = True,
    use_icp: bool = True,
    keypoint_weights=None,
    icp_max_rotation_deg: float = 30.0,
    min_points: int = 10,
    nn_every: int = 1,
    chamfer_vertex_max_m: float | None = None,
) -> FitResult:
    """Fit B persons jointly (batched Adam), returning cam-frame bodies.

    model: BodyModel; prior: callable body_pose (B, 69) -> (B,) neg. log-likelihood (the GMM);
    init: BodyParams (cam frame) of the initial estimate (oracle, CLIFF, or the track's previous
    frame for a warm start); nn_every: recompute the Chamfer nearest pairs every this many steps
    (the k-d tree search dominates a CPU step; pairs change slowly); chamfer_vertex_max_m: cap of
    the vertex -> point distances in L_3D (see :func:`tasks.fit.losses.chamfer_loss`; None = the
    paper's uncapped Chamfer); keypoints (B, 17, 3) COCO-17 (u, v, confidence), pixels;
    K (B, 3, 3) or (3, 3); T_cam_from_lidar (4, 4) or (B, 4, 4) float64; points (B, P, 3) lidar
    frame (m), padded; point_mask (B, P) bool. Persons with fewer than ``min_points`` points skip
    ICP and L_3D. use_visibility=False uses every vertex and flags no joint occluded (ablation).
    Deterministic for a fixed seed on a given device.
    """
    B = len(init)
    kp_np, pts_in, pm_in = np.asarray(keypoints), np.asarray(points), np.asarray(point_mask)
    for name, arr, shape in (("keypoints", kp_np, (B, 17, 3)), ("points", pts_in, (B, None, 3)), ("point_mask", pm_in, (B, None))):
        if arr.ndim != len(shape) or any(e is not None and a != e for a, e in zip(arr.shape, shape)):
            raise ValueError(f"fit_persons: {name} has shape {arr.shape}, expected {shape} for {B} persons")
    if pm_in.shape[1] != pts_in.shape[1]:
        raise ValueError(f"fit_persons: point_mask {pm_in.shape} does not match points {pts_in.shape}")
    torch.manual_seed(seed)
    dev = torch.device(device)
    f32 = torch.float32
    if model.v_template.device != dev:
        model = copy.deepcopy(model).to(dev)  # never move a shared (memoised) model in place
    kp = torch.as_tensor(np.asarray(keypoints), dtype=f32, device=dev)
    Kt = torch.as_tensor(np.asarray(K), dtype=f32, device=dev)
    T = np.asarray(T_cam_from_lidar, dtype=np.float64)
    T = np.broadcast_to(T, (B, 4, 4))
    pts_l = np.asarray(points, dtype=np.float64).reshape(B, -1, 3)
    pts_np = np.einsum("bij,bpj->bpi", T[:, :3, :3], pts_l) + T[:, None, :3, 3]
    pmask_np = np.asarray(point_mask, dtype=bool).reshape(B, -1)
    has_pts = pmask_np.sum(1) >= min_points
    pmask_np = pmask_np & has_pts[:, None]
    # valid points first, padding trimmed to the largest person (the NN search is B x V x P)
    order = np.argsort(~pmask_np, axis=1, kind="stable")
    keep = max(int(pmask_np.sum(1).max()), 1)
    pts_np = np.take_along_axis(pts_np, order[:, :keep, None], 1)
    pmask_np = np.take_along_axis(pmask_np, order[:, :keep], 1)
    pts = torch.as_tensor(pts_np, dtype=f32, device=dev)
    pmask = torch.as_tensor(pmask_np, device=dev)
    kw = None if keypoint_weights is None else torch.as_tensor(np.asarray(keypoint_weights), dtype=f32, device=dev)
    faces = model.faces_tensor.to(dev)
    parts = torch.as_tensor(vertex_parts(model.lbs_weights), device=dev)
    conf = kp[..., 2]

    def visibility(verts):
        if use_visibility:
            return visibility_masks(verts, faces, parts, conf, w=weights.w, j_conf=weights.j_conf)
        ones = torch.ones(verts.shape[:2], dtype=torch.bool, device=dev)
        return Visibility(ones, torch.zeros(B, 24, dtype=torch.bool, device=dev), ones)

    betas = torch.as_tensor(init.betas, dtype=f32, device=dev)
    go = torch.as_tensor(init.global_orient, dtype=f32, device=dev)
    bp = torch.as_tensor(init.body_pose, dtype=f32, device=dev)
    tr = torch.as_tensor(init.transl, dtype=f32, device=dev)

    # 1-2: visibility on the estimate, then ICP per person.
    icp_fitness = np.zeros(B)
    if use_icp:
        with torch.no_grad():
            out = model(betas, go, bp, tr)
            vis = visibility(out.vertices)
            j0 = model.rest_joints(betas)[:, 0].cpu().numpy()
        verts_np = out.vertices.cpu().numpy()
        vmask_np = vis.vertex_mask.cpu().numpy()
        Rg = axis_angle_to_matrix(go.double()).cpu().numpy()
        tr_np = tr.double().cpu().numpy()
        for b in range(B):
            if not has_pts[b]:
                continue
            res = icp_align(
                verts_np[b][vmask_np[b]], pts_np[b][pmask_np[b]],
                max_rotation_deg=icp_max_rotation_deg, min_points=min_points,
            )
            icp_fitness[b] = res.fitness
            Rg[b], tr_np[b] = rigid_update_params(Rg[b], tr_np[b], j0[b], res.T[:3, :3], res.T[:3, 3])
        go = matrix_to_axis_angle(torch.as_tensor(Rg)).to(dev, f32)
        tr = torch.as_tensor(tr_np, dtype=f32, device=dev)

    # 3: visible set on the aligned mesh; its indices stay fixed during the optimisation.
    with torch.no_grad():
        out = model(betas, go, bp, tr)
        vis = visibility(out.vertices)
        R0 = axis_angle_to_matrix(torch.cat([go[:, None], bp.reshape(B, 23, 3)], 1))
    vidx, vvalid = _visible_index(vis.vertex_mask)
    occluded = vis.occluded_joints

    params = [t.clone().requires_grad_(True) for t in (betas, go, bp, tr)]
    opt = torch.optim.Adam(params, lr=lr)

    pairs = None

    def terms(p_betas, p_go, p_bp, p_tr, refresh=True):
        nonlocal pairs
        o = model(p_betas, p_go, p_bp, p_tr)
        visible = _gather_rows(o.vertices, vidx)
        if refresh or pairs is None:
            c = L.masked_centroid(pts, pmask)[:, None, :]
            pairs = L.nearest_indices((visible - c).detach(), vvalid, pts - c, pmask)
        t = {}
        t["L_J"] = L.reprojection_loss(
            model_keypoints(o.joints, o.vertices, model.keypoint_vertex_ids), kp, Kt,
            weights.rho_px, weights.conf_power, kw,
        )
        t["L_3D"] = L.chamfer_loss(visible, vvalid, pts, pmask, indices=pairs,
                                   vertex_max_m=chamfer_vertex_max_m)
        t["L_theta"] = prior(p_bp)
        t["L_a"] = L.hyperextension_loss(p_bp)
        t["L_beta"] = L.shape_loss(p_betas)
        R = axis_angle_to_matrix(torch.cat([p_go[:, None], p_bp.reshape(B, 23, 3)], 1))
        t["L_occ"] = L.occlusion_pose_loss(R, R0, occluded)
        t["total"] = (
            t["L_J"]
            + weights.scale("3d") * t["L_3D"]
            + weights.scale("theta") * t["L_theta"]
            + weights.scale("a") * t["L_a"]
            + weights.scale("beta") * t["L_beta"]
            + weights.scale("occ") * t["L_occ"]
        )
        return o, t

    for step in range(iterations):
        opt.zero_grad(set_to_none=True)
        _, t = terms(*params, refresh=step % max(1, nn_every) == 0)
        t["total"].sum().backward()
        opt.step()

    with torch.no_grad():
        o, t = terms(*params)
    residuals = {k: v.double().cpu().numpy() for k, v in t.items()}
    residuals["icp_fitness"] = icp_fitness
    residuals["visible_vertices"] = vis.vertex_mask.sum(1).cpu().numpy().astype(np.float64)
    cpu = [p.detach().cpu().numpy().astype(np.float32) for p in params]
    return FitResult(
        betas=cpu[0],
        global_orient=cpu[1],
        body_pose=cpu[2],
        transl=cpu[3],
        vertices=o.vertices.cpu().numpy().astype(np.float32),
        joints=o.joints.cpu().numpy().astype(np.float32),
        residuals=residuals,
    )
