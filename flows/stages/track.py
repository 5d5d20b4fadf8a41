"""track: OC-SORT ids over a sequence's 2D detections, and each tracked person's LiDAR points.

Every detection's person points and world position first (tasks/track/product.py), then the whole
sequence tracked offline (tasks/track/offline.py: OC-SORT, back-fill, the world-position check,
stitching), then one row per tracked detection: :class:`storage.products.Tracks`.
"""

from __future__ import annotations

import numpy as np

from flows.pipeline.inputs import TrackInputs
from flows.stages.common import StageContext, detected_positions
from storage.products import Detections, Tracks, labels_to_masks
from tasks.track.ocsort import PedestrianTracker
from tasks.track.offline import detection_evidence, track_offline
from tasks.track.product import FramePersons, frame_persons, track_rows


def persons_of(frame, d: Detections, cam, inp: TrackInputs) -> FramePersons:
    """One frame's persons (each detection's LiDAR points, world positions) from its detections
    ``d``: the track stage's per-frame step (benchmarks call it too)."""
    return frame_persons(
        frame.points_lidar,
        frame.T_world_from_lidar,
        d.boxes_xyxy,
        labels_to_masks(d.mask_labels, len(d.scores)),
        d.lidar_centers,
        d.lidar_sizes,
        d.lidar_yaws,
        cam.K,
        cam.T_cam_from_lidar,
        (cam.width, cam.height),
        inp.person_points,
        inp.world_check,
    )


def _frame(ctx: StageContext[TrackInputs], seq, cam, i: int) -> tuple[int, dict, FramePersons]:
    """Frame i's raw number, detections (without the image-sized arrays: a sequence's worth of
    them would not fit in memory) and persons."""
    inp, frame = ctx.inputs, seq.frame(i)
    d = Detections.read(ctx.upstream["detect"], Detections.file_name(frame.index))
    persons = persons_of(frame, d, cam, inp)
    rows = {
        k: getattr(d, k) for k in ("boxes_xyxy", "scores", "keypoints", "gt_index", "lidar_scores")
    }
    return frame.index, rows, persons


def run_track(ctx: StageContext[TrackInputs]) -> dict:
    inp, seq = ctx.inputs, ctx.open()
    cam, at = seq.info.calibration.cameras[inp.source.camera], detected_positions(ctx, seq)
    raws, dets, persons = zip(*(_frame(ctx, seq, cam, i) for i in at)) if at else ((), (), ())
    per = {k: [d[k] for d in dets] for k in ("boxes_xyxy", "scores", "keypoints", "gt_index")}
    ids = track_offline(
        per["boxes_xyxy"],
        per["scores"],
        PedestrianTracker(inp.tracker),
        inp.offline,
        [p.world_xy for p in persons],
        seq.info.stamps_ns[at] * 1e-9,
        inp.world_check,
        [
            detection_evidence(
                d["scores"], d["keypoints"], p.lidar_box, d["lidar_scores"], inp.confirm
            )
            for d, p in zip(dets, persons)
        ],
    )
    tracks = Tracks(
        **track_rows(
            list(raws),
            ids,
            list(persons),
            per["boxes_xyxy"],
            per["scores"],
            per["keypoints"],
            per["gt_index"],
        )
    )
    tracks.write(ctx.out_dir)
    sizes = np.diff(tracks.points_offsets)
    return {
        "implemented": True,
        "tracks": int(np.unique(tracks.track_id).size),
        "tracked_detections": int(tracks.track_id.size),
        "mean_person_points": float(sizes.mean()) if sizes.size else 0.0,
    }
