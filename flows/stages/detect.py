"""detect: per frame, 2D person boxes / keypoints / masks, image semantics, LiDAR pedestrian boxes.

Providers (flows/stages/providers.py) are built from the stage's inputs; frames fan out in chunks
of 4. Product per frame: :class:`storage.products.Detections` (``frame_<raw>.npz``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flows.pipeline.inputs import DetectInputs, SequenceRef
from flows.pipeline.parallel import fan_out
from flows.stages.common import StageContext, chunks
from flows.stages.providers import image_provider, lidar_provider
from storage.products import Detections, masks_to_labels


def detect_frames(ref: SequenceRef, inputs: DetectInputs, positions: list[int], out_dir: Path) -> list[dict]:
    """Run the providers on some frames (positions in the sequence); one product per frame."""
    seq = inputs.source.open(ref)
    cam = seq.info.calibration.cameras[inputs.source.camera]
    images, lidars = image_provider(inputs.image, seq), lidar_provider(inputs.lidar, seq)
    rows = []
    for i in positions:
        frame = seq.frame(i)
        lidar = lidars.lidar(frame)
        image, gt_index = images.image(frame, lidar)
        if image.image_size != (cam.width, cam.height):
            raise ValueError(f"sequence {ref.sequence} frame {frame.index}: perception image size "
                             f"{image.image_size} != camera {(cam.width, cam.height)}")
        Detections(image.boxes_xyxy, image.scores, image.keypoints, masks_to_labels(image.masks),
                   image.semantic, lidar.centers, lidar.sizes, lidar.yaws, lidar.scores,
                   np.full(len(image), -2, np.int64) if gt_index is None else np.asarray(gt_index, np.int64),
                   ).write(out_dir, Detections.file_name(frame.index))
        rows.append({"frame": frame.index, "detections": len(image), "lidar_boxes": len(lidar)})
    return rows


def run_detect(ctx: StageContext) -> dict:
    n = len(ctx.open())
    resources = {"GPU": 1} if ctx.runtime.gpu_detect else None
    rows = [r for part in fan_out(detect_frames, [(ctx.ref, ctx.inputs, c, ctx.out_dir) for c in chunks(n, 4)],
                                  resources) for r in part]
    return {"implemented": True, "frames": [r["frame"] for r in rows],
            "image_provider": ctx.inputs.image.NAME, "lidar_provider": ctx.inputs.lidar.NAME,
            "detections": sum(r["detections"] for r in rows),
            "lidar_boxes": sum(r["lidar_boxes"] for r in rows)}
