"""The fit stage's speed cuts (issue 29 item 6) keep its results: the oracle's starts read each
frame's ground truth once, and the cuts in the fit kernel give what the plain code gave."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from tasks.body.params import BodyParams
from tasks.body.procedural import default_body_model


@pytest.fixture(scope="module")
def model():
    return default_body_model()


def _frame_truth(frame: int, persons: int) -> SimpleNamespace:
    rng = np.random.default_rng(frame)
    return SimpleNamespace(
        betas=rng.normal(0, 0.5, (persons, 10)).astype(np.float32),
        global_orient=rng.normal(0, 0.3, (persons, 3)).astype(np.float32),
        body_pose=rng.normal(0, 0.1, (persons, 69)).astype(np.float32),
        transl=(rng.normal(0, 1, (persons, 3)) + [0, 0, 6]).astype(np.float32),
    )


def test_oracle_starts_read_each_frame_once_and_match_a_read_per_row(model, monkeypatch):
    import flows.stages.providers as providers
    from flows.pipeline.inputs import OracleInitSpec
    from flows.stages.common import frame_rng
    from tasks.fit.init_oracle import oracle_initial_estimate
    from tasks.fit.reframe import reframe_params

    truths = {f: _frame_truth(f, 4) for f in (10, 12, 14)}
    reads: list[int] = []

    def read(root, sequence, frame):
        reads.append(frame)
        return truths[frame]

    monkeypatch.setattr(providers, "read_frame_gt", read)
    T_cl = np.eye(4)
    T_cl[:3, 3] = [0.1, -0.2, 0.3]
    seq = SimpleNamespace(root="unused", sequence="0")
    init = providers.OracleInit(
        OracleInitSpec(3), seq, model, SimpleNamespace(T_cam_from_lidar=T_cl)
    )
    frame = np.array([10, 10, 12, 12, 12, 14, 10, 14])
    gt_index = np.array([0, 2, 1, 3, 0, 2, 3, 0])
    tracks = SimpleNamespace(frame=frame, gt_index=gt_index)
    rows = np.array([1, 0, 2, 3, 4, 5, 6, 7])
    got = init.estimates(tracks, rows)
    assert sorted(reads) == [10, 12, 14]  # one read per frame, not one per row
    truth = BodyParams.concat(
        [BodyParams.of(truths[int(frame[r])]).take([int(gt_index[r])]) for r in rows]
    )
    want = oracle_initial_estimate(
        model, reframe_params(model, truth, T_cl), frame_rng(3, "0", int(rows[0]), 3)
    )
    for k in BodyParams.FIELDS:
        assert np.array_equal(getattr(got, k), getattr(want, k)), k


def _subset_reference(model, betas, go, bp, tr, ids, offsets):
    """The subset forward as it was written before the vertices-last layout: (B, N, 12)
    skinning transforms, the vertices gathered first."""
    import torch

    from tasks.body.model import NUM_JOINTS

    B = betas.shape[0]
    rot = model._rotations(B, go, bp, True)
    J = model.rest_joints(betas)
    G_rot, joints = model._kinematics(rot, J)
    A = torch.cat((G_rot, (joints - (G_rot @ J[..., None])[..., 0])[..., None]), dim=-1)
    v_posed = (
        model.v_template[None]
        + offsets
        + torch.einsum("bl,vcl->bvc", betas, model.shapedirs[:, :, : betas.shape[1]])
    )
    v_posed = torch.gather(v_posed, 1, ids[..., None].expand(-1, -1, 3))
    T = model.lbs_weights[ids] @ A.reshape(B, NUM_JOINTS, 12)
    c0, c1, c2, c3 = T.unflatten(-1, (3, 4)).unbind(-1)
    x, y, z = (c[..., None] for c in v_posed.unbind(-1))
    return c0 * x + c1 * y + c2 * z + c3 + tr[:, None, :], joints + tr[:, None, :]


@pytest.mark.parametrize("B", [1, 5])
def test_subset_forward_in_the_vertices_last_layout_gives_the_same_bits(model, B):
    import torch

    g = torch.Generator().manual_seed(B)
    V = model.v_template.shape[0]
    ids = torch.stack([torch.randperm(V, generator=g)[:700] for _ in range(B)])
    params = [
        torch.randn(B, n, generator=g, dtype=torch.float32) * s
        for n, s in ((10, 0.5), (3, 0.4), (69, 0.2), (3, 1.0))
    ]
    offsets = model.pose_offsets(params[1], params[2])

    def run(forward):
        x = [p.clone().requires_grad_(True) for p in params]
        verts, joints = forward(x)
        loss = (verts**2).sum() + (verts[..., 0] * verts[..., 2]).sum() + (joints**2).sum()
        return verts.detach(), joints.detach(), torch.autograd.grad(loss, x)

    def new(x):
        o = model(*x, vertex_subset=model.select_vertices(ids), pose_offsets=offsets)
        return o.vertices, o.joints

    got, want = run(new), run(lambda x: _subset_reference(model, *x, ids, offsets))
    assert got[0].shape == (B, 700, 3) and got[0].is_contiguous()
    assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])
    # the gradients to within float32 rounding: the backward's sums run in an order that
    # depends on the CPU's vector width (the same bits on the machine that wrote this test,
    # 9e-8 of the largest gradient apart on a Xeon with AVX-512 BF16 / FP16)
    for a, b in zip(got[2], want[2]):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-6 * float(b.abs().max()))
    full = model(*params, pose_offsets=offsets).vertices  # and the whole body agrees
    torch.testing.assert_close(got[0], torch.gather(full, 1, ids[..., None].expand(-1, -1, 3)))


def test_icp_transform_written_per_coordinate_gives_the_same_bits():
    import torch

    from tasks.fit.icp import _apply

    g = torch.Generator().manual_seed(4)
    for k in (1, 3, 17):
        x = torch.randn(k, 501, 3, dtype=torch.float64, generator=g)
        T = torch.eye(4, dtype=torch.float64).repeat(k, 1, 1)
        T[:, :3, :3] = torch.linalg.qr(torch.randn(k, 3, 3, dtype=torch.float64, generator=g))[0]
        T[:, :3, 3] = torch.randn(k, 3, dtype=torch.float64, generator=g)
        R, t = T[:, None, :3, :3], T[:, None, :3, 3]
        assert torch.equal(_apply(T, x), (R * x[..., None, :]).sum(-1) + t)


def test_a_fit_without_its_posed_bodies_and_final_terms_gives_the_same_parameters(model):
    from tasks.body.prior import GMMPosePrior, generate_pose_prior
    from tasks.fit.init_oracle import oracle_initial_estimate
    from tasks.fit.lidar_sim import R_CAM_FROM_LIDAR, SENSORS, observe_bodies, walking_track_params
    from tasks.fit.optimize import ragged_points
    from tasks.fit.settings import FitSettings
    from tasks.fit.track_fit import persons_fit
    from tasks.fit.weights import FIT_PRESETS

    K = np.array([[1000.0, 0, 960], [0, 1000.0, 540], [0, 0, 1]])
    T_cl = np.eye(4)
    T_cl[:3, :3] = R_CAM_FROM_LIDAR
    rng = np.random.default_rng(5)
    truth = walking_track_params(model, rng.normal(0, 0.8, 10), [0.3, 1.3, 5.0], 0.5, 1.2, 3, 5.0)
    obs = observe_bodies(
        model, *(getattr(truth, f) for f in BodyParams.FIELDS), SENSORS["ouster-64"], rng, K
    )
    pts, counts = ragged_points(obs.points_lidar, obs.point_mask)
    start = oracle_initial_estimate(model, truth, np.random.default_rng(1))
    g = generate_pose_prior()
    prior = GMMPosePrior(g["means"], g["covars"], g["weights"])
    fit = persons_fit(
        model, prior, K, T_cl, FIT_PRESETS["3dpw"], FitSettings(iterations=12, nn_every=3)
    )
    full = fit(obs.keypoints, pts, counts, start, iterations=12)
    lean = fit(obs.keypoints, pts, counts, start, iterations=12, posed=False, terms=False)
    for k in BodyParams.FIELDS:
        assert np.array_equal(getattr(full, k), getattr(lean, k)), k
    assert full.vertices.shape == (3, model.v_template.shape[0], 3)
    assert lean.vertices.shape == (3, 0, 3) and lean.joints.shape == (3, 0, 3)
    assert set(lean.residuals) == {"icp_fitness", "visible_vertices", "steps"}
    for k in lean.residuals:
        assert np.array_equal(full.residuals[k], lean.residuals[k]), k
    assert {"L_J", "L_3D", "total"} <= set(full.residuals)
