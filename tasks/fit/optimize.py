"""Batched fitting of SMPL bodies to keypoints + LiDAR (paper Sec. Human Mesh Optimization).

Frame: the fit works in the OpenCV camera frame (x right, y down, z forward, metres): L_J needs
only K there, and the monocular initial estimate lives there. LiDAR points arrive in the lidar
frame and are moved into the cam frame with ``T_cam_from_lidar``; every returned array is in the
cam frame (use :func:`tasks.body.model.rigid_transform_params` to express a fit elsewhere).

Steps for a batch of B persons (:func:`fit_persons`):
1. visibility filter on the initial mesh (appendix A) -> visible vertices, occluded joints;
2. rigid ICP of the visible vertices onto the person's points; (R, t) moves the global
   orientation and translation about the root joint;
3. visibility again on the aligned mesh, then Adam on (beta, theta, t) minimising
   L_J + l_3D L_3D + l_theta L_theta + l_a L_a + l_beta L_beta + l_occ L_theta,occ.
   Each step poses only the vertices the loss reads (the visible set, fixed after step 3, and
   the face keypoints); the Chamfer pairs and the pose blend shapes (no gradient through them
   in between) are refreshed every ``nn_every`` steps, and a person
   whose objective improved by less than ``converge_rtol`` (relative) between two refreshes
   stops there and leaves the batch.
Persons do not interact: every term is per person, the batch loss is their sum, and a person's
stop depends on its own objective only, so a person's fit does not depend on which batch it was
in (up to float rounding of batched matrix products).

Threads: the kernel never changes a global thread setting. Its torch operations use torch's
intra-op pool, which the caller sizes (``torch.set_num_threads``; a Dask worker should size it to
its own allotment, as torch defaults to every core); its nearest-pair searches (numba) run on the
calling thread.
"""

from __future__ import annotations

import copy
import hashlib
import math
from dataclasses import dataclass

import numpy as np
import torch

from tasks.body.params import BodyParams
from tasks.body.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from tasks.conventions import COCO_TO_SMPL_JOINT
from tasks.fit import losses as L
from tasks.fit.icp import icp_align, rigid_update_params
from tasks.fit.settings import FitSettings
from tasks.fit.visibility import Visibility, vertex_parts, visibility_masks
from tasks.fit.weights import FitWeights

_COCO_JOINT_IDX = [COCO_TO_SMPL_JOINT[i] for i in range(5, 17)]
#: layout of the packed parameter rows (B, 85): betas, global_orient, body_pose, transl
_SLICES = {
    "betas": slice(0, 10),
    "global_orient": slice(10, 13),
    "body_pose": slice(13, 82),
    "transl": slice(82, 85),
}
_ADAM_BETAS = (0.9, 0.999)
_ADAM_EPS = 1e-8
#: a person with fewer LiDAR points is fitted to its keypoints alone (no ICP, no L_3D): a few
#: returns pin nothing down. Not ``fit.min_points`` (10 by default), which leaves such
#: detections out of the fit stage altogether; this is the kernel's own floor below it.
LIDAR_MIN_POINTS = 10


def torch_device(name: str) -> str:
    """The device of ``FitSettings.device``: 'auto' is CUDA where present, else the CPU."""
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return name


@dataclass(frozen=True)
class FitResult(BodyParams):
    """Fitted bodies, cam frame, numpy float32: the parameters (:class:`BodyParams`), and
    vertices (B, V, 3) m; joints (B, 24, 3) m;
    residuals: dict of (B,) float64 final term values ('L_J', 'L_3D', 'L_theta', 'L_a',
    'L_beta', 'L_occ', 'total', 'icp_fitness', 'visible_vertices', 'steps': Adam steps taken)."""

    vertices: np.ndarray
    joints: np.ndarray
    residuals: dict

    def params(self) -> BodyParams:
        """The fitted parameters alone (e.g. to warm-start the track's next frame)."""
        return BodyParams.of(self)


def model_keypoints(
    joints: torch.Tensor, vertices: torch.Tensor, keypoint_vertex_ids
) -> torch.Tensor:
    """COCO-17 keypoints of the model (B, 17, 3): face points from vertices, body from joints."""
    ids = torch.as_tensor(np.asarray(keypoint_vertex_ids), device=vertices.device, dtype=torch.long)
    return torch.cat([vertices[:, ids], joints[:, _COCO_JOINT_IDX]], dim=1)


def ragged_points(points, point_mask) -> tuple[np.ndarray, np.ndarray]:
    """Padded point sets (B, P, 3) with point_mask (B, P) bool -> (points (sum, 3) in person
    order, counts (B,) int64): the layout :func:`fit_persons` takes."""
    pts, mask = np.asarray(points), np.asarray(point_mask, dtype=bool)
    return pts[mask], mask.sum(1).astype(np.int64)


def fit_persons(
    model,
    prior,
    init: BodyParams,
    keypoints,
    K,
    T_cam_from_lidar,
    points,
    counts,
    weights: FitWeights,
    settings: FitSettings,
    *,
    use_visibility: bool = True,
    use_icp: bool = True,
    keypoint_weights=None,
    frozen: tuple[str, ...] = (),
    coupling=None,
    posed: bool = True,
    terms: bool = True,
) -> FitResult:
    """Fit B persons jointly (batched Adam), returning cam-frame bodies.

    model: BodyModel; prior: callable body_pose (B, 69) -> (B,) neg. log-likelihood (the GMM);
    init: BodyParams (cam frame) of the initial estimate (oracle, CLIFF, or the track's previous
    frame for a warm start); keypoints (B, 17, 3) COCO-17 (u, v, confidence), pixels;
    K (B, 3, 3) or (3, 3); T_cam_from_lidar (4, 4) or (B, 4, 4) float64; points (P, 3) lidar
    frame (m), the persons' points one after another, counts (B,) how many belong to each
    (:func:`ragged_points` converts padded sets). Persons with fewer than
    :data:`LIDAR_MIN_POINTS` points skip ICP and L_3D. weights: the objective's (a preset with
    its settings); settings: iterations, learning rate, ``nn_every`` (recompute the Chamfer
    nearest pairs and the pose blend shapes every this many steps: both change slowly; 1 = the
    exact gradient), ``chamfer_vertex_max_m`` (see :func:`tasks.fit.losses.chamfer_loss`),
    ``converge_rtol``, device (:func:`torch_device`) and seed; the rest of
    :class:`tasks.fit.settings.FitSettings` is the stage's (which persons, batches).
    use_visibility=False uses every vertex and flags no joint occluded, use_icp=False skips the
    rigid alignment (ablations). Deterministic for a fixed seed on a device.
    frozen: parameter groups held at their initial values ('betas', 'global_orient',
    'body_pose', 'transl'; e.g. a track's shape). coupling: a term tying persons together,
    joints (B, 24, 3) cam frame -> (B,) added to the objective (residual 'L_coupling'; e.g. the
    acceleration penalty of tasks/fit/refine.py); with it no person leaves the batch early.
    posed=False: vertices / joints (B, 0, 3) (a caller that poses the bodies itself);
    terms=False: residuals 'icp_fitness', 'visible_vertices' and 'steps' only (the loss terms at
    the result cost a last refresh of the Chamfer pairs; a caller that refits skips them).
    """
    B = len(init)
    kp_np, pts_l, counts = np.asarray(keypoints), np.asarray(points), np.asarray(counts).reshape(-1)
    _check_inputs(B, kp_np, pts_l, counts)
    s = settings
    torch.manual_seed(s.seed)
    dev = torch.device(torch_device(s.device))
    if model.v_template.device != dev:
        model = copy.deepcopy(model).to(dev)  # never move a shared (memoised) model in place
    buffers = list(prior.buffers()) if isinstance(prior, torch.nn.Module) else []
    if buffers and buffers[0].device != dev:
        prior = copy.deepcopy(prior).to(dev)  # not one host-to-device copy per step
    pts = _PersonPoints.build(pts_l, counts, T_cam_from_lidar, LIDAR_MIN_POINTS, dev)
    f32 = torch.float32
    kp = torch.as_tensor(kp_np, dtype=f32, device=dev)
    Kt = torch.as_tensor(np.asarray(K), dtype=f32, device=dev).expand(B, 3, 3)
    kw = (
        None
        if keypoint_weights is None
        else torch.as_tensor(np.asarray(keypoint_weights), dtype=f32, device=dev)
    )
    vis_fn = _visibility_fn(model, kp[..., 2], weights, use_visibility, s.data_vertices)
    x = torch.cat(
        [
            torch.as_tensor(np.asarray(getattr(init, k)), dtype=f32, device=dev).reshape(B, -1)
            for k in _SLICES
        ],
        1,
    )

    icp_fitness = np.zeros(B)
    if use_icp:
        x, icp_fitness = _align_rigidly(model, x, vis_fn(_posed(model, x).vertices), pts)
    problem = _Problem.build(
        model, prior, x, vis_fn, pts, kp, Kt, kw, weights, s.chamfer_vertex_max_m
    )
    problem.coupling = coupling
    free = torch.ones(x.shape[1], dtype=x.dtype, device=dev)
    for name in frozen:
        free[_SLICES[name]] = 0.0
    x, steps = _optimize(
        problem,
        x,
        s.iterations,
        s.learning_rate,
        s.nn_every,
        None if coupling else s.converge_rtol,
        free,
    )

    residuals = {}
    with torch.no_grad():
        if terms:
            _, final = problem.objective(x, refresh=True)
            residuals = {k: v.double().cpu().numpy() for k, v in final.items()}
        full = _posed(model, x) if posed else None
    residuals["icp_fitness"] = icp_fitness
    residuals["visible_vertices"] = problem.visible_count.cpu().numpy().astype(np.float64)
    residuals["steps"] = steps.cpu().numpy().astype(np.float64)
    rows = {k: x[:, s].cpu().numpy().astype(np.float32) for k, s in _SLICES.items()}
    none = np.zeros((B, 0, 3), np.float32)
    return FitResult(
        vertices=none if full is None else full.vertices.cpu().numpy().astype(np.float32),
        joints=none if full is None else full.joints.cpu().numpy().astype(np.float32),
        residuals=residuals,
        **rows,
    )


def _check_inputs(B: int, keypoints: np.ndarray, points: np.ndarray, counts: np.ndarray) -> None:
    if keypoints.shape != (B, 17, 3):
        raise ValueError(
            f"fit_persons: keypoints has shape {keypoints.shape}, expected ({B}, 17, 3)"
        )
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"fit_persons: points has shape {points.shape}, expected (P, 3)")
    if counts.shape != (B,) or (counts < 0).any() or counts.sum() != len(points):
        raise ValueError(
            f"fit_persons: counts {counts.tolist()} must be {B} non-negative numbers "
            f"summing to the {len(points)} points"
        )


def _posed(model, x: torch.Tensor, vertex_subset=None):
    """The model posed by packed parameter rows x (B, 85)."""
    return model(*(x[:, s] for s in _SLICES.values()), vertex_subset=vertex_subset)


@dataclass(frozen=True)
class _PersonPoints:
    """Ragged cam-frame points: xyz (P, 3) float32, person (P,) int64, has (B,) bool (persons
    with at least min_count points; the others' points are dropped)."""

    xyz: torch.Tensor
    person: torch.Tensor
    has: torch.Tensor

    @staticmethod
    def build(
        points_lidar: np.ndarray, counts: np.ndarray, T_cam_from_lidar, min_count: int, dev
    ) -> _PersonPoints:
        B = len(counts)
        person = np.repeat(np.arange(B), counts)
        T = np.broadcast_to(np.asarray(T_cam_from_lidar, dtype=np.float64), (B, 4, 4))[person]
        cam = np.einsum("pij,pj->pi", T[:, :3, :3], points_lidar.astype(np.float64)) + T[:, :3, 3]
        has = counts >= max(min_count, 1)
        keep = has[person]
        return _PersonPoints(
            torch.as_tensor(cam[keep], dtype=torch.float32, device=dev),
            torch.as_tensor(person[keep], device=dev),
            torch.as_tensor(has, device=dev),
        )


def _visibility_fn(
    model, conf: torch.Tensor, weights: FitWeights, use_visibility: bool, data_vertices
):
    """verts (B, V, 3) -> Visibility of the persons whose keypoint confidences are conf (B, 17);
    with ``data_vertices``, only that many vertices spread evenly over the template's surface
    count as visible (:func:`uniform_vertex_subset`): ICP and L_3D read no others."""
    faces = model.faces_tensor
    parts = torch.as_tensor(vertex_parts(model.lbs_weights), device=conf.device)
    keep = None
    if data_vertices is not None and data_vertices < model.num_vertices:
        template = model.v_template.detach().cpu().numpy()
        keep = torch.as_tensor(_memo_subset(template, data_vertices), device=conf.device)

    def visibility(verts: torch.Tensor) -> Visibility:
        if use_visibility:
            vis = visibility_masks(verts, faces, parts, conf, w=weights.w, j_conf=weights.j_conf)
        else:
            ones = torch.ones(verts.shape[:2], dtype=torch.bool, device=verts.device)
            none = torch.zeros(verts.shape[0], 24, dtype=torch.bool, device=verts.device)
            vis = Visibility(ones, none, ones)
        if keep is None:
            return vis
        return Visibility(vis.vertex_mask & keep, vis.occluded_joints, vis.front_vertex_mask)

    return visibility


_SUBSETS: dict[tuple[str, int], np.ndarray] = {}


def _memo_subset(template: np.ndarray, count: int) -> np.ndarray:
    key = (hashlib.sha1(np.ascontiguousarray(template).tobytes()).hexdigest(), count)
    if key not in _SUBSETS:
        _SUBSETS[key] = uniform_vertex_subset(template, count)
    return _SUBSETS[key]


def uniform_vertex_subset(vertices: np.ndarray, count: int) -> np.ndarray:
    """(V,) bool: ``count`` of the (V, 3) vertices spread evenly over the shape, by farthest-point
    sampling from vertex 0 (deterministic; each pick the vertex farthest from those picked)."""
    points = np.asarray(vertices, np.float64)
    chosen = np.zeros(points.shape[0], bool)
    nearest = np.full(points.shape[0], np.inf)
    pick = 0
    for _ in range(min(count, points.shape[0])):
        chosen[pick] = True
        nearest = np.minimum(nearest, np.sum((points - points[pick]) ** 2, axis=1))
        pick = int(np.argmax(nearest))
    return chosen


def _align_rigidly(
    model, x: torch.Tensor, vis: Visibility, pts: _PersonPoints
) -> tuple[torch.Tensor, np.ndarray]:
    """Steps 1-2: ICP of each person's visible vertices onto its points; returns the packed rows
    with global_orient and transl moved by the rigid motion, and the ICP fitness (B,)."""
    with torch.no_grad():
        verts = _posed(model, x).vertices
        j0 = model.rest_joints(x[:, _SLICES["betas"]])[:, 0]
    idx, valid = _visible_index(vis.vertex_mask & pts.has[:, None])
    res = icp_align(
        torch.gather(verts, 1, idx[..., None].expand(-1, -1, 3)),
        valid,
        pts.xyz,
        pts.person,
        min_person_points=LIDAR_MIN_POINTS,
    )
    Rg = axis_angle_to_matrix(x[:, _SLICES["global_orient"]].double()).cpu().numpy()
    tr = x[:, _SLICES["transl"]].double().cpu().numpy()
    Rg, tr = rigid_update_params(
        Rg, tr, j0.double().cpu().numpy(), res.T[:, :3, :3], res.T[:, :3, 3]
    )
    x = x.clone()
    x[:, _SLICES["global_orient"]] = matrix_to_axis_angle(torch.as_tensor(Rg)).to(x)
    x[:, _SLICES["transl"]] = torch.as_tensor(tr).to(x)
    return x, res.fitness


def _visible_index(mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Padded indices (B, n) of the True entries of mask (B, V) (ascending), and their validity
    (B, n); padding points at index 0."""
    counts = mask.sum(1)
    n = int(counts.max().item()) if mask.shape[0] else 0
    order = torch.argsort((~mask).to(torch.int8), dim=1, stable=True)[:, :n]
    valid = torch.arange(n, device=mask.device)[None, :] < counts[:, None]
    return torch.where(valid, order, torch.zeros_like(order)), valid


class _Problem:
    """The objective of the persons still being optimised (step 3), with what stays fixed
    during the optimisation: the vertex subset each person's loss reads (face keypoint vertices
    first, then the visible set of the aligned mesh), occluded joints, initial rotations,
    keypoints, and the current Chamfer targets. Rows can be dropped (:meth:`keep`)."""

    def __init__(
        self, model, prior, weights, cap, subset, occluded, R0, kp, Kt, kw, pts, vertex_mask
    ):
        self.model, self.prior, self.weights, self.cap = model, prior, weights, cap
        self.subset, self.occluded, self.R0, self.kp, self.Kt, self.kw = (
            subset,
            occluded,
            R0,
            kp,
            Kt,
            kw,
        )
        self.pts, self.vertex_mask = pts, vertex_mask
        self.targets: L.ChamferTargets | None = None
        self.coupling = None  # joints (k, 24, 3) -> (k,), or None
        self.offsets: torch.Tensor | None = None  # pose blend shapes, (k, V, 3)
        self.visible_count = vertex_mask.sum(1)

    @staticmethod
    def build(model, prior, x, vis_fn, pts: _PersonPoints, kp, Kt, kw, weights, cap) -> _Problem:
        B = x.shape[0]
        dev = x.device
        with torch.no_grad():
            vis = vis_fn(_posed(model, x).vertices)
            R0 = axis_angle_to_matrix(x[:, 10:82].reshape(B, 24, 3))
        # no points: no L_3D, no visible set needed
        order, valid = _visible_index(vis.vertex_mask & pts.has[:, None])
        kp_ids = torch.as_tensor(np.asarray(model.keypoint_vertex_ids), device=dev).expand(B, -1)
        ids = torch.cat([kp_ids, order], 1)
        vertex_mask = torch.cat([torch.zeros_like(kp_ids, dtype=torch.bool), valid], 1)
        problem = _Problem(
            model,
            prior,
            weights,
            cap,
            model.select_vertices(ids),
            vis.occluded_joints,
            R0,
            kp,
            Kt,
            kw,
            pts,
            vertex_mask,
        )
        problem.visible_count = vis.vertex_mask.sum(1)
        return problem

    def take(self, rows: torch.Tensor) -> _Problem:
        """The problem of persons rows (k,) int64 only (in the current numbering)."""
        new_index = torch.full((self.kp.shape[0],), -1, dtype=torch.long, device=rows.device)
        new_index[rows] = torch.arange(len(rows), device=rows.device)
        p = self.pts
        on = new_index[p.person] >= 0
        out = _Problem(
            self.model,
            self.prior,
            self.weights,
            self.cap,
            self.subset.take(rows),
            self.occluded[rows],
            self.R0[rows],
            self.kp[rows],
            self.Kt[rows],
            self.kw,
            _PersonPoints(p.xyz[on], new_index[p.person[on]], p.has[rows]),
            self.vertex_mask[rows],
        )
        out.targets = None if self.targets is None else self.targets.take(rows)
        out.offsets = None if self.offsets is None else self.offsets[rows]
        out.visible_count = self.visible_count[rows]
        out.coupling = self.coupling
        return out

    def objective(self, x: torch.Tensor, refresh: bool) -> tuple:
        """Pose the vertex subset for parameter rows x (k, 85) and evaluate every term (k,).
        refresh: first recompute the pose blend shapes from this pose and, from the posed
        vertices, the Chamfer targets; in between both are held fixed (no gradient flows
        through the pose blend shapes then: a second-order term, and the (k, 207) x (207, 3V)
        product it needs is the largest of a step)."""
        w = self.weights
        if refresh or self.offsets is None:
            with torch.no_grad():
                self.offsets = self.model.pose_offsets(
                    x[:, _SLICES["global_orient"]], x[:, _SLICES["body_pose"]]
                )
        o = self.model(
            *(x[:, s] for s in _SLICES.values()),
            vertex_subset=self.subset,
            pose_offsets=self.offsets,
        )
        if refresh or self.targets is None:
            self.targets = L.chamfer_targets(
                o.vertices.detach(), self.vertex_mask, self.pts.xyz, self.pts.person
            )
        bp = x[:, _SLICES["body_pose"]]
        k = x.shape[0]
        keypoints = torch.cat([o.vertices[:, :5], o.joints[:, _COCO_JOINT_IDX]], dim=1)
        R = axis_angle_to_matrix(x[:, 10:82].reshape(k, 24, 3))
        t = {
            "L_J": L.reprojection_loss(
                keypoints, self.kp, self.Kt, w.rho_px, w.conf_power, self.kw
            ),
            "L_3D": L.chamfer_loss(o.vertices, self.targets, vertex_max_m=self.cap),
            "L_theta": self.prior(bp),
            "L_a": L.hyperextension_loss(bp),
            "L_beta": L.shape_loss(x[:, _SLICES["betas"]]),
            "L_occ": L.occlusion_pose_loss(R, self.R0, self.occluded),
        }
        t["total"] = (
            t["L_J"]
            + w.factor(w.lambda_3d) * t["L_3D"]
            + w.factor(w.lambda_theta) * t["L_theta"]
            + w.factor(w.lambda_a) * t["L_a"]
            + w.factor(w.lambda_beta) * t["L_beta"]
            + w.factor(w.lambda_occ) * t["L_occ"]
        )
        if self.coupling is not None:
            t["L_coupling"] = self.coupling(o.joints)
            t["total"] = t["total"] + t["L_coupling"]
        return o, t


def _optimize(
    problem: _Problem,
    x: torch.Tensor,
    iterations: int,
    lr: float,
    nn_every: int,
    converge_rtol: float | None,
    free: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Adam on the packed rows x (B, 85) (torch.optim.Adam's update, written out so that rows
    can leave the batch with their moments); free (85,): 0 where a parameter is held fixed.
    Returns the final rows and the steps per person."""
    B = x.shape[0]
    dev = x.device
    out = x.clone()
    steps = torch.full((B,), iterations, dtype=torch.long, device=dev)
    index = torch.arange(B, device=dev)  # original person of each current row
    x = x.clone()
    m, v = torch.zeros_like(x), torch.zeros_like(x)
    b1, b2 = _ADAM_BETAS
    nn_every = max(1, nn_every)
    last = None  # objective at the previous refresh
    for step in range(iterations):
        if len(index) == 0:
            break
        refresh = step % nn_every == 0
        xr = x.detach().requires_grad_(True)
        _, t = problem.objective(xr, refresh)
        total = t["total"]
        keep = None
        if refresh and converge_rtol is not None:
            now = total.detach()
            if last is not None:
                done = (last - now) <= converge_rtol * now.abs()
                if bool(done.any()):
                    out[index[done]] = x[done]
                    steps[index[done]] = step
                    keep = (~done).nonzero().reshape(-1)
            last = now
        (g,) = torch.autograd.grad(total.sum(), xr)
        if free is not None:
            g = g * free
        if keep is not None:
            x, m, v, g, index, last = x[keep], m[keep], v[keep], g[keep], index[keep], last[keep]
            problem = problem.take(keep)
        m.mul_(b1).add_(g, alpha=1 - b1)
        v.mul_(b2).addcmul_(g, g, value=1 - b2)
        bc1, bc2 = 1 - b1 ** (step + 1), 1 - b2 ** (step + 1)
        x = x.addcdiv(m, (v.sqrt() / math.sqrt(bc2)).add_(_ADAM_EPS), value=-lr / bc1)
    out[index] = x
    return out, steps
