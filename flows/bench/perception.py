"""2D perception quality of an image provider against synthetic ground truth.

``mobileocc bench perception --data DATA [--config CFG] [--set k=v ...] [--boxes gt] --json J``

For every frame (5 Hz) of every sequence under DATA (written by ``mobileocc simulate``): the
detect stage's own code (``detect_frames``) runs with the config, and its boxes / keypoints /
masks are compared with the ground truth: detection recall / precision (tasks.metrics.detection,
as ``mobileocc evaluate``), PCK@0.1 of the box height over visible keypoints and instance-mask
IoU of the detections matched to a person (IoU >= 0.5), milliseconds per frame. ``--boxes gt``
(image_provider 'models' only) feeds the visible persons' ground-truth boxes to the models instead
of the detector: the keypoint and mask quality on their own.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from flows.commands.evaluate import VISIBLE_FRACTION
from flows.pipeline.inputs import detect_inputs, open_sequence, sequence_ref
from flows.pipeline.plan import selected_sequences
from flows.stages.detect import detect_frames
from flows.stages.models import model_perception
from storage.gt import read_frame_gt
from storage.images import read_rgb
from storage.products import Detections as DetectionsProduct
from tasks.geometry import match_boxes
from tasks.metrics.detection import DetectionCounts, detection_counts
from tasks.metrics.keypoints import mask_iou, pck_counts
from tasks.perception.models.detector import Detections


def bench_perception(config, boxes: str = "provider") -> dict:
    counts, pck, ious, seconds, frames, persons = DetectionCounts(), [0, 0], [], 0.0, 0, 0
    for seq_id in selected_sequences(config):
        seq = open_sequence(config, seq_id)
        cam = seq.info.calibration.cameras[config.dataset.camera]
        with tempfile.TemporaryDirectory() as tmp:
            for i in range(seq.info.num_frames):
                frame = seq.frame(i)
                gt = read_frame_gt(seq.root, int(seq_id), frame.index)
                rows = np.flatnonzero(np.all(np.isfinite(gt.box2d), 1) & (gt.visible_fraction > 0))
                vis = gt.visible_fraction[rows] >= VISIBLE_FRACTION
                t = time.perf_counter()
                if boxes == "gt":
                    rows = rows[vis]
                    image = read_rgb(
                        frame.image_paths[config.dataset.camera], (cam.width, cam.height)
                    )
                    p = model_perception(config.detect.models)(
                        image,
                        Detections(
                            gt.box2d[rows].astype(np.float32), np.ones(len(rows), np.float32)
                        ),
                        gt.cam0_semantic,
                    )
                    det = {"boxes_xyxy": p.boxes_xyxy, "keypoints": p.keypoints, "masks": p.masks}
                    vis = np.ones(len(rows), bool)
                else:
                    detect_frames(
                        sequence_ref(config, seq_id), detect_inputs(config), [i], Path(tmp)
                    )
                    d = DetectionsProduct.read(
                        Path(tmp), DetectionsProduct.file_name(frame.index)
                    ).arrays()
                    labels = d["mask_labels"]
                    det = {
                        "boxes_xyxy": d["boxes_xyxy"],
                        "keypoints": d["keypoints"],
                        "masks": labels[None] == np.arange(1, len(d["scores"]) + 1)[:, None, None],
                    }
                seconds += time.perf_counter() - t
                frames += 1
                persons += len(rows)
                counts = counts + detection_counts(gt.box2d[rows], vis, det["boxes_xyxy"])
                gi, di = match_boxes(gt.box2d[rows], det["boxes_xyxy"], 0.5)
                if gi.size:
                    g = rows[gi]
                    c, n = pck_counts(
                        det["keypoints"][di], gt.keypoints[g], gt.box2d[g, 3] - gt.box2d[g, 1]
                    )
                    pck[0] += c
                    pck[1] += n
                    truth = gt.cam0_instance[None] == gt.track_id[g][:, None, None]
                    ious.extend(mask_iou(det["masks"][di], truth).tolist())
    ious = np.asarray(ious)
    return {
        "provider": config.detect.image_provider,
        "boxes": boxes,
        "frames": frames,
        "gt_persons": persons,
        "detection": counts.as_dict(),
        "pck@0.1": pck[0] / max(pck[1], 1),
        "pck_keypoints": pck[1],
        "mask_iou_median": float(np.median(ious)) if ious.size else float("nan"),
        "mask_iou_mean": float(ious.mean()) if ious.size else float("nan"),
        "matched": int(ious.size),
        "ms_per_frame": 1000 * seconds / max(frames, 1),
    }
