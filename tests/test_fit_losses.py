"""Loss terms, visibility filter, ICP and metrics of the fitting stage on analytic cases."""

from __future__ import annotations

import math

import numpy as np
import open3d as o3d
import pytest
import torch

from tasks.fit import losses as L
from tasks.fit.icp import icp_align, rigid_update_params
from tasks.fit.metrics import fit_metrics, mpere, pa_mpjpe_mm, umeyama_align
from tasks.fit.visibility import front_facing_faces, visibility_masks


def _rot(axis, deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = math.radians(deg)
    return np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * K @ K


def test_geman_mcclure_values():
    x = torch.tensor([0.0, 100.0, 1e6])
    g = L.geman_mcclure(x, 100.0)
    assert g[0] == 0.0
    assert g[1].item() == pytest.approx(5000.0)  # rho^2 / 2 at x = rho
    assert g[2].item() == pytest.approx(1e4, rel=1e-6)  # saturates at rho^2


def test_reprojection_zero_at_exact_projection_and_confidence_power():
    K = torch.tensor([[1000.0, 0, 640], [0, 1000.0, 360], [0, 0, 1]])
    X = torch.tensor([[[0.1, -0.2, 4.0], [0.3, 0.5, 6.0]]])
    uv = L.project_points(X, K)
    assert uv[0, 0].tolist() == pytest.approx([665.0, 310.0])
    kp = torch.cat([uv, torch.tensor([[[0.5], [1.0]]])], -1)
    assert L.reprojection_loss(X, kp, K).item() == pytest.approx(0.0, abs=1e-6)
    kp2 = kp.clone()
    kp2[0, 0, 0] += 10.0  # 10 px error on a keypoint with confidence 0.5
    expect = 0.5**2 * (1e4 * 100 / (1e4 + 100))
    assert L.reprojection_loss(X, kp2, K, conf_power=2.0).item() == pytest.approx(expect, rel=1e-5)
    assert L.reprojection_loss(X, kp2, K, conf_power=1.0).item() == pytest.approx(2 * expect, rel=1e-5)


def test_chamfer_known_value_masks_and_minimum():
    v = torch.tensor([[[0.0, 0, 0], [1.0, 0, 0], [9.0, 9, 9]]])
    vm = torch.tensor([[True, True, False]])
    p = torch.tensor([[[0.0, 0, 0.1], [1.0, 0, 0.1], [0.5, 0, 0.1], [5.0, 5, 5]]])
    pm = torch.tensor([[True, True, True, False]])
    # v->p: 0.01, 0.01 -> mean 0.01; p->v: 0.01, 0.01, 0.25 + 0.01 -> mean 0.28/3
    assert L.chamfer_loss(v, vm, p, pm).item() == pytest.approx(0.01 + 0.28 / 3, rel=1e-5)
    same = L.chamfer_loss(v, vm, v.clone(), vm)
    assert same.item() == 0.0


def test_chamfer_vertex_cap_only_limits_the_vertex_to_point_direction():
    # vertex 2 (an unobserved vertex, 1 m from every return) is capped at 0.2 m; the point at
    # (0.5, 0, 0.1) is 0.5 m from every vertex and is never capped (every return lies on the body)
    v = torch.tensor([[[0.0, 0, 0], [1.0, 0, 0], [0.0, 1, 0.1]]], requires_grad=True)
    vm = torch.ones(1, 3, dtype=torch.bool)
    p = torch.tensor([[[0.0, 0, 0.1], [1.0, 0, 0.1], [0.5, 0, 0.1]]])
    pm = torch.ones(1, 3, dtype=torch.bool)
    capped = L.chamfer_loss(v, vm, p, pm, vertex_max_m=0.2)
    # v->p: (0.01 + 0.01 + 0.2^2) / 3; p->v: (0.01 + 0.01 + 0.25 + 0.01) / 3
    assert capped.item() == pytest.approx((0.02 + 0.04) / 3 + 0.28 / 3, rel=1e-5)
    assert L.chamfer_loss(v, vm, p, pm).item() == pytest.approx((0.02 + 1.0) / 3 + 0.28 / 3, rel=1e-5)
    capped.sum().backward()
    assert v.grad[0, 2].abs().max() == 0.0 and v.grad[0, 0].abs().max() > 0.0


def test_chamfer_gradient_finite_at_zero_distance_and_empty_sets():
    v = torch.tensor([[[0.0, 0, 0], [1.0, 0, 0]]], requires_grad=True)
    p = torch.tensor([[[0.0, 0, 0], [1.0, 0, 0]]])
    m = torch.ones(1, 2, dtype=torch.bool)
    loss = L.chamfer_loss(v, m, p, m)
    loss.sum().backward()
    assert torch.isfinite(v.grad).all() and v.grad.abs().max() == 0.0
    v.grad = None
    loss = L.chamfer_loss(v, m, p, torch.zeros(1, 2, dtype=torch.bool))
    loss.sum().backward()
    assert loss.item() == 0.0 and torch.isfinite(v.grad).all()


def test_chamfer_translation_gradient_points_to_minimum():
    torch.manual_seed(0)
    p = torch.randn(2, 50, 3) * 0.3 + torch.tensor([0.0, 0.0, 40.0])  # far away: centroid shift
    shift = torch.zeros(2, 1, 3, requires_grad=True)
    m = torch.ones(2, 50, dtype=torch.bool)
    opt = torch.optim.Adam([shift], lr=0.01)
    offset = torch.tensor([[[0.05, -0.03, 0.1]]])
    for _ in range(200):
        opt.zero_grad()
        L.chamfer_loss(p + offset + shift, m, p, m).sum().backward()
        opt.step()
    assert torch.allclose(shift, -offset.expand(2, 1, 3), atol=2e-3)


def test_hyperextension_shape_occlusion_terms():
    pose = torch.zeros(2, 69)
    assert L.hyperextension_loss(pose).tolist() == [4.0, 4.0]
    pose[1, 52] = 1.0  # left elbow bent the wrong way -> exp(+1)
    pose[1, 9] = 1.0  # left knee bent forward (natural) -> exp(-1)
    assert L.hyperextension_loss(pose)[1].item() == pytest.approx(2 + math.e + math.exp(-1))
    assert L.shape_loss(torch.tensor([[3.0, 4.0] + [0] * 8])).item() == 25.0
    R0 = torch.eye(3).expand(1, 24, 3, 3).clone()
    R = R0.clone()
    R[0, 5] = torch.tensor(_rot([0, 0, 1], 90.0), dtype=torch.float32)
    occ = torch.zeros(1, 24, dtype=torch.bool)
    assert L.occlusion_pose_loss(R, R0, occ).item() == 0.0
    occ[0, 5] = True
    # 1 - <q0, q>^2 = 1 - cos^2(45 deg) = 0.5
    assert L.occlusion_pose_loss(R, R0, occ).item() == pytest.approx(0.5, abs=1e-6)


def test_weights_presets_and_squaring():
    w = L.FIT_PRESETS["humanm3"]
    assert (w.lambda_3d, w.lambda_occ, w.w, w.j_conf) == (600.0, 135.0, -1.0, 0.6)
    assert w.scale("3d") == 600.0**2  # squared by default
    assert w.with_(square_lambdas=False).scale("beta") == 17.5


def _sphere(radius=1.0, center=(0.0, 0.0, 5.0)):
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=40)
    v = torch.tensor(np.asarray(mesh.vertices) + np.asarray(center), dtype=torch.float64)
    f = torch.tensor(np.asarray(mesh.triangles), dtype=torch.long)
    return v[None], f


def test_backface_on_sphere_matches_analytic_cap():
    v, f = _sphere()
    front = front_facing_faces(v, f, w=0.0)[0]
    c = v[0][f].mean(1)
    # a sphere face is visible from o iff (c - centre) . (o - c) > 0: the cap nearer than the
    # tangent circle; with radius 1 at distance 5, z_c < 5 - 1/5
    expected = c[:, 2] < 5.0 - 0.2
    agree = (front == expected).float().mean().item()
    assert agree > 0.98
    assert front[c[:, 2].argmin()] and not front[c[:, 2].argmax()]
    assert front_facing_faces(v, f, w=-1.0).all()
    assert front_facing_faces(v, f, w=0.5)[0].sum() < front.sum()


def test_visibility_part_filter():
    v, f = _sphere()
    V = v.shape[1]
    parts = torch.zeros(V, dtype=torch.long)
    parts[v[0, :, 0] > 0] = 18  # right half of the sphere is the "left forearm"
    conf = torch.ones(1, 17)
    vis = visibility_masks(v, f, parts, conf, w=0.0, j_conf=0.6)
    assert not vis.occluded_joints.any()
    conf[0, [7, 9]] = 0.3  # left elbow and wrist unseen -> part 18 occluded (also 20, 22)
    vis2 = visibility_masks(v, f, parts, conf, w=0.0, j_conf=0.6)
    assert vis2.occluded_joints[0].nonzero().flatten().tolist() == [18, 20, 22]
    assert not (vis2.vertex_mask[0] & (parts == 18)).any()
    assert torch.equal(vis2.vertex_mask[0] & (parts == 0), vis.vertex_mask[0] & (parts == 0))


def test_icp_recovers_rigid_motion_and_param_update():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(800, 3)) * np.array([0.2, 0.5, 0.1]) + np.array([0.3, 0.2, 6.0])
    R = _rot([0.2, 1.0, 0.1], 12.0)
    c = pts.mean(0)
    t = np.array([0.05, -0.04, 0.35])
    moved_back = (pts - c) @ R + c - t  # the "estimate" is the inverse motion of the points
    res = icp_align(moved_back, pts)
    assert res.used_icp
    aligned = moved_back @ res.T[:3, :3].T + res.T[:3, 3]
    assert np.abs(aligned - pts).max() < 1e-4
    # parameter update about the root joint J0 reproduces moving the mesh
    Rg = _rot([1, 0, 0], 180.0)
    transl = np.array([0.1, 0.2, 3.0])
    j0 = np.array([0.0, -0.2, 0.02])
    x_rest = np.array([0.3, 0.4, 0.1])  # a rest-pose point
    x = Rg @ (x_rest - j0) + j0 + transl
    R2, t2 = rigid_update_params(Rg, transl, j0, res.T[:3, :3], res.T[:3, 3])
    x2 = R2 @ (x_rest - j0) + j0 + t2
    assert np.allclose(x2, res.T[:3, :3] @ x + res.T[:3, 3])


def test_icp_too_few_points_is_identity():
    res = icp_align(np.zeros((5, 3)), np.zeros((3, 3)))
    assert not res.used_icp and np.array_equal(res.T, np.eye(4))


def test_metrics_analytic():
    rng = np.random.default_rng(1)
    gt = rng.normal(size=(2, 24, 3))
    R = _rot([0, 1, 0], 30.0)
    pred = 1.3 * gt @ R.T + np.array([1.0, 2.0, 3.0])
    assert np.allclose(umeyama_align(pred, gt), gt, atol=1e-10)
    assert np.allclose(pa_mpjpe_mm(pred, gt), 0.0, atol=1e-7)
    faces = np.array([[0, 1, 2], [1, 2, 3]])
    verts = rng.normal(size=(1, 4, 3))
    assert mpere(verts * 1.1, verts, faces)[0] == pytest.approx(0.1)
    s = np.array([0, 0, 0.01])
    m = fit_metrics(gt + s, gt + s, gt, gt, faces)
    assert m["mpjpe"] == pytest.approx([10.0, 10.0]) and m["mpjpe_root"] == pytest.approx([0, 0], abs=1e-9)


def test_nearest_kdtree_matches_brute_force():
    g = torch.Generator().manual_seed(3)
    a, b = torch.rand(3, 40, 3, generator=g), torch.rand(3, 25, 3, generator=g)
    am, bm = torch.rand(3, 40, generator=g) > 0.3, torch.rand(3, 25, generator=g) > 0.3
    k = L.nearest_indices(a, am, b, bm, method="kdtree")
    f = L.nearest_indices(a, am, b, bm, method="brute")
    assert torch.equal(k[0][am], f[0][am]) and torch.equal(k[1][bm], f[1][bm])
