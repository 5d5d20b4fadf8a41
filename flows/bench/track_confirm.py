"""Tracks confirmed by evidence: what they give short logs and what they cost in false tracks.

``mobileocc bench track-confirm --data DATA [--config CFG] [--set k=v ...] [--log-frames 1,2,0]
[--json J]``

For every sequence under DATA (``mobileocc simulate``): the detect stage's own code on every
frame (dataset.rate_hz), each detection's person points and LiDAR box (the track stage's
flows.stages.track.persons_of), then the sequence cut into logs of ``n`` frames (0: the whole
sequence) and each log tracked on its own (tasks.track.offline.track_offline) twice: OC-SORT's
hit count alone, and with ``track.confirm`` (tasks.track.offline.Confirmation). Reported per n and
rule: tracked rows, MOTA, IDF1, misses, false positives and id switches against the ground-truth
persons in view (as ``mobileocc evaluate``: the ids of the logs of one sequence are kept apart).
"""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path

import numpy as np

from flows.pipeline.inputs import detect_inputs, open_sequence, sequence_ref, track_inputs
from flows.pipeline.plan import selected_sequences
from flows.stages.detect import detect_frames
from flows.stages.track import persons_of
from storage.gt import read_frame_gt
from storage.products import Detections
from tasks.metrics.tracking import tracking_scores
from tasks.track.ocsort import PedestrianTracker
from tasks.track.offline import Confirmation, detection_evidence, track_offline


def _frames(config, seq_id: str, inp) -> list[dict]:
    """Per frame: detections, persons and ground truth (the persons cam0 sees)."""
    seq = open_sequence(config, seq_id)
    cam = seq.info.calibration.cameras[inp.source.camera]
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        positions = list(range(seq.info.num_frames))
        rows = detect_frames(
            sequence_ref(config, seq_id), detect_inputs(config), positions, Path(tmp)
        )
        bad = [row for row in rows if "error" in row]
        if bad:  # the benchmark needs every frame (e.g. ground truth of an older simulator)
            raise ValueError(f"sequence {seq_id} frame {bad[0]['frame']}: {bad[0]['error']}")
        for i in positions:
            frame = seq.frame(i)
            d = Detections.read(Path(tmp), Detections.file_name(frame.index))
            persons = persons_of(frame, d, cam, inp)
            gt = read_frame_gt(seq.root, seq_id, frame.index)
            seen = np.flatnonzero(np.all(np.isfinite(gt.box2d), axis=1) & (gt.visible_fraction > 0))
            out.append(
                {
                    "boxes": d.boxes_xyxy,
                    "scores": d.scores,
                    "keypoints": d.keypoints,
                    "lidar_box": persons.lidar_box,
                    "lidar_scores": d.lidar_scores,
                    "world_xy": persons.world_xy,
                    "time_s": float(seq.info.stamps_ns[i]) * 1e-9,
                    "gt_ids": gt.track_id[seen].astype(np.int64),
                    "gt_boxes": gt.box2d[seen],
                }
            )
    return out


def bench_track_confirm(config, log_frames: tuple[int, ...] = (1, 2, 0)) -> dict:
    inp = track_inputs(config)
    per_seq = {s: _frames(config, s, inp) for s in selected_sequences(config)}
    result = {}
    rules = {"hits": Confirmation(enabled=False), "evidence": inp.confirm}
    for n in log_frames:
        for rule, confirm in rules.items():
            rows_tracked, scores = 0, None
            for frames in per_seq.values():
                size = n or len(frames)
                track_frames = []
                for start in range(0, len(frames), size):
                    log = frames[start : start + size]
                    evidence = [
                        detection_evidence(
                            f["scores"], f["keypoints"], f["lidar_box"], f["lidar_scores"], confirm
                        )
                        for f in log
                    ]
                    ids = track_offline(
                        [f["boxes"] for f in log],
                        [f["scores"] for f in log],
                        PedestrianTracker(inp.tracker),
                        inp.offline,
                        [f["world_xy"] for f in log],
                        np.array([f["time_s"] for f in log]),
                        inp.world_check,
                        evidence if confirm.enabled else None,
                    )
                    offset = 100000 * start  # ids of different logs are different tracks
                    for f, row_ids in zip(log, ids):
                        keep = row_ids >= 0
                        rows_tracked += int(keep.sum())
                        track_frames.append(
                            (f["gt_ids"], f["gt_boxes"], row_ids[keep] + offset, f["boxes"][keep])
                        )
                s = tracking_scores(track_frames)
                scores = s if scores is None else scores + s
            d = scores.as_dict()
            result[f"log_frames={n or 'all'} {rule}"] = {
                "tracked_rows": rows_tracked,
                **{
                    k: d[k]
                    for k in (
                        "mota",
                        "idf1",
                        "num_objects",
                        "misses",
                        "false_positives",
                        "switches",
                    )
                },
            }
    return {"confirm": dataclasses.asdict(inp.confirm), "results": result}
