"""fit: a body-model fit per tracked person and frame, fused with its LiDAR points, along tracks.

Rows of the track product with an initial estimate (providers: the oracle, precomputed CLIFF
files, a CLIFF export; ``lidar-keypoints`` computes one from the points and keypoints instead)
and at least ``min_points`` LiDAR points in the image are fitted by tasks/fit/track_fit.py: left /
right keypoint swaps decided along each track, per-frame fits (the paper's six-term objective,
tasks/fit/optimize.py; warm-started from the track's previous frame with ``warm_start``) in
batches of ``batch_persons`` fanned out to the cluster (``GPU=1`` workers with
``dask.gpu_fit``), one shape per track, then the temporal refinement of each track (here). Fits
that moved the root more than ``max_shift_m`` from their estimate are dropped; frames a track
coasted over get interpolated bodies (tasks/fit/gaps.py, checked against their sweep);
velocities come from the tracks' pelvis motion (tasks/track/velocity.py). Product:
:class:`storage.products.Bodies`.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from flows.pipeline.inputs import FitInputs, LidarKeypointsInitSpec
from flows.pipeline.parallel import fan_out
from flows.stages.common import StageContext, body_model, detected_positions, pose_prior
from flows.stages.providers import init_provider
from storage.products import Bodies, Tracks
from tasks.body.params import BodyParams
from tasks.fit.batch import concat_point_sets, drop_far_fits, fit_rows
from tasks.fit.gaps import check_body, find_gaps, interpolate_bodies, shifted
from tasks.fit.optimize import torch_device
from tasks.fit.shape import shape_spread
from tasks.fit.track_fit import TrackRows, fit_tracks, persons_fit, posed_result
from tasks.track.velocity import velocities_in_base

_FIELDS = BodyParams.FIELDS


@functools.lru_cache(maxsize=2)
def _tracks(folder: str) -> Tracks:
    return Tracks.read(Path(folder))  # key-named, never rewritten: safe to keep per process


class FitCall:
    """The fit of a batch of persons with this sequence's camera, the stage's weights and
    settings (tasks.fit.track_fit.persons_fit); picklable, so a batch may run on another worker
    (which loads the body model and prior once per process)."""

    def __init__(self, inputs: FitInputs, out_root: Path, K: np.ndarray, T_cam_from_lidar):
        self.inputs, self.out_root, self.K, self.T = inputs, out_root, K, T_cam_from_lidar

    def __call__(self, keypoints, points_lidar, counts, init, **kw):
        i = self.inputs
        fit = persons_fit(
            body_model(i.body, self.out_root),
            pose_prior(i.body, self.out_root),
            self.K,
            self.T,
            i.weights,
            i.settings,
        )
        return fit(keypoints, points_lidar, counts, init, **kw)


def _person_points(seq, tracks: Tracks, rows: np.ndarray, at: dict) -> list[np.ndarray]:
    """Each row's LiDAR points in the image (its frame's LiDAR frame), one sweep read per frame."""
    out: list[np.ndarray] = [np.zeros((0, 3), np.float32)] * len(rows)
    for raw in np.unique(tracks.frame[rows]).tolist():
        sweep = seq.frame(at[raw]).points_lidar
        for k in np.flatnonzero(tracks.frame[rows] == raw):
            out[k] = sweep[tracks.points_of(int(rows[k]), in_image_only=True)]
    return out


def _fitted(
    ctx: StageContext[FitInputs], seq, tracks: Tracks, rows: np.ndarray
) -> tuple[dict, dict]:
    """The fits of ``rows`` (tasks.fit.batch.fit_rows, LiDAR frame) and the track kernel's counts."""
    inp, s = ctx.inputs, ctx.inputs.settings
    cam = seq.info.calibration.cameras[inp.source.camera]
    model = body_model(inp.body, ctx.out_root)
    at = {raw: i for i, raw in enumerate(seq.info.frame_indices)}
    points = _person_points(seq, tracks, rows, at)
    track_rows = TrackRows(
        tracks.track_id[rows],
        np.array([at[int(f)] for f in tracks.frame[rows]], np.int64),
        tracks.keypoints[rows],
        *concat_point_sets(points),
        cam.K,
        cam.T_cam_from_lidar,
        seq.info.poses,
        seq.info.stamps_ns * 1e-9,
    )
    weight_free = isinstance(inp.init, LidarKeypointsInitSpec)
    init = None if weight_free else init_provider(inp.init, seq, model, cam).estimates(tracks, rows)
    resources = {"GPU": 1} if ctx.runtime.gpu_fit else None
    result = fit_tracks(
        track_rows,
        FitCall(inp, ctx.out_root, cam.K, cam.T_cam_from_lidar),
        model,
        init,
        s,
        inp.init_lidar,
        inp.flips,
        inp.refine,
        lambda fn, args: fan_out(fn, args, resources, ctx.runtime.threads),
    )
    out = fit_rows(
        model,
        posed_result(model, result.params, result.residuals),
        result.starts,
        points,
        result.keypoints,
        cam.K,
        cam.T_cam_from_lidar,
        inp.weights.j_conf,
    )
    n = len(rows)
    flips = result.flips.counts() if result.flips is not None else {}
    out.update(
        frame=tracks.frame[rows],
        track_id=tracks.track_id[rows],
        det_index=tracks.det_index[rows],
        position=track_rows.position,
        mirrored=np.zeros(n, bool) if result.flips is None else result.flips.mirrored,
        gap_filled=np.zeros(n, bool),
    )
    return out, {
        **{f"flips_{k}": v for k, v in flips.items()},
        "warm_started": int(result.warm.sum()),
        "shape_spread": shape_spread(out["track_id"], out["betas"]),
    }


def _gap_bodies(ctx: StageContext[FitInputs], seq, out: dict) -> tuple[dict, dict]:
    """Bodies for the frames inside tracks without a kept fit (tasks/fit/gaps.py), as rows like
    ``out``'s; and how many were filled, by the check's outcome."""
    g = ctx.inputs.gaps
    gaps = find_gaps(out["track_id"], out["position"], seq.info.stamps_ns * 1e-9, g.max_gap_frames)
    gaps = gaps.only(detected_positions(ctx, seq))  # a frame detect left out is never read
    counts = {"gap_filled": 0, "gap_dropped_seen_through": 0}
    if not g.enabled or len(gaps) == 0:
        return {}, counts
    model = body_model(ctx.inputs.body, ctx.out_root)
    fits = BodyParams(*(out[k] for k in _FIELDS))
    bodies = interpolate_bodies(model, fits, gaps, seq.info.poses, out["position"])
    posed = posed_result(model, bodies, {})
    checks = [
        check_body(posed.vertices[k], seq.frame(int(p)).points_lidar, g)
        for k, p in enumerate(gaps.position)
    ]
    keep = np.array([c.keep for c in checks])
    counts["gap_filled"] = int(keep.sum())
    counts["gap_dropped_seen_through"] = int((~keep).sum())
    bodies = shifted(model, bodies, np.stack([c.shift for c in checks]))
    pelvis = posed.joints[:, 0].astype(np.float64) + np.stack([c.shift for c in checks])
    G, nan = len(gaps), np.full(len(gaps), np.nan, np.float32)
    rows = {
        **{k: getattr(bodies, k) for k in _FIELDS},
        "pelvis_lidar": pelvis,
        "loss_j": nan,
        "loss_3d": nan,
        "loss_total": nan,
        "chamfer_m": nan,
        "reproj_px": nan,
        "num_points": np.array([c.support for c in checks], np.int64),
        "shift_m": np.linalg.norm(np.stack([c.shift for c in checks]), axis=1).astype(np.float32),
        "frame": np.asarray(seq.info.frame_indices, np.int64)[gaps.position],
        "track_id": gaps.track_id,
        "det_index": np.full(G, -1, np.int64),
        "position": gaps.position,
        "mirrored": np.zeros(G, bool),
        "gap_filled": np.ones(G, bool),
    }
    return {k: np.asarray(v)[keep] for k, v in rows.items()}, counts


def _bodies(seq, out: dict) -> Bodies:
    """The product from the kept rows: velocities from the tracks' pelvis motion."""
    if not out or len(out["frame"]) == 0:
        return Bodies.empty()
    order = np.lexsort((out["track_id"], out["frame"]))
    out = {k: np.asarray(v)[order] for k, v in out.items()}
    at = out.pop("position")
    velocity = velocities_in_base(
        out["track_id"],
        seq.info.stamps_ns[at] * 1e-9,
        out.pop("pelvis_lidar"),
        seq.info.poses[at],
        seq.info.calibration.T_base_from_lidar,
    )
    return Bodies(velocity_base=velocity.astype(np.float32), **out)


def run_fit(ctx: StageContext[FitInputs]) -> dict:
    inp, seq = ctx.inputs, ctx.open()
    s, tracks = inp.settings, _tracks(str(ctx.upstream["track"]))
    cam = seq.info.calibration.cameras[inp.source.camera]
    rows = init_provider(inp.init, seq, body_model(inp.body, ctx.out_root), cam).available(tracks)
    few = tracks.points_in_image[rows] < s.min_points
    rows = rows[~few]
    out, counts = _fitted(ctx, seq, tracks, rows) if len(rows) else ({}, {})
    out, far = drop_far_fits(out, s.max_shift_m) if out else ({}, 0)
    gap_rows, gap_counts = _gap_bodies(ctx, seq, out) if out else ({}, {})
    if gap_rows:
        out = {k: np.concatenate([np.asarray(out[k]), np.asarray(gap_rows[k])]) for k in out}
    bodies = _bodies(seq, out)
    bodies.write(ctx.out_dir)
    return {
        "implemented": True,
        "fitted": int((~bodies.gap_filled).sum()),
        "batches": -(-len(rows) // s.batch_persons),
        "skipped_without_estimate": int(len(tracks.track_id) - len(rows) - int(few.sum())),
        "skipped_few_points": int(few.sum()),
        "dropped_far_from_estimate": far,
        **counts,
        **gap_counts,
        "device": torch_device(s.device),
        "preset": inp.preset,
    }
