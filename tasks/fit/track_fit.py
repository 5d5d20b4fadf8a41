"""The bodies of a sequence's tracks: starts, left / right swaps, per-frame fits with warm starts,
one shape per track and the temporal refinement, as one kernel (the fit stage and the benchmark
both run it).

Steps (each its own module):
1. facing costs of every detection (tasks/fit/init_lidar.py) when the start is weight-free or
   swaps are decided;
2. left / right swaps decided along each track (tasks/fit/flips.py): the fit then uses the
   chosen keypoints (mirrored where decided so);
3. starts: the provider's estimates, or the weight-free ones (init_lidar) for the chosen
   labelling and heading;
4. per-frame fits (tasks/fit/optimize.py): rows whose track was fitted in the previous frame
   start from that fit moved by the robot's motion (``warm_start``) with ``warm_iterations``
   steps, the others (a track's first frame, after a gap) from their start with ``iterations``;
5. one shape per track (tasks/fit/shape.py), the roots kept in place;
6. the refinement of pose and root translation with an acceleration penalty, the shape held
   (tasks/fit/refine.py).

Frames: rows' bodies are fitted in their frame's camera frame (OpenCV) and returned there.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from tasks.body.params import BodyParams
from tasks.fit.flips import (
    FlipDecision,
    FlipSettings,
    chains_towards,
    decide_flips,
    far_from_start,
)
from tasks.fit.init_lidar import (
    FacingCosts,
    InitLidarSettings,
    facing_costs,
    initial_bodies,
    mirrored,
)
from tasks.fit.refine import RefineSettings, refine_tracks
from tasks.fit.reframe import reframe_params
from tasks.fit.settings import FitSettings
from tasks.fit.shape import track_shapes, with_shape

_FIELDS = BodyParams.FIELDS


@dataclass(frozen=True)
class TrackRows:
    """R detections of one sequence with what the fit needs.

    track_id (R,) int64; position (R,) int64: frame position (index into the per-frame arrays);
    keypoints (R, 17, 3) COCO-17 (u, v, confidence) px as detected; points_lidar (P, 3) the rows'
    LiDAR points one after another (each in its frame's LiDAR frame, m) and counts (R,); K (3,
    3); T_cam_from_lidar (4, 4); T_world_from_lidar (F, 4, 4) and stamps_s (F,) per frame
    position."""

    track_id: np.ndarray
    position: np.ndarray
    keypoints: np.ndarray
    points_lidar: np.ndarray
    counts: np.ndarray
    K: np.ndarray
    T_cam_from_lidar: np.ndarray
    T_world_from_lidar: np.ndarray
    stamps_s: np.ndarray

    def __len__(self) -> int:
        return len(self.track_id)

    def points_of(self, rows) -> tuple[np.ndarray, np.ndarray]:
        """(points (n, 3), counts (k,)) of rows (k,) int64, in that order."""
        ends = np.cumsum(self.counts)
        parts = [self.points_lidar[ends[r] - self.counts[r] : ends[r]] for r in rows]
        pts = np.concatenate(parts) if parts else np.zeros((0, 3), np.float32)
        return pts, self.counts[np.asarray(rows, np.int64)]

    def T_world_from_cam(self) -> np.ndarray:
        """(R, 4, 4) each row's camera in the world."""
        return self.T_world_from_lidar[self.position] @ np.linalg.inv(self.T_cam_from_lidar)


@dataclass(frozen=True)
class TrackFitResult:
    """Per row: params (cam frame bodies), starts (cam frame: the estimates the per-frame fits
    started from, the provider's or the weight-free ones), keypoints (R, 17, 3) the ones fitted
    (mirrored where decided), flips (FlipDecision or None), warm (R,) bool: started from the
    previous frame's fit, residuals: dict of (R,) float64 (the last fit's terms, 'steps' of the
    per-frame fit summed with the refinement's), shapes: {track id: betas (10,)}."""

    params: BodyParams
    starts: BodyParams
    keypoints: np.ndarray
    flips: FlipDecision | None
    warm: np.ndarray
    residuals: dict
    shapes: dict


def fit_tracks(
    rows: TrackRows,
    fit,
    model,
    init: BodyParams | None,
    settings: FitSettings,
    start: InitLidarSettings,
    flips: FlipSettings,
    refine: RefineSettings,
    run=None,
) -> TrackFitResult:
    """Fit every row of a sequence (steps 1-6 of the module docstring).

    fit: callable (keypoints (k, 17, 3), points_lidar (n, 3), counts (k,), init BodyParams, *,
    iterations, frozen, coupling, use_icp, lr, posed, terms) -> tasks.fit.optimize.FitResult: the
    per-person fit (tasks.fit.optimize.fit_persons) with the camera, the objective's weights and
    the fit settings bound (lr None: the settings'). model: the body model. init:
    the provider's starts (cam frame, one per row) or None (weight-free). run: maps a function
    over a list of argument tuples (the stage's fan-out; default: in order, here). settings:
    iterations (a cold fit), warm_start / warm_iterations, shared_shape, batch_persons; start /
    flips / refine: the weight-free start, the swap decision, the refinement."""
    s = settings
    run = run or (lambda f, args: [f(*a) for a in args])
    R = len(rows)
    kp = np.asarray(rows.keypoints, np.float64)
    T_wc = rows.T_world_from_cam()
    R_cw = np.transpose(T_wc[:, :3, :3], (0, 2, 1))
    up_cam = R_cw @ np.array([0.0, 0.0, 1.0])
    pts_cam = _points_cam(rows)
    costs: FacingCosts | None = None
    if init is None or flips.enabled:
        costs = _facing_costs(model, kp, rows, pts_cam, up_cam, start, s.batch_persons)
    decision = None
    heading = None if costs is None else costs.best()
    if costs is not None and flips.enabled:
        decision = decide_flips(
            rows.track_id,
            rows.stamps_s[rows.position],
            _world_positions(rows),
            costs.facing_cam,
            costs.cost,
            T_wc[:, :3, :3],
            flips,
        )
        heading = decision.heading
        kp = np.where(decision.mirrored[:, None, None], mirrored(kp), kp)
        if init is not None and flips.follow_start != "never" and R:
            # the rows the track left undecided (or all): each chain labelled as the start is
            decision, kp = _follow_start(model, init, kp, rows.K, decision, start, flips)
    if init is None:
        init = _weight_free(
            model, costs, heading, kp, rows, pts_cam, up_cam, start, s.batch_persons
        )
    # the refinement's refit gives the rows' final loss terms: the per-frame fits skip theirs
    params, residuals, warm = _per_frame(rows, fit, model, init, kp, s, run, not refine.enabled)
    shapes: dict = {}
    if s.shared_shape and R:
        betas, shapes = track_shapes(rows.track_id, params.betas, rows.counts)
        params = BodyParams(
            betas,
            params.global_orient,
            params.body_pose,
            with_shape(model, params.betas, params.transl, betas),
        )
    if refine.enabled and R:
        step = _nominal_step(rows.stamps_s)

        def refit(sel, start, coupling):
            pts, counts = rows.points_of(sel)
            return fit(
                kp[sel],
                pts,
                counts,
                start,
                iterations=refine.iterations,
                frozen=("betas",),
                coupling=coupling,
                use_icp=False,
                lr=refine.learning_rate,
                posed=False,
            )

        steps = residuals.get("steps", np.zeros(R))
        params, res2 = refine_tracks(
            refit,
            params,
            rows.track_id,
            rows.stamps_s[rows.position],
            rows.position,
            T_wc,
            step,
            refine,
        )
        res2["steps"] = steps + res2.get("steps", 0.0)
        res2["icp_fitness"] = residuals.get("icp_fitness", np.zeros(R))
        residuals = res2
    return TrackFitResult(params, init, kp.astype(np.float32), decision, warm, residuals, shapes)


def _follow_start(model, init: BodyParams, kp, K, decision: FlipDecision, start, flips):
    """tasks.fit.flips.chains_towards the provider's starts projected by K: (decision with
    its chains (R, 3) bool, keypoints)."""
    import torch

    from tasks.fit.losses import project_points
    from tasks.fit.optimize import model_keypoints

    posed = posed_result(model, init, {})
    cam = model_keypoints(
        torch.as_tensor(posed.joints), torch.as_tensor(posed.vertices), model.keypoint_vertex_ids
    )
    uv = project_points(cam.double(), torch.as_tensor(np.asarray(K), dtype=torch.float64)).numpy()
    which = np.ones(len(kp), bool) if flips.follow_start == "always" else ~decision.decided
    kp, chains = chains_towards(kp, uv, which, start.keypoint_min_confidence, flips.start_margin)
    dropped = None
    if flips.start_max_distance is not None:
        kp, dropped = far_from_start(kp, uv, np.ones(len(kp), bool), flips.start_max_distance)
    return dataclasses.replace(decision, chains=chains, dropped=dropped), kp


def posed_result(model, params: BodyParams, residuals: dict, chunk: int = 256):
    """tasks.fit.optimize.FitResult of bodies ``params`` (posed by ``model``, in chunks)."""
    import torch

    from tasks.fit.optimize import FitResult

    verts, joints = [], []
    for a in range(0, len(params), chunk):
        p = params.take(slice(a, a + chunk))
        with torch.no_grad():
            o = model(*(torch.as_tensor(np.asarray(getattr(p, f))) for f in _FIELDS))
        verts.append(o.vertices.numpy())
        joints.append(o.joints.numpy())
    nv = int(model.v_template.shape[0])
    return FitResult(
        *(np.asarray(getattr(params, f), np.float32) for f in _FIELDS),
        np.concatenate(verts) if verts else np.zeros((0, nv, 3), np.float32),
        np.concatenate(joints) if joints else np.zeros((0, 24, 3), np.float32),
        residuals,
    )


def _points_cam(rows: TrackRows) -> np.ndarray:
    T = np.asarray(rows.T_cam_from_lidar, np.float64)
    return np.asarray(rows.points_lidar, np.float64) @ T[:3, :3].T + T[:3, 3]


def _world_positions(rows: TrackRows) -> np.ndarray:
    """(R, 3) the median of each row's LiDAR points in the world (NaN-free: rows without
    points take the mean of their track's others, else 0)."""
    out = np.zeros((len(rows), 3))
    has = np.zeros(len(rows), bool)
    ends = np.cumsum(rows.counts)
    for r, (c, e) in enumerate(zip(rows.counts, ends)):
        if c:
            p = np.median(np.asarray(rows.points_lidar[e - c : e], np.float64), axis=0)
            T = rows.T_world_from_lidar[rows.position[r]]
            out[r] = T[:3, :3] @ p + T[:3, 3]
            has[r] = True
    for tid in np.unique(rows.track_id[~has]):
        mine = rows.track_id == tid
        if (mine & has).any():
            out[mine & ~has] = out[mine & has].mean(0)
    return out


def _facing_costs(model, kp, rows: TrackRows, pts_cam, up_cam, s, batch: int) -> FacingCosts:
    parts = []
    ends = np.cumsum(rows.counts)
    for a in range(0, len(rows), batch):
        sel = np.arange(a, min(len(rows), a + batch))
        lo, hi = ends[sel[0]] - rows.counts[sel[0]], ends[sel[-1]]
        parts.append(
            facing_costs(model, kp[sel], rows.K, pts_cam[lo:hi], rows.counts[sel], up_cam[sel], s)
        )
    if not parts:
        z = np.zeros
        return FacingCosts(
            z((0, s.yaw_candidates, 3)),
            z((0, 2, s.yaw_candidates)),
            z((0, 10), np.float32),
            z(0),
            z(0, bool),
            z(0, bool),
            z((0, 3)),
        )
    return FacingCosts(
        *(np.concatenate([getattr(p, f) for p in parts]) for f in FacingCosts.__dataclass_fields__)
    )


def _weight_free(model, costs, heading, kp, rows, pts_cam, up_cam, s, batch) -> BodyParams:
    parts = []
    ends = np.cumsum(rows.counts)
    for a in range(0, len(rows), batch):
        sel = np.arange(a, min(len(rows), a + batch))
        lo, hi = ends[sel[0]] - rows.counts[sel[0]], ends[sel[-1]]
        c = FacingCosts(*(getattr(costs, f)[sel] for f in FacingCosts.__dataclass_fields__))
        parts.append(
            initial_bodies(
                model,
                c,
                heading[sel],
                kp[sel],
                rows.K,
                pts_cam[lo:hi],
                rows.counts[sel],
                up_cam[sel],
                s,
            )
        )
    if not parts:
        z = np.zeros
        return BodyParams(
            z((0, 10), np.float32),
            z((0, 3), np.float32),
            z((0, 69), np.float32),
            z((0, 3), np.float32),
        )
    return BodyParams(*(np.concatenate([getattr(p, f) for p in parts]) for f in _FIELDS))


def _per_frame(rows: TrackRows, fit, model, init: BodyParams, kp, s: FitSettings, run, terms=True):
    """Step 4: the per-frame fits. Returns params, residuals (dict of (R,); the final loss terms
    only with ``terms``), warm (R,) bool."""
    R, batch = len(rows), s.batch_persons
    pos = np.asarray(rows.position)
    ids = np.asarray(rows.track_id)
    out = {k: np.array(getattr(init, k), np.float32, copy=True) for k in _FIELDS}
    residuals: dict[str, np.ndarray] = {}
    warm = np.zeros(R, bool)
    if s.warm_start:
        prev = _previous_frame_row(ids, pos)
        warm = prev >= 0
    cold = np.flatnonzero(~warm)

    def args(sel, start, its):
        return (fit, kp[sel], *rows.points_of(sel), start, its, terms)

    def store(sel, result):
        for k in _FIELDS:
            out[k][sel] = getattr(result, k)
        for k, v in result.residuals.items():
            residuals.setdefault(k, np.zeros(R))[sel] = np.asarray(v)

    jobs = [cold[a : a + batch] for a in range(0, len(cold), batch)]
    for sel, result in zip(
        jobs, run(_fit_call, [args(j, init.take(j), s.iterations) for j in jobs])
    ):
        store(sel, result)
    if warm.any():
        T_cl = np.asarray(rows.T_cam_from_lidar, np.float64)
        for p in np.unique(pos[warm]):
            here = np.flatnonzero(warm & (pos == p))
            # the previous frame's fit, moved into this frame's camera frame
            T = (
                T_cl
                @ np.linalg.inv(rows.T_world_from_lidar[p])
                @ rows.T_world_from_lidar[p - 1]
                @ np.linalg.inv(T_cl)
            )
            start = reframe_params(model, BodyParams(*(out[k][prev[here]] for k in _FIELDS)), T)
            jobs = [np.arange(a, min(len(here), a + batch)) for a in range(0, len(here), batch)]
            results = run(
                _fit_call, [args(here[j], start.take(j), s.warm_iterations) for j in jobs]
            )
            for j, result in zip(jobs, results):
                store(here[j], result)
    return BodyParams(*(out[k] for k in _FIELDS)), residuals, warm


def _fit_call(fit, keypoints, points_lidar, counts, start, iterations, terms=True):
    """One batch of the per-frame fits (a module-level function: the stage may run it on
    another process); the bodies are posed later (:func:`posed_result`), not here."""
    return fit(
        keypoints, points_lidar, counts, start, iterations=iterations, posed=False, terms=terms
    )


def _previous_frame_row(ids: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """(R,) the row of the same track in the previous frame position, -1 if none."""
    where = {(int(t), int(p)): r for r, (t, p) in enumerate(zip(ids, pos))}
    return np.array([where.get((int(t), int(p) - 1), -1) for t, p in zip(ids, pos)], np.int64)


def _nominal_step(stamps_s: np.ndarray) -> float:
    d = np.diff(np.asarray(stamps_s, np.float64))
    d = d[d > 0]
    return float(np.median(d)) if len(d) else 0.2


def persons_fit(model, prior, K, T_cam_from_lidar, weights, settings: FitSettings):
    """The fit callable :func:`fit_tracks` takes: tasks.fit.optimize.fit_persons with one
    camera, the objective's weights and the fit settings bound (iterations and learning rate
    given per call)."""
    from tasks.fit.optimize import fit_persons

    def fit(
        keypoints,
        points_lidar,
        counts,
        init,
        *,
        iterations,
        frozen=(),
        coupling=None,
        use_icp=True,
        lr=None,
        posed=True,
        terms=True,
    ):
        lr = settings.learning_rate if lr is None else lr
        return fit_persons(
            model,
            prior,
            init,
            keypoints,
            K,
            T_cam_from_lidar,
            points_lidar,
            counts,
            weights,
            dataclasses.replace(settings, iterations=iterations, learning_rate=lr),
            use_icp=use_icp,
            frozen=frozen,
            coupling=coupling,
            posed=posed,
            terms=terms,
        )

    return fit
