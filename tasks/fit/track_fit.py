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

from dataclasses import dataclass, field

import numpy as np

from tasks.fit.flips import FlipDecision, FlipSettings, decide_flips
from tasks.fit.init_lidar import (
    FacingCosts,
    InitLidarSettings,
    facing_costs,
    initial_bodies,
    mirrored,
)
from tasks.fit.init_oracle import BodyParams
from tasks.fit.refine import RefineSettings, refine_tracks
from tasks.fit.reframe import reframe_params
from tasks.fit.shape import track_shapes, with_shape

_FIELDS = ("betas", "global_orient", "body_pose", "transl")


@dataclass(frozen=True)
class TrackSettings:
    """How the fits of a track are made beyond one frame's fit (tasks.fit.settings.FitSettings).

    warm_start: start a row from its track's fit in the previous frame; warm_iterations: Adam
    steps of such a warm fit (a cold fit takes FitSettings.iterations). shared_shape: one shape
    per track. init / flips / refine: the weight-free start, the swap decision, the refinement.
    """

    warm_start: bool = True
    warm_iterations: int = 30
    shared_shape: bool = True
    init: InitLidarSettings = field(default_factory=InitLidarSettings)
    flips: FlipSettings = field(default_factory=FlipSettings)
    refine: RefineSettings = field(default_factory=RefineSettings)


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
    """Per row: params (cam frame bodies), keypoints (R, 17, 3) the ones fitted (mirrored where
    decided), flips (FlipDecision or None), warm (R,) bool: started from the previous frame's fit,
    residuals: dict of (R,) float64 (the last fit's terms, 'steps' of the per-frame fit summed
    with the refinement's), shapes: {track id: betas (10,)}."""

    params: BodyParams
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
    cold_iterations: int,
    batch_persons: int,
    settings: TrackSettings = TrackSettings(),
    run=None,
) -> TrackFitResult:
    """Fit every row of a sequence (steps 1-6 of the module docstring).

    fit: callable (keypoints (k, 17, 3), points_lidar (n, 3), counts (k,), init BodyParams, *,
    iterations, frozen, coupling, use_icp, learning_rate) -> tasks.fit.optimize.FitResult: the
    per-person fit (tasks.fit.optimize.fit_persons) with the camera, the objective's weights and
    the fit settings bound (learning_rate None: the settings'). model: the body model. init:
    the provider's starts (cam frame, one per row) or None (weight-free). run: maps a function
    over a list of argument tuples (the stage's fan-out; default: in order, here)."""
    s = settings
    run = run or (lambda f, args: [f(*a) for a in args])
    R = len(rows)
    kp = np.asarray(rows.keypoints, np.float64)
    T_wc = rows.T_world_from_cam()
    R_cw = np.transpose(T_wc[:, :3, :3], (0, 2, 1))
    up_cam = R_cw @ np.array([0.0, 0.0, 1.0])
    pts_cam = _points_cam(rows)
    costs: FacingCosts | None = None
    if init is None or s.flips.enabled:
        costs = _facing_costs(model, kp, rows, pts_cam, up_cam, s.init, batch_persons)
    decision = None
    heading = None if costs is None else costs.best()
    if costs is not None and s.flips.enabled:
        decision = decide_flips(
            rows.track_id,
            rows.stamps_s[rows.position],
            _world_positions(rows),
            costs.facing_cam,
            costs.cost,
            T_wc[:, :3, :3],
            s.flips,
        )
        heading = decision.heading
        kp = np.where(decision.mirrored[:, None, None], mirrored(kp), kp)
    if init is None:
        init = _weight_free(model, costs, heading, kp, rows, pts_cam, up_cam, s.init, batch_persons)
    params, residuals, warm = _per_frame(
        rows, fit, model, init, kp, cold_iterations, batch_persons, s, run
    )
    shapes: dict = {}
    if s.shared_shape and R:
        betas, shapes = track_shapes(rows.track_id, params.betas, rows.counts)
        params = BodyParams(
            betas,
            params.global_orient,
            params.body_pose,
            with_shape(model, params.betas, params.transl, betas),
        )
    if s.refine.enabled and R:
        step = _nominal_step(rows.stamps_s)

        def refit(sel, start, coupling):
            pts, counts = rows.points_of(sel)
            return fit(
                kp[sel],
                pts,
                counts,
                start,
                iterations=s.refine.iterations,
                frozen=("betas",),
                coupling=coupling,
                use_icp=False,
                learning_rate=s.refine.learning_rate,
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
            s.refine,
        )
        res2["steps"] = steps + res2.get("steps", 0.0)
        res2["icp_fitness"] = residuals.get("icp_fitness", np.zeros(R))
        residuals = res2
    return TrackFitResult(params, kp.astype(np.float32), decision, warm, residuals, shapes)


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


def _per_frame(rows: TrackRows, fit, model, init: BodyParams, kp, cold_iterations, batch, s, run):
    """Step 4: the per-frame fits. Returns params, residuals (dict of (R,)), warm (R,) bool."""
    R = len(rows)
    pos = np.asarray(rows.position)
    ids = np.asarray(rows.track_id)
    out = {k: np.array(getattr(init, k), np.float32, copy=True) for k in _FIELDS}
    residuals: dict[str, np.ndarray] = {}
    warm = np.zeros(R, bool)
    if s.warm_start:
        prev = _previous_frame_row(ids, pos)
        warm = prev >= 0
    cold = np.flatnonzero(~warm)
    jobs = [cold[a : a + batch] for a in range(0, len(cold), batch)]

    def job(sel, start, its):
        pts, counts = rows.points_of(sel)
        return fit(kp[sel], pts, counts, start, iterations=its)

    def store(sel, result):
        for k in _FIELDS:
            out[k][sel] = getattr(result, k)
        for k, v in result.residuals.items():
            residuals.setdefault(k, np.zeros(R))[sel] = np.asarray(v)

    for sel, result in zip(
        jobs, run(job, [(sel, init.take(sel), cold_iterations) for sel in jobs])
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
            before = BodyParams(*(out[k][prev[here]] for k in _FIELDS))
            start = reframe_params(model, before, T)
            args = [
                (here[a : a + batch], start.take(slice(a, a + batch)), s.warm_iterations)
                for a in range(0, len(here), batch)
            ]
            for (sel, _, _), result in zip(args, run(job, args)):
                store(sel, result)
    return BodyParams(*(out[k] for k in _FIELDS)), residuals, warm


def _previous_frame_row(ids: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """(R,) the row of the same track in the previous frame position, -1 if none."""
    where = {(int(t), int(p)): r for r, (t, p) in enumerate(zip(ids, pos))}
    return np.array([where.get((int(t), int(p) - 1), -1) for t, p in zip(ids, pos)], np.int64)


def _nominal_step(stamps_s: np.ndarray) -> float:
    d = np.diff(np.asarray(stamps_s, np.float64))
    d = d[d > 0]
    return float(np.median(d)) if len(d) else 0.2


def persons_fit(
    model,
    prior,
    K,
    T_cam_from_lidar,
    weights,
    learning_rate: float,
    nn_every: int,
    chamfer_vertex_max_m: float | None,
    converge_rtol: float | None,
    device: str = "cpu",
    seed: int = 0,
):
    """The fit callable :func:`fit_tracks` takes: tasks.fit.optimize.fit_persons with one
    camera, the objective's weights and the fit settings bound."""
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
        learning_rate=None,
    ):
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
            iterations=iterations,
            lr=learning_rate if learning_rate is not None else lr0,
            device=device,
            seed=seed,
            use_icp=use_icp,
            nn_every=nn_every,
            chamfer_vertex_max_m=chamfer_vertex_max_m,
            converge_rtol=converge_rtol,
            frozen=frozen,
            coupling=coupling,
        )

    lr0 = learning_rate
    return fit
