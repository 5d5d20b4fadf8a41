"""A weight-free initial body from a person's LiDAR points and 2D keypoints (``fit.init_provider:
lidar-keypoints``): no network, no ground truth.

Frame: the OpenCV camera frame (x right, y down, z forward, metres), as the fit
(tasks/fit/optimize.py); ``up_cam`` is the direction of gravity's up in that frame (from the
robot's pose). Per person:

1. **shape**: the stature from the points' vertical extent (the highest point; the lowest point,
   or lower where the ankle keypoints lifted onto the person's depth say the feet are lower, less
   the model's ankle height), turned into the minimum-norm betas whose rest height it is (a
   body model's heel-to-crown height is linear in betas);
2. **facing**: the neutral body (arms down, :func:`tasks.body.poses.neutral_pose`) turned about up
   to ``yaw_candidates`` headings, each scored by the LiDAR points (symmetric Chamfer, capped,
   between the points and the candidate's camera-facing vertices after aligning their centroids:
   a body seen side-on is narrower than one seen from the front) and by the keypoints (robust 2D
   error of the candidate's projected keypoints after removing their mean offset, relative to the
   person's height in pixels: which shoulder is left of which says front or back). Scored for the
   keypoints as labelled and mirrored left <-> right (:data:`MIRROR`): tasks/fit/flips.py decides
   between them along the track;
3. **limbs**: hips, knees, shoulders and elbows swung so that each bone points at its child
   keypoint lifted to 3D (depth: the person's points around the keypoint in the image plus a limb
   radius, else the candidate's own joint depth);
4. **position**: the camera-facing vertices' centroid onto the points' centroid (the fit's ICP
   then aligns the visible surface). Without points: the depth at which the neutral body's
   keypoint extent matches the detected one.

:func:`facing_costs` does steps 1-2 for a batch; :func:`initial_bodies` steps 3-4 for a chosen
labelling and heading; :func:`lidar_keypoint_init` chains them, keeping the labels as detected.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from tasks.body.params import BodyParams
from tasks.body.poses import neutral_pose
from tasks.body.rotations import matrix_to_axis_angle
from tasks.conventions import COCO_TO_SMPL_JOINT
from tasks.fit.settings import InitLidarSettings

#: COCO-17 index of each keypoint's left / right counterpart (itself for the nose)
MIRROR: tuple[int, ...] = (0, 2, 1, 4, 3, 6, 5, 8, 7, 10, 9, 12, 11, 14, 13, 16, 15)
#: limbs: (root joint, middle joint, end joint, COCO keypoint of the middle, of the end, the
#: middle joint's hinge axis (template frame: 0 x, 1 y), sign of its flexion about that axis)
_LIMBS: tuple[tuple[int, int, int, int, int, int, float], ...] = (
    (16, 18, 20, 7, 9, 1, -1.0),  # left arm: elbow flexion is a negative y rotation
    (17, 19, 21, 8, 10, 1, 1.0),
    (1, 4, 7, 13, 15, 0, 1.0),  # left leg: knee flexion is a positive x rotation
    (2, 5, 8, 14, 16, 0, 1.0),
)
#: limbs placed together (indices into _LIMBS): the legs. The arms stay as in the neutral pose:
#: placed the same way they made the fit worse (16 benchmark persons, 3dpw preset: MPJPE 40.3 mm
#: with arms and legs placed, 27.6 legs only, 35.0 neither), as an arm crossing the torso in the
#: image has no reliable depth
_PAIRS: tuple[tuple[int, int], ...] = ((2, 3),)
#: limb root joints whose COCO keypoint is the joint itself (shoulders; COCO hips are not SMPL's)
_ROOT_KEYPOINT = {16: 5, 17: 6}
_COCO_JOINT = [COCO_TO_SMPL_JOINT[i] for i in range(5, 17)]


@dataclass(frozen=True)
class FacingCosts:
    """Per person the cost of each candidate heading, for the keypoints as labelled and mirrored.

    facing_cam (B, Y, 3) float64: the candidates' facing directions (unit, horizontal, cam frame);
    cost (B, 2, Y) float64: [:, 0] keypoints as labelled, [:, 1] mirrored (lower is better);
    betas (B, 10) float32: the shape guess; stature_m (B,) float64; has_points (B,) bool: placed
    by LiDAR (else by the keypoints, or nowhere); has_keypoints (B,) bool: two or more confident
    keypoints; view_cam (B, 3) float64: unit direction from the camera to the person."""

    facing_cam: np.ndarray
    cost: np.ndarray
    betas: np.ndarray
    stature_m: np.ndarray
    has_points: np.ndarray
    has_keypoints: np.ndarray
    view_cam: np.ndarray

    def best(self, labelling: np.ndarray | None = None) -> np.ndarray:
        """(B,) index of the cheapest heading of each person's labelling (B,) in {0, 1}
        (None: as labelled)."""
        lab = np.zeros(len(self.cost), np.int64) if labelling is None else np.asarray(labelling)
        return np.argmin(self.cost[np.arange(len(lab)), lab], axis=1)


def mirrored(keypoints: np.ndarray) -> np.ndarray:
    """COCO-17 keypoints (..., 17, C) with left and right exchanged."""
    return np.asarray(keypoints)[..., list(MIRROR), :]


class _Neutral:
    """The neutral body of given betas, posed once in the template frame (no global rotation):
    vertices, joints, rotations per joint, a fixed vertex subsample with normals, keypoints."""

    def __init__(self, model, betas: np.ndarray, body_pose: np.ndarray, score_vertices: int):
        B = len(betas)
        with torch.no_grad():
            out = model(
                torch.as_tensor(betas, dtype=torch.float32),
                torch.zeros(B, 3),
                torch.as_tensor(body_pose, dtype=torch.float32),
                torch.zeros(B, 3),
            )
            rest = model.rest_joints(torch.as_tensor(betas, dtype=torch.float32))
        self.rest_joints = rest.double().numpy()
        self.vertices = out.vertices.double().numpy()
        self.joints = out.joints.double().numpy()
        self.root_rest = self.rest_joints[:, 0]
        step = max(1, int(np.ceil(model.num_vertices / score_vertices)))
        self.sub = np.arange(0, model.num_vertices, step)
        self.sub_vertices = self.vertices[:, self.sub]
        self.sub_normals = _vertex_normals(self.vertices, model.faces, self.sub)
        kv = np.asarray(model.keypoint_vertex_ids)
        self.keypoints = np.concatenate([self.vertices[:, kv], self.joints[:, _COCO_JOINT]], 1)


def _vertex_normals(verts: np.ndarray, faces: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Area-weighted unit normals (B, N, 3) of vertices ``ids`` (N,) of meshes (B, V, 3)."""
    from scipy.sparse import csr_matrix

    f = np.asarray(faces)
    n_f = np.cross(verts[:, f[:, 1]] - verts[:, f[:, 0]], verts[:, f[:, 2]] - verts[:, f[:, 0]])
    incidence = csr_matrix(
        (np.ones(f.size), (f.T.reshape(-1), np.tile(np.arange(len(f)), 3))),
        shape=(verts.shape[1], len(f)),
    )[ids]
    n = np.stack([incidence @ n_f[b] for b in range(len(verts))])
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)


def _frames(up: np.ndarray, facing: np.ndarray) -> np.ndarray:
    """Rotations (..., 3, 3) taking the template (left +x, up +y, facing +z) to the cam frame."""
    left = np.cross(up, facing)
    return np.stack([left, np.broadcast_to(up, facing.shape), facing], -1)


def _stature_betas(model, stature_m: np.ndarray) -> np.ndarray:
    """Minimum-norm betas (B, 10) whose rest (heel-to-crown) height is stature_m (B,): the
    template's height h0 + g . beta between its highest and lowest vertex (linear in beta)."""
    v = model.v_template.double().numpy()
    sd = model.shapedirs.double().numpy()
    top, bottom = int(np.argmax(v[:, 1])), int(np.argmin(v[:, 1]))
    h0 = v[top, 1] - v[bottom, 1]
    g = sd[top, 1] - sd[bottom, 1]
    beta = (np.asarray(stature_m, np.float64) - h0)[:, None] * g[None] / max(g @ g, 1e-12)
    norm = np.linalg.norm(beta, axis=1, keepdims=True)
    return (beta * np.minimum(1.0, 3.0 / np.maximum(norm, 1e-12))).astype(np.float32)


def _project(K: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Pixels (..., 2) of cam-frame points X (..., 3) (depth clamped at 1 cm)."""
    z = np.maximum(X[..., 2:3], 1e-2)
    return (X[..., :2] / z) * np.array([K[0, 0], K[1, 1]]) + np.array([K[0, 2], K[1, 2]])


def _backproject(K: np.ndarray, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Cam-frame points (..., 3) at pixels uv (..., 2) and depths (...,) (pinhole, no skew)."""
    x = (uv[..., 0] - K[0, 2]) / K[0, 0]
    y = (uv[..., 1] - K[1, 2]) / K[1, 1]
    return np.stack([x, y, np.ones_like(x)], -1) * depth[..., None]


def _gm(x2: np.ndarray, sigma: float) -> np.ndarray:
    """Geman-McClure of squared residuals, scaled to [0, 1)."""
    return x2 / (x2 + sigma * sigma)


def _batch_inputs(keypoints, K, up_cam, points_cam, counts):
    """The per-person inputs as arrays: keypoints (B, 17, 3), B, K (3, 3), unit up (B, 3), and
    each person's points (a list of (P_b, 3))."""
    kp = np.asarray(keypoints, np.float64).reshape(-1, 17, 3)
    B = len(kp)
    up = np.broadcast_to(np.asarray(up_cam, np.float64), (B, 3))
    up = up / np.linalg.norm(up, axis=1, keepdims=True)
    pts = _person_points(np.asarray(points_cam, np.float64).reshape(-1, 3), np.asarray(counts))
    return kp, B, np.asarray(K, np.float64), up, pts


def _person_points(points_cam: np.ndarray, counts: np.ndarray) -> list[np.ndarray]:
    ends = np.cumsum(counts)
    return [points_cam[e - c : e].astype(np.float64) for c, e in zip(counts, ends)]


def _subsample(p: np.ndarray, n: int) -> np.ndarray:
    return p if len(p) <= n else p[np.linspace(0, len(p) - 1, n).round().astype(np.int64)]


def facing_costs(
    model,
    keypoints,
    K,
    points_cam,
    counts,
    up_cam,
    settings: InitLidarSettings,
) -> FacingCosts:
    """Steps 1-2 for B persons: the shape guess and the cost of every candidate heading.

    model: BodyModel; keypoints (B, 17, 3) COCO-17 (u, v, confidence), pixels; K (3, 3)
    intrinsics; points_cam (P, 3) the persons' LiDAR points one after another, cam frame (m), and
    counts (B,) how many belong to each; up_cam (3,) or (B, 3) gravity's up in the cam frame.
    """
    s = settings
    kp, B, K, up, pts = _batch_inputs(keypoints, K, up_cam, points_cam, counts)
    conf_ok = kp[..., 2] >= s.keypoint_min_confidence
    has_pts = np.array([len(p) >= max(s.min_lidar_points, 1) for p in pts])
    has_kp = conf_ok.sum(1) >= 2

    neutral = np.tile(neutral_pose(), (B, 1))
    zero = _Neutral(model, np.zeros((1, 10), np.float32), neutral[:1], s.score_vertices)
    stature = np.array(
        [_stature(pts[b], kp[b], conf_ok[b], K, up[b], zero, 0, s) for b in range(B)]
    )
    betas = _stature_betas(model, stature)
    body = _Neutral(model, betas, neutral, s.score_vertices)

    view = np.empty((B, 3))
    for b in range(B):
        view[b] = _view_direction(pts[b], kp[b], conf_ok[b], has_pts[b], K, up[b], body, b)
    Y = s.yaw_candidates
    psi = np.arange(Y) * (2.0 * np.pi / Y)
    e1 = view - (view * up).sum(1, keepdims=True) * up
    e1 /= np.maximum(np.linalg.norm(e1, axis=1, keepdims=True), 1e-12)
    e2 = np.cross(up, e1)
    facing = np.cos(psi)[None, :, None] * e1[:, None] + np.sin(psi)[None, :, None] * e2[:, None]
    cost = np.zeros((B, 2, Y))
    for b in range(B):
        R = _frames(up[b], facing[b])  # (Y, 3, 3)
        if has_pts[b]:
            cost[b] += _lidar_cost(R, body, b, _subsample(pts[b], s.score_points), view[b], s)[None]
        if has_kp[b]:
            cost[b] += s.keypoint_weight * _keypoint_cost(
                R, body, b, kp[b], conf_ok[b], K, pts[b], s
            )
    return FacingCosts(facing, cost, betas, stature, has_pts, has_kp, view)


def _stature(pts, kp, ok, K, up, body: _Neutral, b: int, s: InitLidarSettings) -> float:
    """Heel-to-crown height (m) of one person from its points (and ankles); the neutral model's
    when there are too few points."""
    v = body.vertices[b]
    model_h = float(v[:, 1].max() - v[:, 1].min())
    if len(pts) < max(s.min_lidar_points, 1):
        return model_h
    h = pts @ up
    top, bottom = float(h.max()), float(h.min())
    ankles = [k for k in (15, 16) if ok[k]]
    if ankles:
        depth = float(np.median(pts[:, 2]))
        a = _backproject(K, kp[ankles, :2], np.full(len(ankles), depth)) @ up
        ankle_h = float(body.joints[b, 7, 1] - v[:, 1].min())  # ankle above the sole, rest
        bottom = min(bottom, float(a.min()) - ankle_h)
    return float(np.clip(top - bottom, 1.3, 2.1))


def _view_direction(pts, kp, ok, has_pts, K, up, body: _Neutral, b: int) -> np.ndarray:
    """Unit direction (3,) from the camera to the person: the points' centroid; without points
    the confident keypoints' mean pixel; without either the optical axis."""
    if has_pts:
        c = pts.mean(0)
    elif ok.any():
        c = _backproject(K, kp[ok, :2].mean(0), np.array(1.0))
    else:
        c = np.array([0.0, 0.0, 1.0])
    return c / np.linalg.norm(c)


def _lidar_cost(R, body: _Neutral, b: int, pts, view, s: InitLidarSettings) -> np.ndarray:
    """(Y,) symmetric capped Chamfer (m^2) between the points and each candidate's camera-facing
    vertices after aligning the two centroids, over lidar_sigma_m^2."""
    V = np.einsum("yij,vj->yvi", R, body.sub_vertices[b])  # (Y, N, 3)
    vis = np.einsum("yij,vj->yvi", R, body.sub_normals[b]) @ view < 0.0  # facing the camera
    nv = vis.sum(1)
    c = (V * vis[..., None]).sum(1) / np.maximum(nv, 1)[:, None]
    V = np.where(vis[..., None], V - c[:, None], 1e3)  # hidden vertices parked far away
    cap2 = s.lidar_cap_m**2
    d2 = torch.cdist(torch.as_tensor(pts - pts.mean(0))[None], torch.as_tensor(V)).pow_(2)
    to_mesh = d2.amin(2).clamp_(max=cap2).mean(1).numpy()
    to_points = (d2.amin(1).clamp_(max=cap2).numpy() * vis).sum(1) / np.maximum(nv, 1)
    out = np.where(nv > 0, 0.5 * (to_mesh + to_points), cap2)
    return out / s.lidar_sigma_m**2


def _keypoint_cost(R, body: _Neutral, b: int, kp, ok, K, pts, s: InitLidarSettings) -> np.ndarray:
    """(2, Y) mean confidence-weighted Geman-McClure 2D error of each candidate's keypoints
    (after removing the mean offset) against the keypoints as labelled [0] and mirrored [1],
    relative to the person's height in pixels."""
    depth = float(np.median(pts[:, 2])) if len(pts) else _depth_from_keypoints(body, b, kp, ok, K)
    centre = _backproject(K, kp[ok, :2].mean(0), np.array(depth))
    X = np.einsum("yij,kj->yki", R, body.keypoints[b])  # (Y, 17, 3)
    X = X - X[:, ok].mean(1, keepdims=True) + centre
    uv = _project(K, X)  # (Y, 17, 2)
    v = body.vertices[b]
    height_px = K[1, 1] * float(v[:, 1].max() - v[:, 1].min()) / max(depth, 0.5)
    out = np.empty((2, len(R)))
    for lab, det in enumerate((kp, mirrored(kp))):
        w = np.where(ok[list(MIRROR)] if lab else ok, det[:, 2] ** 2, 0.0)
        r = uv - det[None, :, :2]
        r = r - (r * w[None, :, None]).sum(1, keepdims=True) / max(w.sum(), 1e-12)
        e2 = (r * r).sum(-1) / height_px**2
        out[lab] = (_gm(e2, s.keypoint_sigma) * w[None]).sum(1) / max(w.sum(), 1e-12)
    return out


def _depth_from_keypoints(body: _Neutral, b: int, kp, ok, K) -> float:
    """Depth (m) at which the neutral body's confident keypoints span as many pixels vertically
    as the detected ones (5 m when they span too few)."""
    model_span = np.ptp(body.keypoints[b][ok, 1]) if ok.sum() >= 2 else 0.0
    px_span = np.ptp(kp[ok, 1]) if ok.sum() >= 2 else 0.0
    if model_span < 0.2 or px_span < 10.0:
        return 5.0
    return float(K[1, 1] * model_span / px_span)


def initial_bodies(
    model,
    costs: FacingCosts,
    heading: np.ndarray,
    keypoints,
    K,
    points_cam,
    counts,
    up_cam,
    settings: InitLidarSettings,
) -> BodyParams:
    """Steps 3-4: the initial bodies (cam frame) of B persons turned to candidate ``heading``
    (B,) int of ``costs``, limbs swung towards ``keypoints`` (B, 17, 3) (the labelling chosen:
    mirror them first for the mirrored one), placed on the points. Other arguments as
    :func:`facing_costs`."""
    s = settings
    kp, B, K, up, pts = _batch_inputs(keypoints, K, up_cam, points_cam, counts)
    ok = kp[..., 2] >= s.keypoint_min_confidence
    heading = np.asarray(heading, np.int64).reshape(B)
    facing = costs.facing_cam[np.arange(B), heading]
    Rg = _frames(up, facing)  # (B, 3, 3)
    body_pose = np.broadcast_to(neutral_pose(), (B, 69)).copy()
    first = _Neutral(model, costs.betas, body_pose, s.score_vertices)
    transl = _placement(first, Rg, costs, pts, kp, ok, K)
    for b in range(B):
        body_pose[b] = _swing_limbs(
            model, first, b, Rg[b], transl[b], body_pose[b], kp[b], ok[b], K, pts[b], s
        )
    body = _Neutral(model, costs.betas, body_pose, s.score_vertices)
    transl = _placement(body, Rg, costs, pts, kp, ok, K)
    go = matrix_to_axis_angle(torch.as_tensor(Rg)).numpy()
    f32 = np.float32
    return BodyParams(
        costs.betas.astype(f32), go.astype(f32), body_pose.astype(f32), transl.astype(f32)
    )


def _placement(body: _Neutral, Rg, costs: FacingCosts, pts, kp, ok, K) -> np.ndarray:
    """SMPL transl (B, 3) putting each rotated body's camera-facing vertices' centroid on its
    points' centroid (without points: its confident keypoints' centroid on theirs, at the depth
    their vertical extent gives)."""
    B = len(Rg)
    out = np.zeros((B, 3))
    for b in range(B):
        R = Rg[b]
        if costs.has_points[b]:
            V = body.sub_vertices[b] @ R.T
            vis = (body.sub_normals[b] @ R.T) @ costs.view_cam[b] < 0.0
            c_model = V[vis].mean(0) if vis.any() else V.mean(0)
            target = pts[b].mean(0)
        else:
            X = body.keypoints[b] @ R.T
            okb = ok[b] if ok[b].sum() >= 2 else np.ones(17, bool)
            c_model = X[okb].mean(0)
            depth = _depth_from_keypoints(body, b, kp[b], ok[b], K)
            uv = kp[b, okb, :2].mean(0) if ok[b].sum() >= 2 else np.array([K[0, 2], K[1, 2]])
            target = _backproject(K, uv, np.array(depth))
        # posed = R (v - J0) + J0 + transl, with v the template-frame vertex (no global rotation)
        j0 = body.root_rest[b]
        out[b] = target - c_model + R @ j0 - j0
    return out


def _swing_limbs(model, body: _Neutral, b, Rg, transl, pose, kp, ok, K, pts, s) -> np.ndarray:
    """Body pose (69,) with the limbs of :data:`_LIMBS` turned towards their keypoints.

    A limb's middle joint (elbow, knee) lies on its keypoint's camera ray at the bone's length
    from the limb's root joint, its end joint (wrist, ankle) on its ray at the lower bone's
    length from the middle: two points each, four ways to place the limb. The two arms, and the
    two legs, are placed together: of the 16 combinations the one that best explains the LiDAR
    points projecting near the limbs in the image (:func:`_pair_cost`), with no knee bent
    forwards and no two limbs through each other. The root joint then turns so that the upper
    bone points at the middle joint, twisted to bend the hinge (elbow, knee) towards the end
    joint, and the hinge bends by the angle between the bones. Keypoints below the confidence
    threshold leave their part of the limb as it is."""
    parents = np.asarray(model.parents)
    rot = _local_rotations(pose)  # (24, 3, 3), root identity
    rot[0] = Rg
    rest = body.rest_joints[b]
    for pair in _PAIRS:
        G = _global_rotations(rot, parents)
        joints = _posed_joints(G, rest, parents) + transl
        options = []
        for li in pair:
            root, mid, end, k_mid, k_end, hinge, _ = _LIMBS[li]
            if not ok[k_mid]:
                options.append([])
                continue
            L1 = float(np.linalg.norm(rest[mid] - rest[root]))
            L2 = float(np.linalg.norm(rest[end] - rest[mid]))
            S = joints[root]
            k_root = _ROOT_KEYPOINT.get(root)
            if k_root is not None and ok[k_root]:  # the shoulder keypoint, at the model's depth
                S = _backproject(K, kp[k_root, :2], np.array(S[2]))
            options.append(
                [
                    (S, E, W)
                    for E in _bone_ends(kp[k_mid, :2], K, S, L1, s.foreshortening)
                    for W in (
                        _bone_ends(kp[k_end, :2], K, E, L2, s.foreshortening)
                        if ok[k_end]
                        else [None]
                    )
                ]
            )
        choice = _choose_pair(options, [_LIMBS[li] for li in pair], joints, Rg, K, pts, s)
        for li, placed in zip(pair, choice):
            if placed is not None:
                _turn_limb(rot, G, rest, parents, _LIMBS[li], *placed)
    return matrix_to_axis_angle(torch.as_tensor(rot[1:])).numpy().reshape(69)


def _turn_limb(rot, G, rest, parents, limb, S, E, W) -> None:
    """Set the local rotations rot (24, 3, 3) of a limb's root and middle joints so that its
    joints go to S (root, unchanged), E (middle) and W (end; None: the lower bone as it is)."""
    root, mid, end, _, _, hinge, sign = limb
    u = (E - S) / max(np.linalg.norm(E - S), 1e-9)
    b_up = rest[mid] - rest[root]
    G_root = _shortest_rotation(G[root] @ (b_up / np.linalg.norm(b_up)), u) @ G[root]
    if W is not None:
        f = (W - E) / max(np.linalg.norm(W - E), 1e-9)
        theta = float(np.arccos(np.clip(u @ f, -1.0, 1.0)))
        # bent by theta about the hinge as the limb is now, the lower bone would point along
        # f_pred; a twist of the upper bone about u by phi brings it onto f. A nearly straight
        # limb does not say which way it bends (no twist); a bend against the joint's sense
        # (phi beyond +-100 deg) is not followed (kept nearly straight).
        axis = G_root @ np.eye(3)[hinge]
        f_pred = _rodrigues(axis * sign * theta) @ u
        phi = _signed_angle(f_pred - (f_pred @ u) * u, f - (f @ u) * u, u)
        if abs(phi) > np.radians(100.0):
            theta = min(theta, 0.1)
        elif theta > 0.1:
            G_root = _rodrigues(u * np.clip(phi, -np.radians(90), np.radians(90))) @ G_root
        # the rest bones are not quite collinear: a last small swing points the lower bone at W
        G_mid = G_root @ _axis_rotation(hinge, sign * theta)
        low = G_mid @ (rest[end] - rest[mid])
        rot[mid] = G_root.T @ _shortest_rotation(low / np.linalg.norm(low), f) @ G_mid
    rot[root] = G[parents[root]].T @ G_root


def _choose_pair(options, limbs, joints, Rg, K, pts, s: InitLidarSettings):
    """One placement (S, E, W) or None per limb of a pair, from each limb's options (lists of
    placements; empty: leave the limb), minimising :func:`_pair_cost`."""
    a = options[0] or [None]
    b = options[1] or [None]
    best, best_cost = (None, None), np.inf
    for pa in a:
        for pb in b:
            c = _pair_cost((pa, pb), limbs, joints, Rg, K, pts, s)
            if c < best_cost:
                best, best_cost = (pa, pb), c
    return best


def _pair_cost(placed, limbs, joints, Rg, K, pts, s: InitLidarSettings) -> float:
    """How badly two placed limbs explain the LiDAR points that project near them in the image.

    Per point, along its camera ray, against each limb whose bones (capsules of radius
    limb_radius_m) it passes within 4 cm of: 0 if the point lies on the limb's near surface
    (within 5 cm), 0.3 if in front of it (the limb hidden behind something), 1 if behind it (the
    limb would have blocked the ray); the cheapest limb counts, 0.3 if none. Mean over the points,
    plus 1 for a knee bent forwards and 1 for two limbs closer than two radii. Without points:
    the distance of the placed joints to the current ones (m)."""
    r = s.limb_radius_m
    segs = []
    cost = 0.0
    for p, limb in zip(placed, limbs):
        if p is None:
            segs.append([])
            continue
        S, E, W = p
        segs.append([(S, E)] + ([] if W is None else [(E, W)]))
        root, mid, end, _, _, hinge, _ = limb
        if hinge == 0 and W is not None:  # knees bend backwards: (upper x lower) along left
            n = np.cross(E - S, W - E)
            if n @ Rg[:, 0] < -0.02 * np.linalg.norm(E - S) * np.linalg.norm(W - E):
                cost += 1.0
    if segs[0] and segs[1]:
        gap = min(_segments_gap(x, y) for x in segs[0] for y in segs[1])
        cost += 1.0 if gap < 2 * r else 0.0
    if len(pts) == 0:
        for p, limb in zip(placed, limbs):
            if p is not None:
                cost += np.linalg.norm(p[1] - joints[limb[1]])
                cost += 0.0 if p[2] is None else np.linalg.norm(p[2] - joints[limb[2]])
        return cost
    near = np.zeros(len(pts), bool)
    uvp = _project(K, pts)
    for limb_segs in segs:
        for x, y in limb_segs:
            depth = max(0.5, float(min(x[2], y[2])))
            near |= _segment_distance(uvp, _project(K, x), _project(K, y)) < 0.1 * K[0, 0] / depth
    if not near.any():
        return cost
    P = pts[near]
    dist = np.linalg.norm(P, axis=1)
    ray = P / dist[:, None]
    per_point = np.full(len(P), 0.3)
    for limb_segs in segs:
        for x, y in limb_segs:
            # the bone's closest sample to each point's ray: how far off the ray, and how far
            # along it (the point's depth minus the bone's)
            q = x[None] + np.linspace(0.0, 1.0, 9)[:, None] * (y - x)[None]  # (9, 3)
            along = ray @ q.T  # (N, 9)
            off = np.linalg.norm(q[None] - along[..., None] * ray[:, None], axis=-1)
            k = np.argmin(off, axis=1)
            i = np.arange(len(P))
            on = off[i, k] < r + 0.04
            delta = dist - along[i, k]  # > 0: the point is behind the bone's axis
            c = np.where(np.abs(delta + r) < 0.05, 0.0, np.where(delta < -r, 0.3, 1.0))
            per_point = np.where(on, np.minimum(per_point, c), per_point)
    return cost + float(per_point.mean())


def _segments_gap(s1, s2) -> float:
    """Smallest distance (m) between two 3D segments (sampled)."""
    t = np.linspace(0.0, 1.0, 9)[:, None]
    a = s1[0][None] + t * (s1[1] - s1[0])[None]
    b = s2[0][None] + t * (s2[1] - s2[0])[None]
    return float(np.linalg.norm(a[:, None] - b[None], axis=-1).min())


def _posed_joints(G: np.ndarray, rest: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """Joints (24, 3) of global rotations G (24, 3, 3) and rest joints (24, 3), the root joint
    rotating about itself as in SMPL (R_0 (J - J_0) + J_0), without the translation."""
    out = np.empty_like(rest)
    out[0] = rest[0]
    for j in range(1, len(rest)):
        out[j] = out[parents[j]] + G[parents[j]] @ (rest[j] - rest[parents[j]])
    return out


def _bone_ends(uv, K, start, length, foreshortening: float) -> list[np.ndarray]:
    """Where a bone of ``length`` (m) from ``start`` (3,) (cam frame) may end for its end's
    keypoint at pixel uv (2,): the keypoint lifted to start's depth gives the bone's extent v
    across the view; |v| >= foreshortening x length: one end, in that plane at ``length``
    (a bone nearly across the view: its depth is ill-conditioned, a few pixels of keypoint noise
    would swing it); shorter: two ends, v plus +-sqrt(length^2 - |v|^2) along the view ray."""
    v = _backproject(K, np.asarray(uv, np.float64), np.array(start[2])) - start
    n = float(np.linalg.norm(v))
    if n >= foreshortening * length:
        return [start + v * (length / max(n, 1e-9))]
    ray = start / np.linalg.norm(start)
    dz = np.sqrt(length * length - n * n)
    return [start + v - dz * ray, start + v + dz * ray]


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances (N,) of points p (N, D) to the segment from a to b (D,)."""
    ab = b - a
    t = np.clip((p - a) @ ab / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1)


def _axis_rotation(axis: int, angle: float) -> np.ndarray:
    """Rotation (3, 3) by angle (rad) about coordinate axis 0 (x), 1 (y) or 2 (z)."""
    c, s_ = np.cos(angle), np.sin(angle)
    i, j = [k for k in range(3) if k != axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s_, s_, c
    if axis == 1:  # the y rotation is (z, x)-handed
        R[i, j], R[j, i] = s_, -s_
    return R


def _rodrigues(r: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) of the axis-angle vector r (3,)."""
    t = float(np.linalg.norm(r))
    if t < 1e-12:
        return np.eye(3)
    k = r / t
    Kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(t) * Kx + (1.0 - np.cos(t)) * (Kx @ Kx)


def _signed_angle(a: np.ndarray, b: np.ndarray, axis: np.ndarray) -> float:
    """The angle (rad) turning a onto b about axis (a, b normal to it); 0 if either vanishes."""
    if np.linalg.norm(a) < 1e-6 or np.linalg.norm(b) < 1e-6:
        return 0.0
    return float(np.arctan2(np.cross(a, b) @ axis, a @ b))


def _local_rotations(body_pose: np.ndarray) -> np.ndarray:
    aa = np.concatenate([np.zeros(3), np.asarray(body_pose, np.float64)]).reshape(24, 3)
    from tasks.body.rotations import axis_angle_to_matrix

    return axis_angle_to_matrix(torch.as_tensor(aa)).numpy()


def _global_rotations(rot: np.ndarray, parents: np.ndarray) -> np.ndarray:
    G = np.empty_like(rot)
    G[0] = rot[0]
    for j in range(1, len(rot)):
        G[j] = G[parents[j]] @ rot[j]
    return G


def _shortest_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The rotation (3, 3) turning unit vector a onto unit vector b about their common normal."""
    v = np.cross(a, b)
    c = float(a @ b)
    if c < -1.0 + 1e-9:  # opposite: half a turn about any axis normal to a
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    Vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + Vx + Vx @ Vx / (1.0 + c)


def lidar_keypoint_init(
    model,
    keypoints,
    K,
    points_cam,
    counts,
    up_cam,
    settings: InitLidarSettings,
) -> BodyParams:
    """The weight-free initial bodies (cam frame) of B persons, keypoints as labelled (arguments
    as :func:`facing_costs`)."""
    costs = facing_costs(model, keypoints, K, points_cam, counts, up_cam, settings)
    return initial_bodies(
        model, costs, costs.best(), keypoints, K, points_cam, counts, up_cam, settings
    )
