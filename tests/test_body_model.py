"""Body model kernels: LBS, the procedural SMPL-format model, rotations, poses, GMM prior."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tasks.body.model import BodyModel, rigid_transform_params
from tasks.body.poses import arm_swing_pose, gait_pose, sample_plausible_poses, standing_pose
from tasks.body.prior import GMMPosePrior, fit_pose_prior, generate_pose_prior
from tasks.body.procedural import default_body_model, default_body_params, generate_body_model
from tasks.body.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from tasks.conventions import SMPL_PARENTS


@pytest.fixture(scope="module")
def params():
    return default_body_params()


@pytest.fixture(scope="module")
def model64(params):
    return BodyModel(params).to(torch.float64)


def _edges(faces):
    return np.concatenate((faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]))


# ---------------------------------------------------------------- rotations


def test_axis_angle_round_trip_and_orthonormal():
    g = torch.Generator().manual_seed(0)
    axis = torch.nn.functional.normalize(
        torch.randn(500, 3, generator=g, dtype=torch.float64), dim=1
    )
    angle = torch.rand(500, 1, generator=g, dtype=torch.float64) * (math.pi - 1e-3)
    aa = axis * angle
    aa[:5] = torch.tensor(
        [[0.0, 0, 0], [1e-9, 0, 0], [0, 1e-5, 0], [0, 0, 3e-4], [1e-3, -2e-3, 5e-4]]
    )
    R = axis_angle_to_matrix(aa)
    eye = torch.eye(3, dtype=torch.float64)
    assert torch.allclose(R @ R.transpose(-1, -2), eye.expand_as(R), atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(500, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(matrix_to_axis_angle(R), aa, atol=1e-9)


def test_rotation_about_z_by_quarter_turn_is_exact():
    R = axis_angle_to_matrix(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64))
    expected = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=torch.float64)
    assert torch.allclose(R, expected, atol=1e-15)
    # Near pi the axis is recovered up to sign only; the rotation itself must round-trip.
    Rpi = axis_angle_to_matrix(torch.tensor([0.0, math.pi - 1e-7, 0.0], dtype=torch.float64))
    assert torch.allclose(axis_angle_to_matrix(matrix_to_axis_angle(Rpi)), Rpi, atol=1e-7)


def test_rotation_gradients_finite_at_zero():
    aa = torch.zeros(4, 3, dtype=torch.float64, requires_grad=True)
    axis_angle_to_matrix(aa).sum().backward()
    assert torch.isfinite(aa.grad).all()
    # d R / d aa at zero is the skew generator: R ~ I + [aa]_x
    aa2 = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    axis_angle_to_matrix(aa2)[2, 1].backward()  # R[2,1] = +aa_x
    assert torch.allclose(aa2.grad, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    R = axis_angle_to_matrix(torch.zeros(2, 3, dtype=torch.float64)).requires_grad_(True)
    matrix_to_axis_angle(R).sum().backward()
    assert torch.isfinite(R.grad).all()


# ---------------------------------------------------------------- procedural model


def test_generated_model_format(params):
    V = params["v_template"].shape[0]
    assert 6000 <= V <= 7000
    assert params["f"].dtype == np.int64 and params["f"].shape[1] == 3
    assert params["shapedirs"].shape == (V, 3, 10)
    assert params["posedirs"].shape == (V, 3, 207)
    assert np.abs(params["posedirs"]).max() > 1e-3
    assert params["weights"].shape == (V, 24)
    assert params["J_regressor"].shape == (24, V)
    kt = params["kintree_table"]
    assert kt.shape == (2, 24) and kt[0, 0] == 2**32 - 1
    assert [int(p) for p in kt[0, 1:]] == list(SMPL_PARENTS[1:])
    v = params["v_template"]
    height = v[:, 1].max() - v[:, 1].min()
    assert 1.6 < height < 1.85
    assert abs(params["J_rest"][0, 1] + 0.225) < 1e-9  # pelvis near the origin, as SMPL


def test_generation_is_deterministic(params):
    again = generate_body_model(0)
    for k in params:
        np.testing.assert_array_equal(params[k], again[k])


def test_surface_closed_and_outward(params):
    v, f = params["v_template"], params["f"]
    e = np.sort(_edges(f), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    assert np.all(counts == 2), "every edge must be shared by exactly two faces"
    _, dcounts = np.unique(_edges(f), axis=0, return_counts=True)
    assert np.all(dcounts == 1), "consistent orientation: each directed edge appears once"
    signed_vol = np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0
    assert 0.04 < signed_vol < 0.09  # m^3, SMPL's neutral body is ~0.066
    assert len(v) - len(e) // 2 + len(f) == 2  # one closed genus-0 surface
    # Normals point away from the nearest skeleton bone for most faces.
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    c = v[f].mean(1)
    out = (n * (c - c.mean(0))).sum(1) > 0
    assert out.mean() > 0.75
    W = params["weights"]
    J = params["J_rest"]
    part = W[f[:, 0]].argmax(1)
    local = (n * (c - J[part])).sum(1) > 0
    assert local.mean() > 0.95


def test_skinning_weights_and_regressor(params):
    W = params["weights"]
    assert W.min() >= 0
    np.testing.assert_allclose(W.sum(1), 1.0, atol=1e-12)
    R = params["J_regressor"]
    assert R.min() >= 0
    np.testing.assert_allclose(R.sum(1), 1.0, atol=1e-12)
    np.testing.assert_allclose(R @ params["v_template"], params["J_rest"], atol=1e-3)
    # Parts follow the joints: hand vertices are skinned to the hand / wrist joints.
    v = params["v_template"]
    tip = v[:, 0].argmax()
    assert W[tip, [20, 22]].sum() > 0.9
    assert len(params["coco_vertex_ids"]) == 5
    assert v[params["coco_vertex_ids"], 1].min() > 0.38  # on the head


# ---------------------------------------------------------------- LBS


def test_zero_pose_reproduces_template_plus_shape(params, model64):
    B = 2
    betas = torch.tensor(
        [[0.0] * 10, [1.0, -0.5, 0.3, 0, 0.2, 0, 0, 0, 0, 0.7]], dtype=torch.float64
    )
    zero = torch.zeros(B, 3, dtype=torch.float64)
    out = model64(betas, zero, torch.zeros(B, 69, dtype=torch.float64), zero)
    expected = params["v_template"][None] + np.einsum(
        "bl,vcl->bvc", betas.numpy(), params["shapedirs"]
    )
    np.testing.assert_allclose(out.vertices.numpy(), expected, atol=1e-9)
    J = np.einsum("jv,bvc->bjc", params["J_regressor"], expected)
    np.testing.assert_allclose(out.joints.numpy(), J, atol=1e-9)
    # The first beta (height) makes the body taller.
    h = out.vertices[:, :, 1].amax(1) - out.vertices[:, :, 1].amin(1)
    assert h[1] > h[0] * 1.04


def test_joints_follow_regressor_in_pose(params, model64):
    rng = np.random.default_rng(1)
    pose = torch.tensor(sample_plausible_poses(3, rng), dtype=torch.float64)
    z = torch.zeros(3, 3, dtype=torch.float64)
    betas = torch.tensor(rng.normal(size=(3, 10)), dtype=torch.float64)
    out = model64(betas, z, pose, z)
    rest = model64.rest_joints(betas)
    # Bone lengths are preserved by the kinematic chain.
    for j in range(1, 24):
        p = SMPL_PARENTS[j]
        torch.testing.assert_close(
            (out.joints[:, j] - out.joints[:, p]).norm(dim=1), (rest[:, j] - rest[:, p]).norm(dim=1)
        )
    # A single rotated elbow moves only the forearm side: the wrist rotates about the elbow.
    bp = torch.zeros(1, 23, 3, dtype=torch.float64)
    bp[0, 17] = torch.tensor([0.0, -math.pi / 2, 0.0])  # left elbow (joint 18)
    o = model64(torch.zeros(1, 10, dtype=torch.float64), z[:1], bp, z[:1])
    J = model64.rest_joints(torch.zeros(1, 10, dtype=torch.float64))[0].numpy()
    # Rotating (dx, dy, dz) by -90 deg about y gives (-dz, dy, dx): the forearm points forward.
    d = J[20] - J[18]
    np.testing.assert_allclose(o.joints[0, 20].numpy(), J[18] + [-d[2], d[1], d[0]], atol=1e-9)
    np.testing.assert_allclose(o.joints[0, :18].numpy(), J[:18], atol=1e-9)


def test_global_rigid_motion_is_rigid(model64):
    rng = np.random.default_rng(2)
    B = 2
    betas = torch.tensor(rng.normal(size=(B, 10)), dtype=torch.float64)
    pose = torch.tensor(sample_plausible_poses(B, rng), dtype=torch.float64)
    z = torch.zeros(B, 3, dtype=torch.float64)
    base = model64(betas, z, pose, z)
    aa = torch.tensor([[0.3, -1.2, 0.5], [2.0, 0.1, -0.4]], dtype=torch.float64)
    t = torch.tensor([[1.0, 2.0, -3.0], [0.5, 0.0, 10.0]], dtype=torch.float64)
    moved = model64(betas, aa, pose, t)
    R = axis_angle_to_matrix(aa)
    J0 = model64.rest_joints(betas)[:, 0]
    # v' = R (v - J0) + J0 + t
    expected = torch.einsum("bij,bvj->bvi", R, base.vertices - J0[:, None]) + (J0 + t)[:, None]
    torch.testing.assert_close(moved.vertices, expected)
    d0 = torch.cdist(base.vertices[:, :200], base.vertices[:, :200])
    d1 = torch.cdist(moved.vertices[:, :200], moved.vertices[:, :200])
    torch.testing.assert_close(d0, d1, atol=1e-6, rtol=0)
    # Re-expressing a fit under p' = R2 p + t2: transl' = R2 (J0 + transl) + t2 - J0.
    R2 = axis_angle_to_matrix(torch.tensor([0.1, 0.7, -0.2], dtype=torch.float64))
    t2 = torch.tensor([3.0, -1.0, 0.25], dtype=torch.float64)
    new_R, new_t = rigid_transform_params(R, t, J0, R2, t2)
    again = model64(
        betas, new_R, axis_angle_to_matrix(pose.reshape(B, 23, 3)), new_t, pose2rot=False
    )
    torch.testing.assert_close(again.vertices, moved.vertices @ R2.T + t2)


def test_pose_blend_shapes_and_dtype_device(model64):
    model = default_body_model()
    B = 2
    pose = torch.tensor(np.stack([gait_pose(0.3), gait_pose(0.8)]), dtype=torch.float32)
    z = torch.zeros(B, 3)
    out = model(torch.zeros(B, 4), z, pose, z)
    assert out.vertices.dtype == torch.float32 and out.vertices.shape == (B, model.num_vertices, 3)
    out64 = model(torch.zeros(B, 4, dtype=torch.float64), z.double(), pose.double(), z.double())
    assert out64.vertices.dtype == torch.float64
    torch.testing.assert_close(out64.vertices.float(), out.vertices, atol=1e-5, rtol=0)
    assert model.parents[0] == -1 and model.parents.dtype == np.int64
    assert model.faces.dtype == np.int64 and model.keypoint_vertex_ids.shape == (5,)
    # Pose correctives are active: differ from a model without them.
    p = dict(default_body_params())
    p["posedirs"] = np.zeros_like(p["posedirs"])
    plain = BodyModel(p)(torch.zeros(B, 4), z, pose, z)
    diff = (plain.vertices - out.vertices).norm(dim=-1).max()
    assert 1e-4 < diff.item() < 0.05
    # Gradients flow to all parameters.
    betas = torch.zeros(1, 10, requires_grad=True)
    bp = pose[:1].clone().requires_grad_(True)
    model(betas, z[:1], bp, z[:1]).vertices.square().sum().backward()
    assert torch.isfinite(betas.grad).all() and betas.grad.abs().sum() > 0
    assert torch.isfinite(bp.grad).all() and bp.grad.abs().sum() > 0
    with pytest.raises(ValueError):
        model(torch.zeros(1, 11), z[:1], bp, z[:1])


def test_keypoint_ids_default_to_official_and_bad_params_raise(params):
    p = {k: v for k, v in params.items() if k != "coco_vertex_ids"}
    assert BodyModel(p).keypoint_vertex_ids.tolist() == [332, 2800, 6260, 583, 4071]
    assert BodyModel(params).keypoint_vertex_ids.tolist() == params["coco_vertex_ids"].tolist()
    bad = dict(p)
    bad["posedirs"] = bad["posedirs"][:, :, :200]
    with pytest.raises(ValueError, match="posedirs"):
        BodyModel(bad)
    with pytest.raises(ValueError, match="J_regressor"):
        BodyModel({k: v for k, v in p.items() if k != "J_regressor"})


# ---------------------------------------------------------------- poses and prior


def test_poses_are_plausible():
    rng = np.random.default_rng(0)
    g0, g5 = gait_pose(0.0), gait_pose(0.5)
    assert g0.shape == (69,) and g0.dtype == np.float64
    # Half a cycle later the legs have swapped: left hip flexion mirrors right.
    np.testing.assert_allclose(g0[0:3], g5[3:6], atol=1e-12)
    np.testing.assert_allclose(gait_pose(0.0), gait_pose(1.0), atol=1e-12)
    assert np.abs(standing_pose(rng)).max() < 2.0
    assert arm_swing_pose(0.25, rng).shape == (69,)
    X = sample_plausible_poses(50, rng)
    assert X.shape == (50, 69) and np.all(np.isfinite(X))


def test_gmm_prior_fit_and_evaluation():
    prior = generate_pose_prior(0)
    assert prior["means"].shape == (8, 69) and prior["covars"].shape == (8, 69, 69)
    assert prior["weights"].shape == (8,) and prior["means"].dtype == np.float64
    np.testing.assert_allclose(prior["weights"].sum(), 1.0)
    logdets = np.linalg.slogdet(prior["covars"])[1]
    assert np.all(logdets < -250)  # tiny determinants: float32 det would underflow
    gmm = GMMPosePrior(**prior)
    mu = torch.tensor(prior["means"])
    k = int(np.argmax(prior["weights"]))
    at_mean = gmm(mu[k : k + 1])
    away = gmm(mu[k : k + 1] + 0.3)
    assert at_mean.item() < away.item()
    x = (mu[k : k + 1] + 0.01).requires_grad_(True)
    gmm(x).sum().backward()
    assert torch.isfinite(x.grad).all()
    # float32 evaluation agrees with float64 and stays finite.
    v32 = gmm(mu.float())
    assert torch.isfinite(v32).all()
    torch.testing.assert_close(v32.double(), gmm(mu), atol=1e-2, rtol=1e-4)


def test_gmm_prior_matches_direct_formula_on_tiny_case():
    means = np.array([[0.0, 0.0], [1.0, 0.0]])
    covars = np.array([np.diag([1e-3, 2e-3]), np.diag([1e-2, 1e-2])])
    weights = np.array([0.25, 0.75])
    gmm = GMMPosePrior(means, covars, weights)
    x = np.array([[0.1, -0.05], [0.9, 0.1]])
    dens = 0.0
    for m, c, w in zip(means, covars, weights):
        d = x - m
        q = np.einsum("ni,ij,nj->n", d, np.linalg.inv(c), d)
        dens = dens + w * np.exp(-0.5 * q) / np.sqrt((2 * np.pi) ** 2 * np.linalg.det(c))
    np.testing.assert_allclose(gmm(torch.tensor(x)).numpy(), -np.log(dens), rtol=1e-10)


def test_fit_pose_prior_recovers_two_clusters():
    rng = np.random.default_rng(3)
    a = rng.normal([0.0, 0.0, 0.0], 0.05, size=(300, 3))
    b = rng.normal([1.0, -1.0, 0.5], 0.1, size=(100, 3))
    prior = fit_pose_prior(np.vstack((a, b)), n_components=2, seed=0)
    order = np.argsort(prior["weights"])
    np.testing.assert_allclose(prior["weights"][order], [0.25, 0.75], atol=1e-3)
    np.testing.assert_allclose(prior["means"][order[1]], a.mean(0), atol=1e-3)
    np.testing.assert_allclose(prior["means"][order[0]], b.mean(0), atol=1e-3)


def test_empty_batch_is_normal_input():
    model = default_body_model()
    z = torch.zeros(0, 3)
    out = model(torch.zeros(0, 10), z, torch.zeros(0, 69), z)
    assert out.vertices.shape == (0, model.num_vertices, 3) and out.joints.shape == (0, 24, 3)
    gmm = GMMPosePrior(np.zeros((1, 69)), np.eye(69)[None], np.ones(1))
    assert gmm(torch.zeros(0, 69)).shape == (0,)
    with pytest.raises(ValueError, match="body_pose"):
        model(torch.zeros(1, 10), torch.zeros(1, 3), torch.zeros(1, 66), torch.zeros(1, 3))
