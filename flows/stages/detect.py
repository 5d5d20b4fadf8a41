"""detect: per frame, 2D person boxes / keypoints / masks, image semantics, LiDAR pedestrian boxes.

Product per frame ``frame_<raw>.npz``: boxes_xyxy (D, 4) float32 px, scores (D,), keypoints
(D, 17, 3) (u, v, confidence), mask_labels (H, W) uint16 (detection k has label k + 1), semantic
(H, W) uint8 Cityscapes train ids, lidar_centers / lidar_sizes (M, 3) (l, w, h) / lidar_yaws /
lidar_scores (M,) in the LiDAR frame, gt_index (D,) int64 (synthetic data, oracle or models: the
matched ground-truth row, -1 false positive; -2 where unknown).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from configs.schema import Config
from flows.model_providers import gt_index_by_boxes, models_image_perception, uses_oracle_semantic
from flows.parallel import fan_out
from flows.plan import open_sequence
from flows.stages.common import StageContext, chunks, frame_rng, is_night
from storage.gt import read_frame_gt
from storage.intermediate import masks_to_labels, write_product
from storage.perception_files import PrecomputedPerception
from tasks.perception.lidar_clusters import detect_pedestrians_lidar
from tasks.perception.oracle import OracleNoise, oracle_image_perception, oracle_lidar_detections
from tasks.perception.types import ImagePerception, LidarDetections


def _oracle_noise(config: Config) -> OracleNoise:
    return OracleNoise(**config.detect.oracle.model_dump())


def detect_frames(config: Config, sequence: str, positions: list[int], out_dir: Path) -> list[dict]:
    """Run the configured providers on some frames; writes one product per frame."""
    det = config.detect
    seq = open_sequence(config, sequence)
    cam = seq.info.calibration.cameras[config.dataset.camera]
    night = is_night(seq)
    precomputed = (PrecomputedPerception(Path(det.precomputed_dir) / sequence)
                   if "precomputed" in (det.image_provider, det.lidar_provider) else None)
    rows = []
    for i in positions:
        frame = seq.frame(i)
        gt = read_frame_gt(seq.root, int(sequence), frame.index) if "oracle" in (
            det.image_provider, det.lidar_provider) or uses_oracle_semantic(config) else None
        gt_index = None
        if det.image_provider == "oracle" or uses_oracle_semantic(config):
            image, gt_index = oracle_image_perception(
                gt.box2d, gt.keypoints, gt.visible_fraction, np.linalg.norm(gt.box_center, axis=1),
                gt.track_id, gt.cam0_instance, gt.cam0_semantic,
                frame_rng(det.seed, sequence, frame.index, 1), night=night, noise=_oracle_noise(config))
        elif det.image_provider == "precomputed":
            image = ImagePerception(**precomputed.image(frame.index))
        if det.lidar_provider == "lidar-clusters":
            lidar = detect_pedestrians_lidar(frame.points_lidar, **det.lidar_clusters.model_dump())
        elif det.lidar_provider == "oracle":
            counts = np.array([(gt.point_instance == t).sum() for t in gt.track_id], np.int64)
            lidar, _ = oracle_lidar_detections(gt.box_center, gt.box_size, gt.box_yaw, counts,
                                               frame_rng(det.seed, sequence, frame.index, 2),
                                               noise=_oracle_noise(config))
        elif det.lidar_provider == "precomputed":
            lidar = LidarDetections(**precomputed.lidar(frame.index))
        else:
            lidar = LidarDetections.empty()
        if det.image_provider == "models":  # real networks on the frame's image (flows/model_providers.py)
            image = models_image_perception(config, frame, cam, lidar,
                                            image.semantic if uses_oracle_semantic(config) else None)
            gt_index = None if gt is None else gt_index_by_boxes(image.boxes_xyxy, gt.box2d)
        if image.image_size != (cam.width, cam.height):
            raise ValueError(f"sequence {sequence} frame {frame.index}: perception image size "
                             f"{image.image_size} != camera {(cam.width, cam.height)}")
        write_product(out_dir, f"frame_{frame.index}", {
            "boxes_xyxy": image.boxes_xyxy, "scores": image.scores, "keypoints": image.keypoints,
            "mask_labels": masks_to_labels(image.masks), "semantic": image.semantic,
            "lidar_centers": lidar.centers, "lidar_sizes": lidar.sizes, "lidar_yaws": lidar.yaws,
            "lidar_scores": lidar.scores,
            "gt_index": (np.full(len(image), -2, np.int64) if gt_index is None
                         else np.asarray(gt_index, np.int64)),
        })
        rows.append({"frame": frame.index, "detections": len(image), "lidar_boxes": len(lidar.scores),
                     "points": int(frame.points_lidar.shape[0])})
    return rows


def run_detect(ctx: StageContext) -> dict:
    n = len(ctx.open())
    parts = fan_out(detect_frames, [(ctx.config, ctx.sequence, c, ctx.out_dir) for c in chunks(n, 4)],
                    {"GPU": 1} if ctx.config.dask.gpu_detect else None)
    rows = [r for part in parts for r in part]
    return {"implemented": True, "frames": [r["frame"] for r in rows],
            "image_provider": ctx.config.detect.image_provider,
            "lidar_provider": ctx.config.detect.lidar_provider,
            "detections": sum(r["detections"] for r in rows),
            "lidar_boxes": sum(r["lidar_boxes"] for r in rows)}
