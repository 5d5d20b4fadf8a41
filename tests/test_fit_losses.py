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
from tasks.fit.weights import FIT_PRESETS


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
    assert L.reprojection_loss(X, kp, K, 100.0, 2.0).item() == pytest.approx(0.0, abs=1e-6)
    kp2 = kp.clone()
    kp2[0, 0, 0] += 10.0  # 10 px error on a keypoint with confidence 0.5
    expect = 0.5**2 * (1e4 * 100 / (1e4 + 100))
    assert L.reprojection_loss(X, kp2, K, 100.0, conf_power=2.0).item() == pytest.approx(
        expect, rel=1e-5
    )
    assert L.reprojection_loss(X, kp2, K, 100.0, conf_power=1.0).item() == pytest.approx(
        2 * expect, rel=1e-5
    )


def _chamfer(v, vm, p, pm, cap=None, method="auto"):
    """L_3D of padded sets (the kernel takes ragged points), pairs found now."""
    t = L.chamfer_targets(v.detach(), vm, p[pm], pm.nonzero()[:, 0], method=method)
    return L.chamfer_loss(v, t, vertex_max_m=cap)


def test_chamfer_known_value_masks_and_minimum():
    v = torch.tensor([[[0.0, 0, 0], [1.0, 0, 0], [9.0, 9, 9]]])
    vm = torch.tensor([[True, True, False]])
    p = torch.tensor([[[0.0, 0, 0.1], [1.0, 0, 0.1], [0.5, 0, 0.1], [5.0, 5, 5]]])
    pm = torch.tensor([[True, True, True, False]])
    # v->p: 0.01, 0.01 -> mean 0.01; p->v: 0.01, 0.01, 0.25 + 0.01 -> mean 0.28/3
    for method in ("grid", "brute"):
        assert _chamfer(v, vm, p, pm, method=method).item() == pytest.approx(
            0.01 + 0.28 / 3, rel=1e-5
        )
    same = _chamfer(v, vm, v.clone(), vm)
    assert same.item() == 0.0


def test_chamfer_vertex_cap_only_limits_the_vertex_to_point_direction():
    # vertex 2 (an unobserved vertex, 1 m from every return) is capped at 0.2 m; the point at
    # (0.5, 0, 0.1) is 0.5 m from every vertex and is never capped (every return lies on the body)
    v = torch.tensor([[[0.0, 0, 0], [1.0, 0, 0], [0.0, 1, 0.1]]], requires_grad=True)
    vm = torch.ones(1, 3, dtype=torch.bool)
    p = torch.tensor([[[0.0, 0, 0.1], [1.0, 0, 0.1], [0.5, 0, 0.1]]])
    pm = torch.ones(1, 3, dtype=torch.bool)
    capped = _chamfer(v, vm, p, pm, cap=0.2)
    # v->p: (0.01 + 0.01 + 0.2^2) / 3; p->v: (0.01 + 0.01 + 0.25 + 0.01) / 3
    assert capped.item() == pytest.approx((0.02 + 0.04) / 3 + 0.28 / 3, rel=1e-5)
    assert _chamfer(v, vm, p, pm).item() == pytest.approx((0.02 + 1.0) / 3 + 0.28 / 3, rel=1e-5)
    capped.sum().backward()
    assert v.grad[0, 2].abs().max() == 0.0 and v.grad[0, 0].abs().max() > 0.0


def test_chamfer_gradient_finite_at_zero_distance_and_empty_sets():
    v = torch.tensor([[[0.0, 0, 0], [1.0, 0, 0]]], requires_grad=True)
    p = torch.tensor([[[0.0, 0, 0], [1.0, 0, 0]]])
    m = torch.ones(1, 2, dtype=torch.bool)
    loss = _chamfer(v, m, p, m)
    loss.sum().backward()
    assert torch.isfinite(v.grad).all() and v.grad.abs().max() == 0.0
    v.grad = None
    loss = _chamfer(v, m, p, torch.zeros(1, 2, dtype=torch.bool))
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
        _chamfer(p + offset + shift, m, p, m).sum().backward()
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
    w = FIT_PRESETS["humanm3"]
    assert (w.lambda_3d, w.lambda_occ, w.w, w.j_conf) == (600.0, 135.0, -1.0, 0.6)
    assert w.factor(w.lambda_3d) == 600.0**2  # squared by default
    assert w.with_(square_lambdas=False).factor(w.lambda_beta) == 17.5


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


def _icp(vertices, points, **kw):
    """Batched ICP of one person per (vertices (N, 3), points (M, 3)) pair."""
    B = len(vertices)
    n = max(len(v) for v in vertices)
    V = torch.zeros(B, n, 3, dtype=torch.float64)
    vm = torch.zeros(B, n, dtype=torch.bool)
    for b, v in enumerate(vertices):
        V[b, : len(v)] = torch.as_tensor(v)
        vm[b, : len(v)] = True
    P = torch.as_tensor(np.concatenate(points))
    person = torch.repeat_interleave(torch.arange(B), torch.tensor([len(p) for p in points]))
    return icp_align(V, vm, P, person, **kw)


def test_icp_recovers_rigid_motion_and_param_update():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(800, 3)) * np.array([0.2, 0.5, 0.1]) + np.array([0.3, 0.2, 6.0])
    R = _rot([0.2, 1.0, 0.1], 12.0)
    c = pts.mean(0)
    t = np.array([0.05, -0.04, 0.35])
    moved_back = (pts - c) @ R + c - t  # the "estimate" is the inverse motion of the points
    # second person: too few points -> identity, not aligned; third: the first one again
    res = _icp([moved_back, moved_back, moved_back], [pts, pts[:5], pts], relative_change=1e-9)
    assert res.used_icp.tolist() == [True, False, True]
    assert np.array_equal(res.T[1], np.eye(4)) and res.fitness[1] == 0.0
    assert np.array_equal(res.T[0], res.T[2])  # persons do not interact
    aligned = moved_back @ res.T[0, :3, :3].T + res.T[0, :3, 3]
    assert np.abs(aligned - pts).max() < 1e-4
    # parameter update about the root joint J0 reproduces moving the mesh
    Rg = _rot([1, 0, 0], 180.0)
    transl = np.array([0.1, 0.2, 3.0])
    j0 = np.array([0.0, -0.2, 0.02])
    x_rest = np.array([0.3, 0.4, 0.1])  # a rest-pose point
    x = Rg @ (x_rest - j0) + j0 + transl
    R2, t2 = rigid_update_params(Rg, transl, j0, res.T[0, :3, :3], res.T[0, :3, 3])
    x2 = R2 @ (x_rest - j0) + j0 + t2
    assert np.allclose(x2, res.T[0, :3, :3] @ x + res.T[0, :3, 3])


def test_icp_matches_open3d_registration():
    # the batched ICP is Open3D's point-to-point registration_icp (coarse to fine radii, same
    # stopping rule): partial, noisy, offset views of a body-sized ellipsoid
    rng = np.random.default_rng(5)
    verts, pts = [], []
    for k in range(3):
        u = rng.normal(size=(3000, 3))
        surf = u / np.linalg.norm(u, axis=1, keepdims=True) * np.array([0.25, 0.8, 0.15])
        front = surf[surf[:, 2] < 0.05]
        p = (
            front[rng.choice(len(front), 400, replace=False)]
            + rng.normal(0, 0.01, (400, 3))
            + [0.0, 0.0, 5.0 + k]
        )
        v = (front[:1200] @ _rot([0, 1, 0], 8.0 * (k + 1)).T) + [0.03 * k, 0.02, 5.2 + k]
        verts.append(v)
        pts.append(p)
    res = _icp(verts, pts, relative_change=1e-6)
    for k in range(3):
        T = np.eye(4)
        T[:3, 3] = pts[k].mean(0) - verts[k].mean(0)
        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(verts[k]))
        dst = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[k]))
        for radius in (0.3, 0.1):
            reg = o3d.pipelines.registration.registration_icp(
                src,
                dst,
                radius,
                T,
                o3d.pipelines.registration.TransformationEstimationPointToPoint(),
                o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=30),
            )
            if reg.fitness > 0:
                T = np.asarray(reg.transformation)
        assert res.used_icp[k]
        assert np.abs(res.T[k] - T).max() < 1e-6, (k, res.T[k] - T)
        assert res.fitness[k] == pytest.approx(reg.fitness, abs=1e-9)


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
    assert m["mpjpe"] == pytest.approx([10.0, 10.0]) and m["mpjpe_root"] == pytest.approx(
        [0, 0], abs=1e-9
    )


def test_chamfer_targets_grid_matches_brute_force_and_sums():
    # exact nearest pairs both ways: the CPU grid search (numba) and the distance-matrix path
    # agree; the per-vertex sums reproduce the point -> vertex sum over nearest pairs
    g = torch.Generator().manual_seed(3)
    K, N = 3, 60
    v = torch.rand(K, N, 3, generator=g, dtype=torch.float64) * torch.tensor([0.5, 1.8, 0.3]) + 4.0
    vm = torch.rand(K, N, generator=g) > 0.3
    vm[2] = False  # no vertex: takes no part
    counts = torch.tensor([40, 25, 10])
    p = (
        torch.rand(int(counts.sum()), 3, generator=g, dtype=torch.float64)
        * torch.tensor([0.6, 2.0, 0.4])
        + 4.0
    )
    p[:3] += 3.0  # far outliers: every shell empty, the full scan finds them
    person = torch.repeat_interleave(torch.arange(K), counts)
    a = L.chamfer_targets(v, vm, p, person, method="grid")
    b = L.chamfer_targets(v, vm, p, person, method="brute")
    for x, y in zip(
        (a.vertex_target, a.point_count, a.point_mean, a.point_rest),
        (b.vertex_target, b.point_count, b.point_mean, b.point_rest),
    ):
        assert torch.allclose(x, y, atol=1e-9)
    d = torch.cdist(p[:40], v[0][vm[0]])
    near = v[0][vm[0]][d.argmin(1)]
    expect = ((p[:40] - near) ** 2).sum()
    vk = v[0]
    got = (a.point_count[0] * ((vk - a.point_mean[0]) ** 2).sum(-1)).sum() + a.point_rest[0]
    assert got.item() == pytest.approx(expect.item(), rel=1e-9)
    assert a.point_count[2].sum() == 0 and a.point_rest[2] == 0 and not a.vertex_mask[2].any()


def test_grid_nearest_is_exact_on_wide_and_degenerate_sets():
    from tasks.fit.nearest import nearest_indices

    rng = np.random.default_rng(4)
    for data in (
        rng.normal(size=(500, 3)) * [5.0, 0.1, 0.1],  # wide: cells grow
        np.zeros((7, 3)),  # one cell, all tied: lowest index
        rng.normal(size=(1, 3)),
    ):
        q = rng.normal(size=(300, 3)) * 3.0
        d = ((q[:, None] - data[None]) ** 2).sum(-1)
        assert np.array_equal(nearest_indices(q, data), d.argmin(1))
