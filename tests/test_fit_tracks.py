"""Bodies along tracks (issue 29): the weight-free start, left / right swaps, one shape per track,
the temporal refinement, gap filling, and their edge cases, on procedural persons."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from tasks.body.params import BodyParams
from tasks.body.poses import sample_plausible_poses
from tasks.body.prior import GMMPosePrior, generate_pose_prior
from tasks.body.procedural import default_body_model
from tasks.body.rotations import axis_angle_to_matrix
from tasks.fit.flips import CHAINS, chains_towards, decide_flips
from tasks.fit.gaps import (
    OCCLUDED,
    SEEN_THROUGH,
    SUPPORTED,
    UNOBSERVED,
    check_body,
    find_gaps,
    interpolate_bodies,
)
from tasks.fit.init_lidar import facing_costs, initial_bodies, lidar_keypoint_init, mirrored
from tasks.fit.init_oracle import oracle_initial_estimate
from tasks.fit.lidar_sim import (
    R_CAM_FROM_LIDAR,
    SENSORS,
    observe_bodies,
    synthesize_persons,
    walking_track_params,
)
from tasks.fit.metrics import mean_error_mm
from tasks.fit.optimize import ragged_points
from tasks.fit.refine import (
    acceleration_error,
    divided_difference_coefficients,
    neighbours,
    refine_tracks,
    smooth_tracks,
    whittaker_lambda,
    whittaker_smooth,
    windows,
)
from tasks.fit.reframe import reframe_params
from tasks.fit.settings import (
    FitSettings,
    FlipSettings,
    GapSettings,
    InitLidarSettings,
    RefineSettings,
)
from tasks.fit.shape import geometric_median, shape_spread, track_shapes, with_shape
from tasks.fit.track_fit import persons_fit
from tasks.fit.weights import FIT_PRESETS

K = np.array([[1000.0, 0, 960], [0, 1000.0, 540], [0, 0, 1]])
T_CL = np.eye(4)
T_CL[:3, :3] = R_CAM_FROM_LIDAR
UP_CAM = np.array([0.0, -1.0, 0.0])  # a level camera: y down
INIT = InitLidarSettings()


@pytest.fixture(scope="module")
def model():
    return default_body_model()


@pytest.fixture(scope="module")
def prior():
    g = generate_pose_prior()
    return GMMPosePrior(g["means"], g["covars"], g["weights"])


def _posed(model, p: BodyParams):
    with torch.no_grad():
        o = model(*(torch.as_tensor(getattr(p, f)) for f in BodyParams.FIELDS))
    return o.vertices.numpy(), o.joints.numpy()


def _cam_points(points_lidar, mask):
    pts, counts = ragged_points(points_lidar, mask)
    return pts.astype(np.float64) @ R_CAM_FROM_LIDAR.T, pts, counts


def _track(model, heading, speed, frames=4, seed=3, mirror=False):
    """One person walking (or standing) 5 m ahead of a level camera: truth, observations."""
    rng = np.random.default_rng(seed)
    truth = walking_track_params(
        model, rng.normal(0, 0.8, 10), [0.3, 1.3, 5.0], heading, speed, frames, 5.0, 0.2
    )
    obs = observe_bodies(
        model,
        *(getattr(truth, f) for f in BodyParams.FIELDS),
        SENSORS["ouster-64"],
        rng,
        K,
        max_points=400,
    )
    kp = mirrored(obs.keypoints) if mirror else obs.keypoints
    return truth, obs, kp


# ---- the weight-free start ---------------------------------------------------------------------


def test_weight_free_start_on_procedural_persons(model, prior):
    rng = np.random.default_rng(5)
    sp = synthesize_persons(
        model,
        sample_plausible_poses(3, rng),
        SENSORS["ouster-64"],
        rng,
        distance_m=(4.0, 7.0),
        occlusion_prob=0.0,
        max_points=400,
    )
    pc, pts, counts = _cam_points(sp.points_lidar, sp.point_mask)
    costs = facing_costs(model, sp.keypoints, K, pc, counts, UP_CAM, INIT)
    start = initial_bodies(model, costs, costs.best(), sp.keypoints, K, pc, counts, UP_CAM, INIT)
    # heading: the chosen facing within 30 deg of the true one (the template faces +z)
    true_facing = axis_angle_to_matrix(
        torch.as_tensor(sp.truth.global_orient, dtype=torch.float64)
    ).numpy()[:, :, 2]
    got = costs.facing_cam[np.arange(3), costs.best()]
    assert np.degrees(np.arccos(np.clip((true_facing * got).sum(1), -1, 1))).max() < 30.0
    # stature from the points: within 12 cm of the true heel-to-crown height
    with torch.no_grad():
        rest = model(
            torch.as_tensor(sp.truth.betas),
            torch.zeros(3, 3),
            torch.zeros(3, 69),
            torch.zeros(3, 3),
        )
    assert np.abs(costs.stature_m - np.ptp(rest.vertices.numpy()[..., 1], axis=1)).max() < 0.12
    _, joints = _posed(model, start)
    assert np.linalg.norm(joints[:, 0] - sp.truth_joints[:, 0], axis=1).max() < 0.25
    # no network, no ground truth: the start is already nearer than the oracle's (depth errs
    # 0.3 m there), and a short fit from it is as good as one from the oracle's
    oracle = oracle_initial_estimate(
        model,
        sp.truth,
        rng,
    )
    assert (
        mean_error_mm(joints, sp.truth_joints).mean()
        < mean_error_mm(_posed(model, oracle)[1], sp.truth_joints).mean()
    )
    fit = persons_fit(model, prior, K, T_CL, FIT_PRESETS["3dpw"], FitSettings())
    ours = fit(sp.keypoints, pts, counts, start, iterations=30)
    theirs = fit(sp.keypoints, pts, counts, oracle, iterations=30)
    e_ours = mean_error_mm(ours.joints, sp.truth_joints).mean()
    assert e_ours < 60.0 and e_ours < mean_error_mm(theirs.joints, sp.truth_joints).mean() + 15.0


def test_weight_free_start_without_points_or_confident_keypoints(model):
    """A detection with no LiDAR points is placed by its keypoints alone; one whose keypoints
    are all below the confidence threshold and that has no points either still gets a finite
    body, and both labellings cost the same (nothing to decide)."""
    truth, obs, kp = _track(model, np.pi, 0.0, frames=1)
    low = kp.copy()
    low[..., 2] = 0.1
    none = np.zeros((0, 3))
    for keypoints in (kp, low):
        costs = facing_costs(model, keypoints, K, none, np.array([0]), UP_CAM, INIT)
        body = lidar_keypoint_init(model, keypoints, K, none, np.array([0]), UP_CAM, INIT)
        assert not costs.has_points[0]
        assert all(np.isfinite(getattr(body, f)).all() for f in BodyParams.FIELDS)
    _, joints = _posed(model, lidar_keypoint_init(model, kp, K, none, np.array([0]), UP_CAM, INIT))
    assert (
        np.linalg.norm(joints[0, 0] - obs.joints[0, 0]) < 1.0
    )  # keypoints alone: depth within 1 m
    costs = facing_costs(model, low, K, none, np.array([0]), UP_CAM, INIT)
    assert not costs.has_keypoints[0] and np.array_equal(costs.cost[:, 0], costs.cost[:, 1])


# ---- left / right swaps ------------------------------------------------------------------------


def _decide(model, heading, speed, mirror, settings=FlipSettings()):
    truth, obs, kp = _track(model, heading, speed, mirror=mirror)
    pc, pts, counts = _cam_points(obs.points_lidar, obs.point_mask)
    costs = facing_costs(model, kp, K, pc, counts, UP_CAM, INIT)
    ends = np.cumsum(counts)
    where = np.stack([np.median(pts[e - n : e], 0) for n, e in zip(counts, ends)])
    return decide_flips(
        np.ones(len(kp), int),
        np.arange(len(kp)) * 0.2,
        where,
        costs.facing_cam,
        costs.cost,
        R_CAM_FROM_LIDAR.T,
        settings,
    )


def test_mirrored_keypoints_of_a_back_view_are_flipped(model):
    """A person walking away (seen from behind) whose keypoints came mirrored, as BlazePose
    gives them: every frame is decided mirrored; the same person walking towards the camera
    with keypoints as detected: none is."""
    back = _decide(model, 0.0, 1.2, mirror=True)
    assert back.mirrored.all() and back.decided.all()
    assert back.counts() == {"flipped": 4, "kept": 0, "undecided": 0}
    front = _decide(model, np.pi, 1.2, mirror=False)
    assert not front.mirrored.any() and front.decided.all()


def test_flip_with_both_candidates_equally_poor_is_kept_and_counted():
    R, Y = 3, 8
    facing = np.zeros((R, Y, 3))
    psi = np.arange(Y) * 2 * np.pi / Y
    facing[..., 0], facing[..., 2] = np.sin(psi), np.cos(psi)
    cost = np.ones((R, 2, Y))  # the same for both labellings and every heading
    d = decide_flips(
        np.ones(R, int),
        np.arange(R) * 0.2,
        np.zeros((R, 3)),
        facing,
        cost,
        R_CAM_FROM_LIDAR.T,
        FlipSettings(),
    )
    assert not d.mirrored.any() and not d.decided.any()
    assert d.counts() == {"flipped": 0, "kept": 0, "undecided": 3}
    # a track of one frame, standing: its own costs decide; equal costs: kept, undecided
    one = decide_flips(
        [7], [0.0], np.zeros((1, 3)), facing[:1], cost[:1], R_CAM_FROM_LIDAR.T, FlipSettings()
    )
    assert not one.mirrored[0] and not one.decided[0]
    off = decide_flips(
        np.ones(R, int),
        np.arange(R) * 0.2,
        np.zeros((R, 3)),
        facing,
        cost,
        R_CAM_FROM_LIDAR.T,
        FlipSettings(enabled=False),
    )
    assert not off.mirrored.any()


def _swap_chain(kp, chain):
    out = np.array(kp, copy=True)
    left, right = (list(x) for x in CHAINS[chain])
    out[:, left], out[:, right] = kp[:, right], kp[:, left]
    return out


def _identity_fit(keypoints, points_lidar, counts, init, **kw):
    from types import SimpleNamespace

    return SimpleNamespace(**{f: getattr(init, f) for f in BodyParams.FIELDS}, residuals={})


def _standing_back_view(model, swap):
    """Three frames of a person standing with its back to the camera, keypoints changed by
    swap; its TrackRows, the true keypoints and an oracle-like start."""
    from tasks.fit.track_fit import TrackRows

    truth, obs, kp = _track(model, 0.0, 0.0, frames=3)
    pts, counts = ragged_points(obs.points_lidar, obs.point_mask)
    n = len(kp)
    rows = TrackRows(
        np.ones(n, np.int64),
        np.arange(n),
        swap(kp).astype(np.float32),
        pts.astype(np.float32),
        counts,
        K,
        T_CL,
        np.stack([np.eye(4)] * n),
        np.arange(n) * 0.2,
    )
    return rows, kp, oracle_initial_estimate(model, truth, np.random.default_rng(1))


def _fit_ids(model, rows, start, flips):
    from tasks.fit.track_fit import fit_tracks

    return fit_tracks(
        rows,
        _identity_fit,
        model,
        start,
        FitSettings(shared_shape=False),
        INIT,
        flips,
        RefineSettings(enabled=False),
    )


def test_legs_swapped_alone_follow_the_start(model):
    """A back view whose legs alone came swapped, as BlazePose does: the track decides to keep
    the labelling (the arms are right), so the legs stay swapped unless each chain follows the
    provider's start (``follow_start: always``: legs relabelled, arms and face untouched); with
    ``undecided`` (configs/bundled-models.yaml's) only rows the track could not decide follow it."""
    rows, kp, start = _standing_back_view(model, lambda k: _swap_chain(k, 2))
    legs = np.asarray(rows.keypoints)
    assert np.abs(legs - kp).max() > 10.0  # the swap moved keypoints (pixels)
    # standing, the legs are ~0.055 start heights apart in the image: a margin below that
    near = FlipSettings(start_margin=0.02, follow_start="undecided")
    every = _fit_ids(model, rows, start, dataclasses.replace(near, follow_start="always"))
    assert every.flips.decided.all() and not every.flips.mirrored.any()
    np.testing.assert_allclose(every.keypoints, kp, atol=1e-3)
    assert every.flips.chains[:, 2].all() and not every.flips.chains[:, :2].any()
    assert every.flips.counts()["chains_to_start"] == 3
    for mode in ("undecided", "never"):
        kept = _fit_ids(model, rows, start, dataclasses.replace(near, follow_start=mode))
        np.testing.assert_allclose(kept.keypoints, legs, atol=1e-3)
    # the same rows left undecided by the track (a margin nothing reaches): relabelled
    undecided = _fit_ids(model, rows, start, dataclasses.replace(near, min_margin=100.0))
    assert undecided.flips.counts() == {
        "flipped": 0,
        "kept": 0,
        "undecided": 3,
        "chains_to_start": 3,
        "keypoints_dropped": 0,  # exact keypoints, all near the start's
    }
    np.testing.assert_allclose(undecided.keypoints, kp, atol=1e-3)


def test_a_keypoint_far_from_the_start_is_dropped(model):
    """With ``start_max_distance`` a keypoint far from the start's (a wrist 0.6 heights off, as
    on a person cut by the image border) gets confidence 0 and is counted; the others keep
    theirs; without the setting (None) nothing is dropped."""

    def wild(k):
        out = np.array(k, copy=True)
        out[:, 9, :2] += [0.0, -200.0]  # left wrist 200 px up, about 0.6 heights
        return out

    rows, kp, start = _standing_back_view(model, wild)
    follow = FlipSettings(follow_start="undecided")
    got = _fit_ids(model, rows, start, dataclasses.replace(follow, start_max_distance=0.3))
    assert (got.keypoints[:, 9, 2] == 0).all()
    others = np.delete(np.arange(17), 9)
    np.testing.assert_allclose(got.keypoints[:, others], kp[:, others], atol=1e-3)
    assert got.flips.counts()["keypoints_dropped"] == 3
    kept = _fit_ids(model, rows, start, dataclasses.replace(follow, start_max_distance=None))
    assert (kept.keypoints[:, 9, 2] > 0).all() and "keypoints_dropped" not in kept.flips.counts()


def test_chains_towards_a_start_keep_ties_and_unconfident_chains():
    """Keypoints as far from the start either way (a chain whose left and right coincide) or
    below the confidence threshold are kept as detected; rows not selected are untouched."""
    uv = np.zeros((3, 17, 2))
    uv[:, :, 1] = np.linspace(0, 170, 17)  # 170 px tall
    uv[:, 5::2, 0], uv[:, 6::2, 0] = 10.0, -10.0  # left keypoints at +10 px, right at -10
    kp = np.concatenate([uv, np.ones((3, 17, 1))], -1)
    sw = _swap_chain(kp, 1)  # arms swapped
    sw[1, 5:11, 2] = 0.1  # row 1: the arms not confident
    for left, right in zip(*CHAINS[1]):  # row 2: each pair on its start pair's midpoint: a tie
        sw[2, [left, right], :2] = (uv[2, left] + uv[2, right]) / 2
    out, chains = chains_towards(sw, uv, np.ones(3, bool), 0.3, 0.02)
    assert chains[:, 1].tolist() == [True, False, False]
    np.testing.assert_array_equal(out[0], kp[0])
    np.testing.assert_array_equal(out[1:], sw[1:])
    out, chains = chains_towards(sw, uv, np.zeros(3, bool), 0.3, 0.02)
    assert not chains.any() and np.array_equal(out, sw)


# ---- one shape per track -----------------------------------------------------------------------


def test_track_shape_is_a_robust_median_and_keeps_the_root(model):
    rng = np.random.default_rng(0)
    true = rng.normal(0, 1, 10)
    betas = true + rng.normal(0, 0.05, (7, 10))
    betas[3] += 3.0  # one frame gone wrong
    ids = np.r_[np.ones(7, int), 2 * np.ones(2, int)]
    all_b = np.concatenate([betas, rng.normal(0, 1, (2, 10))])
    shared, per_track = track_shapes(ids, all_b, np.r_[np.full(7, 100), 50, 50])
    assert np.abs(per_track[1] - true).max() < 0.1  # the outlier frame moved it little
    assert np.abs(np.mean(betas, 0) - true).max() > 0.3  # where a mean would follow it
    assert shape_spread(ids, shared) == 0.0 and shape_spread(ids, all_b) > 0.1
    assert np.allclose(geometric_median(np.eye(3), np.ones(3)), np.full(3, 1 / 3), atol=1e-3)
    transl = rng.normal(0, 1, (9, 3)).astype(np.float32)
    moved = with_shape(model, all_b, transl, shared)
    with torch.no_grad():
        j_old = model.rest_joints(torch.as_tensor(all_b, dtype=torch.float32))[:, 0].numpy()
        j_new = model.rest_joints(torch.as_tensor(shared))[:, 0].numpy()
    assert np.allclose(j_old + transl, j_new + moved, atol=1e-5)


# ---- the temporal refinement -------------------------------------------------------------------


def _refine(model, prior, truth, obs, start, settings=RefineSettings()):
    pc, pts, counts = _cam_points(obs.points_lidar, obs.point_mask)
    fit = persons_fit(model, prior, K, T_CL, FIT_PRESETS["3dpw"], FitSettings())
    n = len(start)

    def refit(sel, init, coupling):
        ends = np.cumsum(counts)
        p = np.concatenate([pts[ends[r] - counts[r] : ends[r]] for r in sel])
        return fit(
            obs.keypoints[sel],
            p,
            counts[sel],
            init,
            iterations=settings.iterations,
            frozen=("betas",),
            coupling=coupling,
            use_icp=False,
            lr=settings.learning_rate,
        )

    out, _ = refine_tracks(
        refit,
        start,
        np.ones(n, int),
        np.arange(n) * 0.2,
        np.arange(n),
        np.tile(np.linalg.inv(T_CL), (n, 1, 1)),
        0.2,
        settings,
    )
    return out


def test_refinement_lowers_acceleration_of_a_jittered_track_and_keeps_a_steady_one(model, prior):
    truth, obs, _ = _track(model, 0.6, 1.2, frames=5)
    rng = np.random.default_rng(1)
    jittered = BodyParams(
        truth.betas,
        truth.global_orient,
        (truth.body_pose + rng.normal(0, 0.06, truth.body_pose.shape)).astype(np.float32),
        (truth.transl + rng.normal(0, 0.03, truth.transl.shape)).astype(np.float32),
    )
    refined = _refine(model, prior, truth, obs, jittered)
    ids, t = np.ones(5, int), np.arange(5) * 0.2
    acc = lambda p: np.nanmean(acceleration_error(ids, t, _posed(model, p)[1], obs.joints)[0])
    assert acc(refined) < 0.7 * acc(jittered)
    assert (
        mean_error_mm(_posed(model, refined)[1], obs.joints).mean()
        < mean_error_mm(_posed(model, jittered)[1], obs.joints).mean()
    )
    # a person standing still, already fitted frame by frame: the refinement leaves it be
    still, obs2, _ = _track(model, 2.0, 0.0, frames=4, seed=4)
    fitted = _refine(
        model,
        prior,
        still,
        obs2,
        still,
        RefineSettings(joint_weight=0, torso_weight=0, root_weight=0),
    )
    kept = _refine(model, prior, still, obs2, fitted)
    moved = np.linalg.norm(_posed(model, kept)[1] - _posed(model, fitted)[1], axis=-1)
    assert moved.mean() < 0.005 and moved.max() < 0.02


def test_whittaker_smoother_keeps_lines_and_cuts_at_the_same_frequency_at_any_rate():
    for rate in (5.0, 10.0, 30.0):
        t = np.arange(int(8 * rate)) / rate
        ids = np.ones(len(t), int)
        prev, nxt = neighbours(ids, t, 1.0)
        coef = divided_difference_coefficients(t, prev, nxt, 1 / rate)
        lam = whittaker_lambda(1.0, 1 / rate)
        line = np.stack([0.3 + 1.2 * t, -0.5 * t], 1)
        np.testing.assert_allclose(whittaker_smooth(line, prev, nxt, coef, lam), line, atol=1e-9)
        # a sine at the cut-off keeps about half its amplitude, one at a quarter of it nearly
        # all, one at twice it little, whatever the rate
        mid = slice(len(t) // 4, 3 * len(t) // 4)
        for f, lo, hi in ((1.0, 0.45, 0.6), (0.25, 0.97, 1.01), (2.0, 0.0, 0.1)):
            if 2 * f >= rate / 2:
                continue
            y = np.sin(2 * np.pi * f * t)[:, None]
            out = whittaker_smooth(y, prev, nxt, coef, lam)
            gain = np.abs(out[mid]).max() / np.abs(y[mid]).max()
            assert lo <= gain <= hi, (rate, f, gain)


def test_whittaker_smoother_is_the_exact_minimiser_on_uneven_steps_and_scales_to_long_tracks():
    rng = np.random.default_rng(4)
    t = np.cumsum(rng.uniform(0.1, 0.3, 40))
    t = np.concatenate([t, t[-1] + 2.0 + t])  # two chains: a gap longer than the tie
    ids = np.ones(len(t), int)
    prev, nxt = neighbours(ids, t, 0.5)
    coef = divided_difference_coefficients(t, prev, nxt, 0.2)
    y = rng.normal(size=(len(t), 3))
    lam = np.array([0.5, 5.0, 50.0])
    # the dense normal equations, per column
    inner = np.flatnonzero((prev >= 0) & (nxt >= 0))
    D2 = np.zeros((len(inner), len(t)))
    D2[np.arange(len(inner)), prev[inner]] = coef[inner, 0]
    D2[np.arange(len(inner)), inner] = coef[inner, 1]
    D2[np.arange(len(inner)), nxt[inner]] = coef[inner, 2]
    want = np.stack(
        [np.linalg.solve(np.eye(len(t)) + w * D2.T @ D2, y[:, k]) for k, w in enumerate(lam)], 1
    )
    np.testing.assert_allclose(whittaker_smooth(y, prev, nxt, coef, lam), want, atol=1e-10)
    # a person in view for an hour at 10 Hz: a dense system would take 10 GB
    n = 36_000
    t = np.arange(n) / 10.0
    prev, nxt = neighbours(np.zeros(n, int), t, 0.5)
    coef = divided_difference_coefficients(t, prev, nxt, 0.1)
    line = np.stack([0.5 * t, np.ones(n)], 1)
    out = whittaker_smooth(line, prev, nxt, coef, whittaker_lambda(3.0, 0.1))
    np.testing.assert_allclose(out, line, atol=1e-6)


def _world_track(model, rate, frames, rng, walk=(0.0, 0.0, 0.0)):
    """A standing person (pose from the prior's samples) gliding at ``walk`` m/s in the world,
    seen from a camera that drives and turns: cam-frame params, T_world_from_cam, the world
    joints."""
    betas = np.tile(rng.normal(0, 0.8, 10), (frames, 1)).astype(np.float32)
    t = np.arange(frames) / rate
    T = np.tile(np.eye(4), (frames, 1, 1))
    yaw = 0.4 * t
    T[:, :3, :3] = Rotation.from_rotvec(yaw[:, None] * [0, 0, 1]).as_matrix() @ R_CAM_FROM_LIDAR.T
    T[:, :3, 3] = np.stack([1.0 * t, 0.2 * t, np.full(frames, 0.5)], 1)
    R_w = Rotation.from_euler("zx", [0.7, np.pi / 2]).as_matrix()
    pose = np.tile(rng.normal(0, 0.1, 69), (frames, 1)).astype(np.float32)
    J0 = model.rest_joints(torch.as_tensor(betas[:1]))[0, 0].detach().numpy().astype(np.float64)
    p_w = np.array([4.0, 1.0, 0.9]) + np.asarray(walk) * t[:, None]
    Rcw = np.transpose(T[:, :3, :3], (0, 2, 1))
    go = Rotation.from_matrix(Rcw @ R_w).as_rotvec().astype(np.float32)
    transl = (np.einsum("rij,rj->ri", Rcw, p_w - T[:, :3, 3]) - J0).astype(np.float32)
    return BodyParams(betas, go, pose, transl), T, t


def _world_joints(model, p, T):
    j = _posed(model, p)[1].astype(np.float64)
    return np.einsum("rij,rkj->rki", T[:, :3, :3], j) + T[:, None, :3, 3]


def test_smoothing_start_lowers_jitter_and_keeps_a_steady_track(model):
    """The refinement's closed-form start (root, orientation and pose through a Whittaker
    smoother in a world-fixed frame): a gliding person seen from a driving, turning robot is
    kept as it is; the same person with per-frame jitter of root, orientation and pose gets
    back most of the way, its acceleration error a third or less."""
    rng = np.random.default_rng(5)
    rate, n = 10.0, 16
    steady, T, t = _world_track(model, rate, n, rng, walk=(0.8, -0.3, 0.0))
    ids = np.ones(n, int)
    s = RefineSettings(root_cutoff_hz=2.0, orient_cutoff_hz=2.0, pose_cutoff_hz=2.0)
    kept = smooth_tracks(steady, ids, t, T, 1 / rate, s)
    for f in ("global_orient", "body_pose", "transl"):
        np.testing.assert_allclose(getattr(kept, f), getattr(steady, f), atol=2e-5)
    truth = _world_joints(model, steady, T)
    jit = BodyParams(
        steady.betas,
        (steady.global_orient + rng.normal(0, 0.05, (n, 3))).astype(np.float32),
        (steady.body_pose + rng.normal(0, 0.05, (n, 69))).astype(np.float32),
        (steady.transl + rng.normal(0, 0.02, (n, 3))).astype(np.float32),
    )
    out = smooth_tracks(jit, ids, t, T, 1 / rate, s)
    acc = lambda p: np.nanmean(acceleration_error(ids, t, _world_joints(model, p, T), truth)[0])
    err = lambda p: np.linalg.norm(_world_joints(model, p, T) - truth, axis=-1).mean()
    assert acc(out) < acc(jit) / 3
    assert err(out) < 0.6 * err(jit)
    # another track in the same call is smoothed on its own (no term across tracks)
    both = BodyParams(
        *(np.concatenate([getattr(jit, f), getattr(steady, f)]) for f in BodyParams.FIELDS)
    )
    two = smooth_tracks(both, np.r_[ids, ids + 1], np.r_[t, t], np.concatenate([T, T]), 1 / rate, s)
    np.testing.assert_allclose(two.transl[:n], out.transl, atol=1e-5)
    np.testing.assert_allclose(two.transl[n:], steady.transl, atol=2e-5)


def test_refinement_windows_and_a_track_of_one_frame():
    # a long track in overlapping windows, a track of one row in its own
    w = windows(np.r_[np.ones(100, int), [2]], np.r_[np.arange(100), 5], 48, 8)
    assert [len(x) for x in w] == [48, 48, 20, 1]
    err, ok = acceleration_error([1], [0.0], np.zeros((1, 24, 3)), np.zeros((1, 24, 3)))
    assert not ok.any() and np.isnan(err).all()


# ---- gap filling -------------------------------------------------------------------------------


def test_gap_filling_on_a_track_with_a_hole(model):
    """A walking person fitted in frames 0, 1, 3, 4 (frame 2 missed): frame 2 gets a body from
    its neighbours, near the truth; checked against the sweep it is supported by the person's
    points, seen through when the sweep has only a wall behind it, kept when the sweep says
    nothing; a hole longer than the limit is left empty."""
    truth, obs, _ = _track(model, 1.0, 1.2, frames=5)
    # the fits in each frame's LiDAR frame (the robot stands still: identity poses)
    fits = reframe_params(model, truth, np.linalg.inv(T_CL))
    keep = np.array([0, 1, 3, 4])
    poses = np.tile(np.eye(4), (5, 1, 1))
    gaps = find_gaps(np.ones(4, int), keep, np.arange(5) * 0.2, max_gap_frames=2)
    assert (
        gaps.position.tolist() == [2] and gaps.before.tolist() == [1] and gaps.after.tolist() == [2]
    )
    filled = interpolate_bodies(model, fits.take(keep), gaps, poses, keep)
    verts, joints = _posed(model, filled)
    truth_lidar = (obs.joints[2].astype(np.float64) - T_CL[:3, 3]) @ R_CAM_FROM_LIDAR
    # better than holding the frame before's body (moved along the track)
    hold = interpolate_bodies(
        model, fits.take(keep), dataclasses.replace(gaps, alpha=np.zeros(1)), poses, keep
    )
    err = mean_error_mm(joints, truth_lidar[None]).mean()
    assert err < 80.0 and err < mean_error_mm(_posed(model, hold)[1], truth_lidar[None]).mean()
    s = GapSettings()
    sweep = obs.points_lidar[2][obs.point_mask[2]]
    assert check_body(verts[0], sweep, s).status == SUPPORTED
    wall = np.stack(np.meshgrid(np.linspace(-1, 1, 30), np.linspace(-1.5, 1.5, 40)), -1).reshape(
        -1, 2
    )
    centre = verts[0].mean(0)
    behind = np.c_[
        np.full(len(wall), centre[0] + 3.0), centre[1] + wall[:, 0], centre[2] + wall[:, 1]
    ]
    seen = check_body(verts[0], behind, s)
    assert seen.status == SEEN_THROUGH and not seen.keep
    front = behind.copy()
    front[:, 0] = centre[0] - 1.5
    assert check_body(verts[0], front, s).status == OCCLUDED
    nothing = check_body(verts[0], np.zeros((0, 3)), s)
    assert nothing.keep and nothing.status == UNOBSERVED
    # a longer hole than the limit: not filled
    assert len(find_gaps([1, 1], [0, 4], np.arange(5) * 0.2, max_gap_frames=2)) == 0


# ---- warm starts along a track ------------------------------------------------------------------


def test_warm_start_carries_a_tracks_fit_into_its_next_frame(model):
    """fit_tracks with an identity 'fit' (its output is its start): a track fitted in the
    previous frame starts from that body moved by the ego-motion, so in the world it stays put
    exactly; a new track, or one after a frame gap, starts from the provider's estimate."""
    from types import SimpleNamespace

    from tasks.fit.track_fit import TrackRows, fit_tracks

    def pose(yaw, x):
        T = np.eye(4)
        T[:3, :3] = axis_angle_to_matrix(torch.tensor([0.0, 0.0, yaw], dtype=torch.float64)).numpy()
        T[:3, 3] = [x, 0.5 * x, 0.0]
        return T

    poses = np.stack([pose(0.1 * k, 0.7 * k) for k in range(4)])
    # track 1 in frames 0, 1, 2; track 2 in 1; track 3 in 0 and 2 (a gap)
    track_id, position = np.array([1, 3, 1, 2, 1, 3]), np.array([0, 0, 1, 1, 2, 2])
    n = len(track_id)
    rng = np.random.default_rng(0)
    est = BodyParams(
        rng.normal(0, 0.5, (n, 10)).astype(np.float32),
        rng.normal(0, 0.3, (n, 3)).astype(np.float32),
        rng.normal(0, 0.2, (n, 69)).astype(np.float32),
        (rng.normal(0, 0.5, (n, 3)) + [0, 0, 6]).astype(np.float32),
    )

    def identity_fit(keypoints, points_lidar, counts, init, **kw):
        return SimpleNamespace(
            **{f: getattr(init, f) for f in BodyParams.FIELDS},
            residuals={},
        )

    rows = TrackRows(
        track_id,
        position,
        np.zeros((n, 17, 3), np.float32),
        np.zeros((0, 3), np.float32),
        np.zeros(n, np.int64),
        K,
        T_CL,
        poses,
        np.arange(4) * 0.2,
    )
    settings = FitSettings(warm_start=True, shared_shape=False, batch_persons=2)
    res = fit_tracks(
        rows,
        identity_fit,
        model,
        est,
        settings,
        InitLidarSettings(),
        FlipSettings(enabled=False),
        RefineSettings(enabled=False),
    )
    assert res.warm.tolist() == [False, False, True, False, True, False]
    world = {}
    for r in range(n):
        T_world_from_cam = poses[position[r]] @ np.linalg.inv(T_CL)
        w = reframe_params(model, res.params.take(slice(r, r + 1)), T_world_from_cam)
        world[r] = _posed(model, w)[0][0]
    # track 1: frames 1 and 2 start from frame 0's body (the same world pose, to float32)
    assert np.abs(world[2] - world[0]).max() < 1e-4 and np.abs(world[4] - world[0]).max() < 1e-4
    # track 2 (new) and track 3 after a gap: their own estimates
    for r in (3, 5):
        np.testing.assert_array_equal(res.params.betas[r], est.betas[r])
    assert np.abs(world[5] - world[1]).max() > 0.05


def test_a_unit_of_several_threads_runs_torch_on_one():
    """limit_threads sizes BLAS / OpenMP to the unit's share but torch to one thread, also in a
    fresh thread (the thread runner's): torch's pool is the OpenMP runtime threadpoolctl limits,
    so the order of the two decides (a 2-thread unit ran the fit on 2 torch threads)."""
    import threading

    from flows.pipeline.parallel import limit_threads

    seen = {}

    def unit():
        limit_threads(2)
        seen["torch"] = torch.get_num_threads()

    t = threading.Thread(target=unit)
    t.start()
    t.join()
    assert seen["torch"] == 1


def test_gaps_at_frames_detect_left_out_are_not_filled():
    """Regression (issue 41): the gap filler read the sweep of a frame the detect stage had left
    out (a cut or NaN sweep), so one bad frame failed and withdrew its whole sequence."""
    gaps = find_gaps(np.ones(3, int), np.array([0, 2, 5]), np.arange(6) * 0.2, max_gap_frames=2)
    assert gaps.position.tolist() == [1, 3, 4]
    usable = gaps.only([0, 2, 3, 5])  # frames 1 and 4 were left out by detect
    assert usable.position.tolist() == [3] and usable.before.tolist() == [1]
    assert usable.after.tolist() == [2] and len(gaps.only([])) == 0
