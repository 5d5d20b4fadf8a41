"""fit: a body-model fit per tracked person and frame, fused with its LiDAR points.

Rows of the track product are fitted in batches of ``fit.batch_persons`` (Adam over the paper's
six-term objective, tasks/fit/optimize.py), fanned out to Dask (routed to ``GPU=1`` workers when
``dask.gpu_fit``). The initial estimate comes from the ``oracle`` (ground truth perturbed like a
monocular regressor; synthetic data) or ``precomputed`` CLIFF outputs
(``<fit.init_dir>/<sequence>/cliff.parquet``, storage/PERCEPTION_FORMAT.md), keyed by (frame,
det_index); a tracked detection without an estimate, or with fewer than ``fit.min_points`` LiDAR
points, is not fitted, and a fit whose root moved more than ``fit.max_shift_m`` from its initial
estimate is dropped (it latched onto someone else's points or floated off); all are counted in
the summary.

Product ``bodies.npz`` (one row per fitted person-frame, LiDAR frame of that frame): frame (R,)
int64 raw frame, track_id (R,) int64, det_index (R,), betas (R, 10), global_orient (R, 3),
body_pose (R, 69), transl (R, 3) float32, velocity_base (R, 2) float32 m/s (from the track's
pelvis motion, base frame), loss_j / loss_3d / loss_total (R,) float32 final term values,
num_points (R,) int64, shift_m (R,) float32 how far the fit moved the root from its initial
estimate.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import torch

from configs.schema import Config
from flows.parallel import fan_out
from flows.plan import open_sequence
from flows.stages.common import StageContext, frame_rng
from storage.cliff_files import cliff_path, read_cliff_estimates
from storage.body_files import (load_body_model, load_pose_prior, save_body_model_npz,
                                save_pose_prior_pkl)
from storage.gt import read_frame_gt
from storage.intermediate import read_product, write_product
from tasks.body.model import BodyModel
from tasks.body.prior import GMMPosePrior, generate_pose_prior
from tasks.body.procedural import generate_body_model
from tasks.fit.init_oracle import BodyParams, cliff_to_params, oracle_initial_estimate
from tasks.fit.losses import FitWeights
from tasks.fit.optimize import fit_persons
from tasks.fit.reframe import reframe_params
from tasks.track.velocity import track_velocities


#: our procedural stand-ins are generated once per output store and saved in the official formats
PROCEDURAL_MODEL = "procedural_smpl_v1.npz"
PROCEDURAL_PRIOR = "procedural_gmm_08_v1.pkl"


def _procedural_file(config: Config, name: str, make, save) -> Path:
    """OUT/.cache/<name>: our procedural stand-in, made and saved once per output store."""
    path = Path(config.output.root) / ".cache" / name
    if not path.exists():
        save(path, make())
    return path


@functools.lru_cache(maxsize=4)
def _load_model(path: str) -> BodyModel:
    return BodyModel(load_body_model(path))


@functools.lru_cache(maxsize=4)
def _load_prior(path: str) -> GMMPosePrior:
    p = load_pose_prior(path)
    return GMMPosePrior(p["means"], p["covars"], p["weights"])


def body_model(config: Config) -> BodyModel:
    """The user's SMPL file, or our procedural model in the same format."""
    path = config.fit.body_model_path or _procedural_file(
        config, PROCEDURAL_MODEL, generate_body_model, save_body_model_npz)
    return _load_model(str(path))


def pose_prior(config: Config) -> GMMPosePrior:
    """The user's gmm_08.pkl, or our generated prior in the same format."""
    path = config.fit.pose_prior_path or _procedural_file(
        config, PROCEDURAL_PRIOR, generate_pose_prior, save_pose_prior_pkl)
    return _load_prior(str(path))


def fit_weights(config: Config) -> FitWeights:
    w = config.fit.weights
    return FitWeights(rho_px=w.rho, lambda_theta=w.lambda_theta, lambda_a=w.lambda_a,
                      lambda_beta=w.lambda_beta, lambda_3d=w.lambda_3d, lambda_occ=w.lambda_occ,
                      w=w.w, j_conf=w.j_conf, conf_power=config.fit.confidence_power,
                      square_lambdas=config.fit.squared_weights)


def _device(config: Config) -> str:
    if config.fit.device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return config.fit.device


def oracle_estimates(config: Config, sequence: str, rows: list[int], tracks: dict) -> BodyParams:
    """The oracle's initial estimates (cam frame) of some rows of the track product: their
    ground-truth bodies perturbed like a monocular regressor (one generator per batch)."""
    seq = open_sequence(config, sequence)
    T_cam = seq.info.calibration.cameras[config.dataset.camera].T_cam_from_lidar
    truths = []
    for r in rows:
        gt = read_frame_gt(seq.root, int(sequence), int(tracks["frame"][r]))
        g = [int(tracks["gt_index"][r])]
        truths.append(BodyParams(gt.betas[g], gt.global_orient[g], gt.body_pose[g], gt.transl[g]))
    truth = BodyParams(*(np.concatenate([getattr(t, f) for t in truths]) for f in
                         ("betas", "global_orient", "body_pose", "transl")))
    return oracle_initial_estimate(body_model(config), reframe_params(body_model(config), truth, T_cam),
                                   frame_rng(config.fit.seed, sequence, rows[0], 3))


def precomputed_estimates(config: Config, sequence: str, tracks: dict) -> tuple[np.ndarray, BodyParams]:
    """Rows of the track product that have a precomputed CLIFF estimate, and those estimates
    (cam frame, converted with the sequence's calibrated K)."""
    K = open_sequence(config, sequence).info.calibration.cameras[config.dataset.camera].K
    est = read_cliff_estimates(cliff_path(config.fit.init_dir, sequence))
    where = {key: i for i, key in enumerate(zip(est["frame"].tolist(), est["det_index"].tolist()))}
    keys = zip(tracks["frame"].tolist(), tracks["det_index"].tolist())
    pairs = [(r, where[k]) for r, k in enumerate(keys) if k in where]
    rows = np.array([r for r, _ in pairs], np.int64)
    i = np.array([j for _, j in pairs], np.int64)
    params = cliff_to_params(est["rotmats"][i].reshape(-1, 24, 3, 3), est["betas"][i].reshape(-1, 10),
                             est["cam_crop"][i].reshape(-1, 3), est["bbox_center"][i].reshape(-1, 2),
                             est["bbox_size"][i], K, est["transl"][i].reshape(-1, 3), est["has_transl"][i])
    return rows, params


def fit_batch(config: Config, sequence: str, rows: list[int], tracks: dict, init: BodyParams | None = None) -> dict:
    """Fit some rows of the track product from ``init`` (cam frame; None = the oracle's
    estimates); returns their parameters in the LiDAR frame."""
    seq = open_sequence(config, sequence)
    cam = seq.info.calibration.cameras[config.dataset.camera]
    model = body_model(config)
    T_cam = cam.T_cam_from_lidar
    points, sweeps = [], {}
    # the points in the image only: the visibility filter knows only what the camera shows
    in_image = tracks["points_in_image"]
    for r in rows:
        raw = int(tracks["frame"][r])
        if raw not in sweeps:
            sweeps[raw] = seq.frame(seq.info.frame_indices.index(raw)).points_lidar
        lo = tracks["points_offsets"][r]
        points.append(sweeps[raw][tracks["points_index"][lo:lo + in_image[r]]])
    if init is None:
        init = oracle_estimates(config, sequence, rows, tracks)
    result = fit_persons(model, pose_prior(config), init, tracks["keypoints"][rows], cam.K, T_cam,
                         np.concatenate(points), [len(p) for p in points], weights=fit_weights(config),
                         iterations=config.fit.iterations,
                         lr=config.fit.learning_rate, device=_device(config), seed=config.fit.seed,
                         nn_every=config.fit.nn_every, converge_rtol=config.fit.converge_rtol,
                         chamfer_vertex_max_m=config.fit.chamfer_vertex_max_m)
    T_lidar_from_cam = np.linalg.inv(T_cam)
    lidar = reframe_params(model, result.params(), T_lidar_from_cam)
    pelvis = result.joints[:, 0].astype(np.float64) @ T_lidar_from_cam[:3, :3].T + T_lidar_from_cam[:3, 3]
    res = result.residuals
    return {"rows": np.asarray(rows, np.int64), "betas": lidar.betas,
            "global_orient": lidar.global_orient, "body_pose": lidar.body_pose,
            "transl": lidar.transl, "pelvis_lidar": pelvis,
            "loss_j": np.asarray(res["L_J"], np.float32), "loss_3d": np.asarray(res["L_3D"], np.float32),
            "loss_total": np.asarray(res["total"], np.float32),
            "num_points": np.array([len(p) for p in points], np.int64),
            "shift_m": np.linalg.norm(np.asarray(result.transl, np.float64) - np.asarray(init.transl, np.float64),
                                      axis=1)}


def _fit_warm_started(cfg: Config, sequence: str, tracks: dict, rows: np.ndarray, est: BodyParams | None,
                      info, resources) -> list[dict]:
    """Fit frame by frame; a track fitted in the previous frame starts from that fit, moved into
    this frame's camera frame by the ego-motion (beyond the paper: fit.warm_start), instead of
    the provider's estimate (est: the precomputed estimates of ``rows``; None = the oracle)."""
    model = body_model(cfg)
    T_cam = info.calibration.cameras[cfg.dataset.camera].T_cam_from_lidar
    pos = {raw: k for k, raw in enumerate(info.frame_indices)}
    at_row = {int(r): k for k, r in enumerate(rows)}
    last: dict[int, tuple[int, BodyParams]] = {}  # track -> (frame position, fit in its LiDAR frame)
    parts: list[dict] = []
    frames = tracks["frame"][rows]
    for f in np.unique(frames):
        p = pos[int(f)]
        args = []
        for a in range(0, int((frames == f).sum()), cfg.fit.batch_persons):
            batch = rows[frames == f][a:a + cfg.fit.batch_persons].tolist()
            init = (oracle_estimates(cfg, sequence, batch, tracks) if est is None
                    else est.take([at_row[r] for r in batch]))
            fields = {k: getattr(init, k).copy() for k in ("betas", "global_orient", "body_pose", "transl")}
            for k, r in enumerate(batch):
                prev = last.get(int(tracks["track_id"][r]))
                if prev is None or prev[0] != p - 1:
                    continue
                T = T_cam @ np.linalg.inv(info.poses[p]) @ info.poses[prev[0]]  # cam(now) <- lidar(prev)
                moved = reframe_params(model, prev[1], T)
                for key in fields:
                    fields[key][k] = getattr(moved, key)[0]
            args.append((cfg, sequence, batch, tracks, BodyParams(**fields)))
        for out in fan_out(fit_batch, args, resources):
            parts.append(out)
            for k, r in enumerate(out["rows"]):
                last[int(tracks["track_id"][r])] = (p, BodyParams(
                    out["betas"][k:k + 1], out["global_orient"][k:k + 1], out["body_pose"][k:k + 1],
                    out["transl"][k:k + 1]))
    return parts


_FIELDS = {"rows": (0,), "betas": (0, 10), "global_orient": (0, 3), "body_pose": (0, 69),
           "transl": (0, 3), "pelvis_lidar": (0, 3), "loss_j": (0,), "loss_3d": (0,),
           "loss_total": (0,), "num_points": (0,), "shift_m": (0,)}


def drop_far_fits(out: dict, max_shift_m: float | None) -> tuple[dict, int]:
    """The fit arrays ``out`` (one row per fit) without the rows whose ``shift_m`` exceeds
    ``max_shift_m`` (None keeps all), and how many were dropped."""
    if max_shift_m is None:
        return out, 0
    keep = np.asarray(out["shift_m"]) <= max_shift_m
    return {k: np.asarray(v)[keep] for k, v in out.items()}, int((~keep).sum())


def run_fit(ctx: StageContext) -> dict:
    cfg = ctx.config
    tracks = read_product(ctx.upstream["track"], "tracks")
    rows = np.arange(len(tracks["track_id"]))
    step = cfg.fit.batch_persons
    if cfg.fit.init_provider == "oracle":  # the oracle has no estimate for a false positive
        rows, est = rows[tracks["gt_index"] >= 0], None
    else:
        rows, est = precomputed_estimates(cfg, ctx.sequence, tracks)
    few = tracks["points_in_image"][rows] < cfg.fit.min_points
    rows = rows[~few]
    if est is None:
        inits = [None] * len(range(0, len(rows), step))
    else:
        est = est.take(np.flatnonzero(~few))
        inits = [est.take(slice(a, a + step)) for a in range(0, len(rows), step)]
    batches = [rows[a:a + step].tolist() for a in range(0, len(rows), step)]
    resources = {"GPU": 1} if cfg.dask.gpu_fit else None
    if cfg.fit.warm_start:
        parts = _fit_warm_started(cfg, ctx.sequence, tracks, rows, est, ctx.open().info, resources)
    else:
        parts = fan_out(fit_batch, [(cfg, ctx.sequence, b, tracks, i) for b, i in zip(batches, inits)], resources)
    out = {k: (np.concatenate([p[k] for p in parts]) if parts else np.zeros(shape))
           for k, shape in _FIELDS.items()}
    out, far = drop_far_fits(out, cfg.fit.max_shift_m)
    r = out["rows"].astype(np.int64)
    info = ctx.open().info
    pos = {raw: k for k, raw in enumerate(info.frame_indices)}
    at = np.array([pos[int(f)] for f in tracks["frame"][r]], np.int64)
    T_w = info.poses[at].reshape(-1, 4, 4)
    pelvis_world = np.einsum("rij,rj->ri", T_w[:, :3, :3], out["pelvis_lidar"]) + T_w[:, :3, 3]
    v_world = track_velocities(tracks["track_id"][r], info.stamps_ns[at] * 1e-9, pelvis_world)
    R_base_from_world = info.calibration.T_base_from_lidar[:3, :3] @ np.transpose(T_w[:, :3, :3], (0, 2, 1))
    v_base = np.einsum("rij,rj->ri", R_base_from_world, v_world)[:, :2]
    f32 = np.float32
    write_product(ctx.out_dir, "bodies", {
        "frame": tracks["frame"][r].astype(np.int64), "track_id": tracks["track_id"][r].astype(np.int64),
        "det_index": tracks["det_index"][r].astype(np.int64), "betas": out["betas"].astype(f32),
        "global_orient": out["global_orient"].astype(f32), "body_pose": out["body_pose"].astype(f32),
        "transl": out["transl"].astype(f32), "velocity_base": v_base.astype(f32),
        "loss_j": out["loss_j"].astype(f32), "loss_3d": out["loss_3d"].astype(f32),
        "loss_total": out["loss_total"].astype(f32), "num_points": out["num_points"].astype(np.int64),
        "shift_m": out["shift_m"].astype(f32)})
    return {"implemented": True, "fitted": int(len(r)), "batches": len(batches),
            # oracle: false positives (no ground truth); precomputed: detections without an estimate
            "skipped_without_estimate": int(len(tracks["track_id"]) - len(rows) - int(few.sum())),
            "skipped_few_points": int(few.sum()), "dropped_far_from_estimate": far,
            "device": _device(cfg), "preset": cfg.fit.preset}
