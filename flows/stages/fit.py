"""fit: a body-model fit per tracked person and frame, fused with its LiDAR points.

Rows of the track product with an initial estimate (providers: the oracle, or precomputed CLIFF
files) and at least ``min_points`` LiDAR points in the image are fitted in batches of
``batch_persons`` (tasks/fit/optimize.py, the paper's six-term objective), fanned out as row
ranges (routed to ``GPU=1`` workers with ``dask.gpu_fit``). With ``warm_start`` frames run in
order and a track starts from its previous frame's fit (tasks/fit/warm_start.py). Fits that moved
the root more than ``max_shift_m`` from their estimate are dropped; velocities come from the
track's pelvis motion (tasks/track/velocity.py). Product: :class:`storage.products.Bodies`.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from flows.pipeline.inputs import FitInputs, SequenceRef
from flows.pipeline.parallel import fan_out
from flows.stages.common import StageContext, body_model, pose_prior
from flows.stages.providers import init_provider
from storage.products import Bodies, Tracks
from tasks.body.params import BodyParams
from tasks.fit.batch import concat_point_sets, drop_far_fits, fit_rows
from tasks.fit.optimize import fit_persons, torch_device
from tasks.fit.warm_start import warm_started
from tasks.track.velocity import velocities_in_base


@functools.lru_cache(maxsize=2)
def _tracks(folder: str) -> Tracks:
    return Tracks.read(Path(folder))  # key-named, never rewritten: safe to keep per process


def fit_batch(
    ref: SequenceRef,
    inputs: FitInputs,
    out_root: Path,
    tracks_dir: Path,
    rows: list[int],
    init: BodyParams | None = None,
) -> dict:
    """Fit some rows of the track product from ``init`` (cam frame; None: the provider's
    estimates); returns their rows (tasks.fit.batch.fit_rows) in the LiDAR frame."""
    seq, s, tracks = inputs.source.open(ref), inputs.settings, _tracks(str(tracks_dir))
    cam = seq.info.calibration.cameras[inputs.source.camera]
    model, at = (
        body_model(inputs.body, out_root),
        {raw: i for i, raw in enumerate(seq.info.frame_indices)},
    )
    sweeps = {
        raw: seq.frame(at[raw]).points_lidar for raw in np.unique(tracks.frame[rows]).tolist()
    }
    points = [sweeps[int(tracks.frame[r])][tracks.points_of(r, in_image_only=True)] for r in rows]
    if init is None:
        init = init_provider(inputs.init, seq, model, cam).estimates(tracks, np.asarray(rows))
    result = fit_persons(
        model,
        pose_prior(inputs.body, out_root),
        init,
        tracks.keypoints[rows],
        cam.K,
        cam.T_cam_from_lidar,
        *concat_point_sets(points),
        inputs.weights,
        s,
    )
    return {
        "rows": np.asarray(rows, np.int64),
        **fit_rows(
            model,
            result,
            init,
            points,
            tracks.keypoints[rows],
            cam.K,
            cam.T_cam_from_lidar,
            inputs.weights.j_conf,
        ),
    }


def _warm_started(
    ctx: StageContext[FitInputs], seq, tracks: Tracks, rows: np.ndarray, resources
) -> list[dict]:
    """Fit frame by frame; a track fitted in the previous frame starts from that fit."""
    inp, step = ctx.inputs, ctx.inputs.settings.batch_persons
    model = body_model(inp.body, ctx.out_root)
    cam = seq.info.calibration.cameras[inp.source.camera]
    provider, pos = (
        init_provider(inp.init, seq, model, cam),
        {raw: k for k, raw in enumerate(seq.info.frame_indices)},
    )
    last: dict[
        int, tuple[int, BodyParams]
    ] = {}  # track -> (frame position, fit in its LiDAR frame)
    parts = []
    for f in np.unique(tracks.frame[rows]):
        p, here = pos[int(f)], rows[tracks.frame[rows] == f]
        args = []
        for a in range(0, len(here), step):
            batch = here[a : a + step]
            prev = [last.get(int(tracks.track_id[r])) for r in batch]
            prev = [q[1] if q is not None and q[0] == p - 1 else None for q in prev]
            init = warm_started(
                model,
                provider.estimates(tracks, batch),
                prev,
                cam.T_cam_from_lidar,
                seq.info.poses[p],
                seq.info.poses[p - 1] if p else seq.info.poses[p],
            )
            args.append((ctx.ref, inp, ctx.out_root, ctx.upstream["track"], batch.tolist(), init))
        for out in fan_out(fit_batch, args, resources, ctx.runtime.threads):
            parts.append(out)
            for k, r in enumerate(out["rows"]):
                last[int(tracks.track_id[r])] = (
                    p,
                    BodyParams.of(out).take(slice(k, k + 1)),
                )
    return parts


def _bodies(seq, tracks: Tracks, out: dict) -> Bodies:
    """The product from the kept fits' rows: velocities from the tracks' pelvis motion."""
    if not out:
        return Bodies.empty()
    r, pos = out.pop("rows"), {raw: k for k, raw in enumerate(seq.info.frame_indices)}
    at = np.array([pos[int(f)] for f in tracks.frame[r]], np.int64)
    velocity = velocities_in_base(
        tracks.track_id[r],
        seq.info.stamps_ns[at] * 1e-9,
        out.pop("pelvis_lidar"),
        seq.info.poses[at],
        seq.info.calibration.T_base_from_lidar,
    )
    return Bodies(
        tracks.frame[r],
        tracks.track_id[r],
        tracks.det_index[r],
        velocity_base=velocity.astype(np.float32),
        **out,
    )


def run_fit(ctx: StageContext[FitInputs]) -> dict:
    inp, seq = ctx.inputs, ctx.open()
    s, tracks = inp.settings, _tracks(str(ctx.upstream["track"]))
    cam = seq.info.calibration.cameras[inp.source.camera]
    rows = init_provider(inp.init, seq, body_model(inp.body, ctx.out_root), cam).available(tracks)
    few = tracks.points_in_image[rows] < s.min_points
    rows, resources = rows[~few], {"GPU": 1} if ctx.runtime.gpu_fit else None
    if s.warm_start:
        parts = _warm_started(ctx, seq, tracks, rows, resources)
    else:
        parts = fan_out(
            fit_batch,
            [
                (
                    ctx.ref,
                    inp,
                    ctx.out_root,
                    ctx.upstream["track"],
                    rows[a : a + s.batch_persons].tolist(),
                )
                for a in range(0, len(rows), s.batch_persons)
            ],
            resources,
            ctx.runtime.threads,
        )
    out, far = (
        drop_far_fits({k: np.concatenate([p[k] for p in parts]) for k in parts[0]}, s.max_shift_m)
        if parts
        else ({}, 0)
    )
    bodies = _bodies(seq, tracks, out)
    bodies.write(ctx.out_dir)
    return {
        "implemented": True,
        "fitted": len(bodies.frame),
        "batches": -(-len(rows) // s.batch_persons),
        "skipped_without_estimate": int(len(tracks.track_id) - len(rows) - int(few.sum())),
        "skipped_few_points": int(few.sum()),
        "dropped_far_from_estimate": far,
        "device": torch_device(s.device),
        "preset": inp.preset,
    }
