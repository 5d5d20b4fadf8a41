"""detect: per frame, 2D person boxes / keypoints / masks, image semantics, LiDAR pedestrian boxes.

Providers (flows/stages/providers.py) are built from the stage's inputs; frames fan out in chunks
of 4. Product per frame: :class:`storage.products.Detections` (``frame_<raw>.npz``).

Bad frames: a frame whose files are unreadable (the reader's or the ground truth's error about
that frame: a cut sweep, an image that does not decode or is not the calibrated size, a broken
label file) is left out with its error in the summary (``failed_frames``); every later stage takes
its frames from ``frames``, the ones detect produced. The stage fails when no frame is left, or
when more than ``max_failed_frame_share`` of them failed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flows.pipeline.inputs import DetectInputs, SequenceRef
from flows.pipeline.parallel import fan_out
from flows.stages.common import StageContext, chunks
from flows.stages.providers import image_provider, lidar_provider
from storage.files import InputError
from storage.products import Detections, masks_to_labels


class FramesFailed(ValueError):
    """Too many of a sequence's frames are unreadable for the stage to go on."""


def _perceive(seq, i: int, images, lidars):
    """Frame i, its LiDAR and image perception; None and the error when the frame's input is bad."""
    try:
        frame = seq.frame(i)
        seq.check_images(frame.index)  # decoded here: later stages and the exports trust them
        lidar = lidars.lidar(frame)
        return (frame, lidar, *images.image(frame, lidar)), None
    except InputError as exc:
        if exc.frame is None:  # not about one frame: the sequence fails
            raise
        return None, str(exc)


def detect_frames(
    ref: SequenceRef, inputs: DetectInputs, positions: list[int], out_dir: Path
) -> list[dict]:
    """Run the providers on some frames (positions in the sequence); one product per good frame,
    ``{"frame": raw, "error": message}`` for a frame whose input is bad."""
    seq = inputs.source.open(ref)
    cam = seq.info.calibration.cameras[inputs.source.camera]
    images, lidars = image_provider(inputs.image, seq), lidar_provider(inputs.lidar, seq)
    rows = []
    for i in positions:
        done, error = _perceive(seq, i, images, lidars)
        if done is None:
            rows.append({"frame": seq.info.frame_indices[i], "error": error})
            continue
        frame, lidar, image, gt_index = done
        if image.image_size != (cam.width, cam.height):
            raise ValueError(
                f"sequence {ref.sequence} frame {frame.index}: perception image size "
                f"{image.image_size} != camera {(cam.width, cam.height)}"
            )
        Detections(
            image.boxes_xyxy,
            image.scores,
            image.keypoints,
            masks_to_labels(image.masks),
            image.semantic,
            lidar.centers,
            lidar.sizes,
            lidar.yaws,
            lidar.scores,
            np.full(len(image), -2, np.int64)
            if gt_index is None
            else np.asarray(gt_index, np.int64),
        ).write(out_dir, Detections.file_name(frame.index))
        rows.append({"frame": frame.index, "detections": len(image), "lidar_boxes": len(lidar)})
    return rows


def check_failed_frames(rows: list[dict], max_share: float) -> list[dict]:
    """The failed rows; FramesFailed (naming the first files and frames) when none is left or more
    than ``max_share`` of the frames failed."""
    failed = [r for r in rows if "error" in r]
    if failed and (len(failed) == len(rows) or len(failed) > max_share * len(rows)):
        first = "; ".join(r["error"] for r in failed[:3]) + (
            f"; ... ({len(failed) - 3} more)" if len(failed) > 3 else ""
        )
        raise FramesFailed(
            f"{len(failed)} of {len(rows)} frame(s) have bad input (more than "
            f"detect.max_failed_frame_share = {max_share:g}): {first}"
        )
    return failed


def run_detect(ctx: StageContext[DetectInputs]) -> dict:
    n = len(ctx.open())
    resources = {"GPU": 1} if ctx.runtime.gpu_detect else None
    rows = [
        r
        for part in fan_out(
            detect_frames,
            [(ctx.ref, ctx.inputs, c, ctx.out_dir) for c in chunks(n, 4)],
            resources,
            ctx.runtime.threads,
        )
        for r in part
    ]
    failed, rows = (
        check_failed_frames(rows, ctx.inputs.max_failed_frame_share),
        [r for r in rows if "error" not in r],
    )
    return {
        "implemented": True,
        "frames": [r["frame"] for r in rows],
        "failed_frames": [{"frame": int(r["frame"]), "error": r["error"]} for r in failed],
        "image_provider": ctx.inputs.image.NAME,
        "lidar_provider": ctx.inputs.lidar.NAME,
        "detections": sum(r["detections"] for r in rows),
        "lidar_boxes": sum(r["lidar_boxes"] for r in rows),
    }
