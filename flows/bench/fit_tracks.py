"""Benchmark of the fit along tracks: simulated people walking (or standing) in front of a moving
robot, seen at the sequence rate by a camera and a co-located Ouster-style LiDAR, fitted

- frame by frame (each detection cold from its start, keypoints as detected: the fit before
  issue 29), and
- along their tracks (tasks/fit/track_fit.py: swaps decided, warm starts, one shape per track,
  the temporal refinement),

from the oracle's starts (truth with monocular-like errors) or the weight-free ones
(``--init lidar-keypoints``). Optionally the keypoints of back views are mirrored left / right
as BlazePose does (``--swap-back-views P``: with probability P per track seen from behind).
Reports MPJPE / PA-MPJPE (mm), the acceleration error of joints and root (mm/frame^2 and
m/s^2), the per-track shape spread, the swaps decided (and how many right), and the CPU
seconds per person-fit of each method, measured in the same process one after the other.

    mobileocc bench fit-tracks --tracks 12 --frames 10 [--init lidar-keypoints] [--set fit.x=y]
"""

from __future__ import annotations

import dataclasses
import json
import time


def simulate_tracks(
    model,
    tracks: int,
    frames: int,
    rate_hz: float,
    sensor: str,
    seed: int,
    swap_back_views: float = 0.0,
    robot_speed_mps: float = 1.0,
    standing_share: float = 0.2,
    keypoint_noise_px: float = 3.0,
):
    """People along straight tracks in front of a robot driving forwards; returns a dict of
    arrays: rows (track_id, position), per row truth (cam frame BodyParams), joints and
    vertices (cam frame), keypoints (mirrored on swapped back views), points (LiDAR frame),
    counts, swapped (R,) bool; per frame T_world_from_lidar, stamps_s; K, T_cam_from_lidar."""
    import numpy as np

    from tasks.body.params import BodyParams
    from tasks.body.poses import standing_pose
    from tasks.fit.init_lidar import mirrored
    from tasks.fit.lidar_sim import (
        R_CAM_FROM_LIDAR,
        SENSORS,
        observe_bodies,
        walking_track_params,
    )
    from tasks.fit.reframe import reframe_params

    rng = np.random.default_rng(seed)
    K = np.array([[1000.0, 0, 960.0], [0, 1000.0, 540.0], [0, 0, 1]])
    T_cl = np.eye(4)
    T_cl[:3, :3] = R_CAM_FROM_LIDAR
    stamps = np.arange(frames) / rate_hz
    T_wl = np.tile(np.eye(4), (frames, 1, 1))
    T_wl[:, 0, 3] = robot_speed_mps * stamps  # the robot drives along its x (forwards)
    parts = {k: [] for k in ("track_id", "position", "swapped")}
    truth_parts, obs_parts = [], []
    for tid in range(1, tracks + 1):
        for _ in range(50):  # draw until the person stays in view
            standing = rng.random() < standing_share
            speed = 0.0 if standing else rng.uniform(0.8, 1.5)
            heading = rng.uniform(-np.pi, np.pi)
            start = np.array(
                [rng.uniform(-3.0, 3.0), rng.uniform(1.0, 1.6), rng.uniform(4.0, 11.0)]
            )
            params = walking_track_params(
                model,
                rng.normal(0.0, 0.8, 10).clip(-2, 2),
                start,
                heading,
                speed,
                frames,
                rate_hz,
                rng.random(),
                standing_pose(rng) if standing else None,
            )
            # frame 0's camera is the world camera; frame p's moved with the robot
            cam = [
                reframe_params(
                    model,
                    params.take(slice(p, p + 1)),
                    T_cl @ np.linalg.inv(T_wl[p]) @ T_wl[0] @ np.linalg.inv(T_cl),
                )
                for p in range(frames)
            ]
            cam = BodyParams(
                *(np.concatenate([getattr(c, f) for c in cam]) for f in BodyParams.FIELDS)
            )
            z, x = cam.transl[:, 2], cam.transl[:, 0]
            if (z > 3.0).all() and (np.abs(x / z) < 0.45).all() and (z < 13.0).all():
                break
        obs = observe_bodies(
            model,
            cam.betas,
            cam.global_orient,
            cam.body_pose,
            cam.transl,
            SENSORS[sensor],
            rng,
            K,
            keypoint_noise_px=keypoint_noise_px,
            max_points=1024,
        )
        # seen from behind: facing away from the camera
        facing = np.array([np.sin(heading), 0.0, np.cos(heading)])
        view = obs.joints[:, 0] / np.linalg.norm(obs.joints[:, 0], axis=1, keepdims=True)
        back = view @ facing > np.cos(np.radians(60.0))
        swap = back & (rng.random() < swap_back_views)
        kp = np.where(swap[:, None, None], mirrored(obs.keypoints), obs.keypoints)
        parts["track_id"].append(np.full(frames, tid))
        parts["position"].append(np.arange(frames))
        parts["swapped"].append(swap)
        truth_parts.append(cam)
        obs_parts.append(dataclasses.replace(obs, keypoints=kp))
    cat = np.concatenate
    mask = cat([o.point_mask for o in obs_parts])
    pts = cat([o.points_lidar for o in obs_parts])
    return {
        "track_id": cat(parts["track_id"]).astype(np.int64),
        "position": cat(parts["position"]).astype(np.int64),
        "swapped": cat(parts["swapped"]),
        "truth": BodyParams(
            *(cat([getattr(t, f) for t in truth_parts]) for f in BodyParams.FIELDS)
        ),
        "joints": cat([o.joints for o in obs_parts]),
        "vertices": cat([o.vertices for o in obs_parts]),
        "keypoints": cat([o.keypoints for o in obs_parts]),
        "points_lidar": pts[mask],
        "counts": mask.sum(1).astype(np.int64),
        "T_world_from_lidar": T_wl,
        "stamps_s": stamps,
        "K": K,
        "T_cam_from_lidar": T_cl,
    }


def _metrics(model, sim: dict, params, rate_hz: float) -> dict:
    import numpy as np
    import torch

    from tasks.body.params import BodyParams
    from tasks.fit.metrics import pa_mpjpe_mm
    from tasks.fit.refine import acceleration_error
    from tasks.fit.shape import shape_spread

    with torch.no_grad():
        o = model(*(torch.as_tensor(getattr(params, f)) for f in BodyParams.FIELDS))
    J = o.joints.double().numpy()
    G = sim["joints"].astype(np.float64)
    T_wc = sim["T_world_from_lidar"][sim["position"]] @ np.linalg.inv(sim["T_cam_from_lidar"])
    to_world = lambda X: np.einsum("rij,rkj->rki", T_wc[:, :3, :3], X) + T_wc[:, None, :3, 3]
    Jw, Gw = to_world(J), to_world(G)
    stamps = sim["stamps_s"][sim["position"]]
    acc_j, ok = acceleration_error(sim["track_id"], stamps, Jw, Gw)
    acc_r, _ = acceleration_error(sim["track_id"], stamps, Jw[:, :1], Gw[:, :1])
    step2 = (1.0 / rate_hz) ** 2
    mpjpe = np.linalg.norm(J - G, axis=-1).mean(1) * 1000
    return {
        "mpjpe_mm": float(mpjpe.mean()),
        "pa_mpjpe_mm": float(pa_mpjpe_mm(J, G).mean()),
        "accel_joints_m_s2": float(np.nanmean(acc_j)),
        "accel_joints_mm_frame2": float(np.nanmean(acc_j) * step2 * 1000),
        "accel_root_m_s2": float(np.nanmean(acc_r)),
        "accel_root_mm_frame2": float(np.nanmean(acc_r) * step2 * 1000),
        "shape_spread": shape_spread(sim["track_id"], params.betas),
    }


def bench_tracks(
    tracks: int,
    frames: int,
    weights,
    settings,
    start_settings,
    flip_settings,
    refine_settings,
    init: str = "oracle",
    rate_hz: float = 5.0,
    sensor: str = "ouster-128",
    seed: int = 0,
    swap_back_views: float = 0.0,
    methods=("per-frame", "tracks"),
) -> dict:
    """Run the benchmark; returns {method: metrics} (see the module docstring)."""
    import numpy as np

    from tasks.body.prior import GMMPosePrior, generate_pose_prior
    from tasks.body.procedural import default_body_model
    from tasks.fit.init_oracle import oracle_initial_estimate
    from tasks.fit.track_fit import TrackRows, fit_tracks, persons_fit

    model = default_body_model()
    g = generate_pose_prior()
    prior = GMMPosePrior(g["means"], g["covars"], g["weights"])
    sim = simulate_tracks(model, tracks, frames, rate_hz, sensor, seed, swap_back_views)
    rows = TrackRows(
        sim["track_id"],
        sim["position"],
        sim["keypoints"],
        sim["points_lidar"],
        sim["counts"],
        sim["K"],
        sim["T_cam_from_lidar"],
        sim["T_world_from_lidar"],
        sim["stamps_s"],
    )
    rng = np.random.default_rng(seed + 1)
    oracle = oracle_initial_estimate(model, sim["truth"], rng)
    fit = persons_fit(model, prior, sim["K"], sim["T_cam_from_lidar"], weights, settings)
    start = oracle if init == "oracle" else None
    out: dict = {"rows": len(rows), "swapped_rows": int(sim["swapped"].sum())}
    for method in methods:
        s, fl, rf = settings, flip_settings, refine_settings
        if method == "per-frame":  # the fit before issue 29: each row alone, as detected
            s = dataclasses.replace(settings, warm_start=False, shared_shape=False)
            fl = dataclasses.replace(flip_settings, enabled=False)
            rf = dataclasses.replace(refine_settings, enabled=False)
        t0 = time.process_time()
        res = fit_tracks(rows, fit, model, start, s, start_settings, fl, rf)
        cpu = time.process_time() - t0
        m = _metrics(model, sim, res.params, rate_hz)
        m["cpu_s_per_fit"] = cpu / max(len(rows), 1)
        m["fits_per_cpu_s"] = len(rows) / max(cpu, 1e-9)
        m["mean_steps"] = float(np.mean(res.residuals.get("steps", [0])))
        if res.flips is not None:
            m["flips"] = res.flips.counts()
            m["flips_right"] = int((res.flips.mirrored == sim["swapped"]).sum())
        out[method] = m
        print(
            method,
            json.dumps({k: (round(v, 3) if isinstance(v, float) else v) for k, v in m.items()}),
            flush=True,
        )
    return out
