"""Occ3D export: ``gts/<scene>/<sample_token>/labels.npz``, ``annotations.json``, ``occ3d_metadata.json``.

labels.npz (written deterministically, np.load reads it): ``semantics``, ``mask_lidar``,
``mask_camera``, uint8, shape (X, Y, Z) in [x, y, z] order, free = 10 (last class; 9
unclassified, Occ3D's "others"); masks 0/1;
and OpenOcc's ``flow``, float16 (X, Y, Z, 2): (vx, vy) m/s of each voxel, base-frame axes, the
robot's own motion removed (the store's ``velocity``: non-zero at pedestrian voxels), read with
the same masks. Scene names and sample tokens equal those of the nuScenes export, so trainers
that look labels up by nuScenes sample token (BEVDet, FlashOcc) find them; ``annotations.json``
lists scenes and each scene's samples in time order. ``occ3d_metadata.json``: grid spec, class
names, free id (storage/SCHEMA.md). With ``gt_root`` (synthetic data) ``semantics`` is the exact
ground-truth occupancy of the frame instead of the pipeline's labels and ``flow`` each GT
person's velocity on its voxels, masks unchanged, so a network is scored against exact labels on
the same voxels.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from storage.atomic import atomic_write_text
from storage.dataset import open_dataset
from storage.export.common import (
    CAM_CHANNEL,
    from_log,
    grid_metadata,
    mat4,
    pose_record,
    sample_file_name,
    sample_token,
    scene_name,
    sequence_info,
    write_json,
)
from storage.npzio import save_npz_deterministic
from storage.occupancy_store import open_layout, read_frames

LABEL_KEYS = ("semantics", "mask_lidar", "mask_camera")
#: the store's array written as OpenOcc's ``flow``
FLOW_KEY = "velocity"
#: grid spec, class names, free id, which labels (beside the nuScenes export's own, same folder)
METADATA_FILE = "occ3d_metadata.json"


def export_occ3d(
    dataset_root: str | os.PathLike,
    out_dir: str | os.PathLike,
    scene_prefix: str = "coda",
    val_sequences: Iterable[str] = (),
    sequences: Iterable[str] | None = None,
    gt_root: str | os.PathLike | None = None,
    source_root: str | os.PathLike | None = None,
) -> Path:
    """Export the published dataset at ``dataset_root`` to Occ3D format under ``out_dir``.

    val_sequences: sequences listed in ``val_split`` (the rest go to ``train_split``).
    sequences: restrict to these (default: all published).
    gt_root: the raw data root holding synthetic ground truth (``gt/<seq>/``): export its exact
    occupancy as ``semantics`` (the grids must be the same).
    source_root: the raw data root (needed for robot logs only: the image's extension, ".jpg" or
    ".png", is the one the nuScenes export writes). Returns the annotations.json path.
    """
    ds = open_dataset(dataset_root)
    out = Path(out_dir)
    val = set(val_sequences)
    unknown = val - set(ds.sequences)
    if unknown:
        raise ValueError(
            f"export_occ3d: val_sequences {sorted(unknown)} are not in the dataset {list(ds.sequences)}"
        )
    chosen = list(ds.sequences if sequences is None else sequences)
    metadata = grid_metadata(ds, chosen)
    scene_infos: dict[str, dict] = {}
    scenes: dict[str, str] = {}
    for seq in chosen:
        info = sequence_info(ds, seq)
        scene = scenes[seq] = scene_name(scene_prefix, seq, from_log(info.frames))
        log_ext = _log_image_suffix(info.frames, source_root, seq)
        store = ds.store_path(seq)
        layout = open_layout(store)
        if len(info.frames) != layout.num_frames:
            raise ValueError(
                f"export_occ3d: sequence {seq!r} has {len(info.frames)} frame rows but "
                f"{layout.num_frames} frames in {store}"
            )
        gt_labels = _gt_reader(gt_root, seq, metadata["grid"]) if gt_root is not None else None
        tokens = [sample_token(seq, row["frame"]) for row in info.frames]
        cam = pose_record(info.T_base_from_cam0)
        samples: dict[str, dict] = {}
        for start, stop in layout.write_units():  # read whole chunks: zarr is slow on small reads
            grids = read_frames(store, slice(start, stop), (*LABEL_KEYS, FLOW_KEY))
            for i in range(start, stop):
                row = info.frames[i]
                tok = tokens[i]
                gt_rel = f"gts/{scene}/{tok}/labels.npz"
                labels = {k: np.ascontiguousarray(grids[k][i - start]) for k in LABEL_KEYS}
                labels["flow"] = np.ascontiguousarray(grids[FLOW_KEY][i - start], np.float16)
                if gt_labels is not None:
                    labels["semantics"], labels["flow"] = gt_labels(int(row["raw_frame"]))
                save_npz_deterministic(out / gt_rel, compressed=True, **labels)
                stamp_us = int(row["stamp_ns"]) // 1000
                ego = pose_record(mat4(row["T_world_from_base"]))
                ext = log_ext or (Path(row["cam0_path"]).suffix if row["cam0_path"] else ".png")
                samples[tok] = {
                    "timestamp": stamp_us,
                    "camera_sensor": {
                        CAM_CHANNEL: {
                            "img_path": sample_file_name(scene, CAM_CHANNEL, stamp_us, ext),
                            "intrinsic": info.K.tolist(),
                            "extrinsic": cam,
                            "ego_pose": ego,
                        }
                    },
                    "ego_pose": ego,
                    "gt_path": gt_rel,
                    "prev": tokens[i - 1] if i > 0 else "",
                    "next": tokens[i + 1] if i + 1 < len(tokens) else "",
                }
        scene_infos[scene] = samples
    # time order: scenes by their first sample, a scene's samples as recorded (not by token)
    first = {
        sc: min((v["timestamp"] for v in smp.values()), default=0)
        for sc, smp in scene_infos.items()
    }
    scene_infos = {
        sc: scene_infos[sc] for sc in sorted(scene_infos, key=lambda sc: (first[sc], sc))
    }
    annotations = {
        "train_split": [scenes[s] for s in chosen if s not in val],
        "val_split": [scenes[s] for s in chosen if s in val],
        "scene_infos": scene_infos,
    }
    path = atomic_write_text(
        out / "annotations.json", json.dumps(_time_ordered_json(annotations), indent=1)
    )
    write_json(
        out / METADATA_FILE,
        {
            **metadata,
            "scene_prefix": scene_prefix,
            "train_split": annotations["train_split"],
            "val_split": annotations["val_split"],
            "labels": "ground-truth" if gt_root is not None else "pipeline",
        },
    )
    return path


def _sort_keys(obj):
    """``obj`` with every dict's keys sorted (deterministic JSON)."""
    if isinstance(obj, dict):
        return {k: _sort_keys(obj[k]) for k in sorted(obj)}
    if isinstance(obj, list):
        return [_sort_keys(v) for v in obj]
    return obj


def _time_ordered_json(annotations: dict) -> dict:
    """Keys sorted everywhere except ``scene_infos``' scenes and their sample tokens, which
    keep their (time) order."""
    return {
        k: {sc: {tok: _sort_keys(r) for tok, r in smp.items()} for sc, smp in v.items()}
        if k == "scene_infos"
        else _sort_keys(v)
        for k, v in sorted(annotations.items())
    }


def _log_image_suffix(frames: list[dict], source_root, sequence: str) -> str | None:
    """A robot log's camera image suffix (every frame's image comes from one topic); None for the
    CODa layout, whose files carry theirs."""
    from storage.sources.log.refs import image_suffix, parse_ref

    ref = parse_ref(frames[0]["cam0_path"]) if frames and frames[0]["cam0_path"] else None
    if ref is None:
        return None
    if source_root is None:
        raise ValueError(
            f"export_occ3d: sequence {sequence!r} comes from a robot log ({ref.log}): its image "
            "extension needs the raw data root (source_root)"
        )
    return image_suffix(ref, Path(source_root))


def _gt_reader(gt_root, sequence: str, grid: dict):
    """raw frame -> ((X, Y, Z) uint8 ground-truth occupancy, (X, Y, Z, 2) float16 flow: each GT
    person's velocity (base axes, m/s) on its voxels) of ``sequence``, checked against the
    exported grid (ValueError naming the ground-truth file when it differs)."""
    from storage.gt import gt_dir, read_frame_gt, read_sequence_gt

    seq_id = sequence
    gseq = read_sequence_gt(Path(gt_root), seq_id)
    same = (
        list(gseq.grid_shape) == grid["shape"]
        and abs(gseq.grid_voxel_size_m - grid["voxel_size_m"]) < 1e-9
        and np.allclose(gseq.grid_range_min, grid["range_min"])
    )
    if not same:
        raise ValueError(
            f"export_occ3d: ground truth {gt_dir(Path(gt_root), seq_id) / 'sequence.npz'} has grid "
            f"{tuple(gseq.grid_shape)} at {gseq.grid_voxel_size_m} m from {gseq.grid_range_min.tolist()}, the dataset "
            f"{tuple(grid['shape'])} at {grid['voxel_size_m']} m from {grid['range_min']}: rebuild with the ground "
            "truth's grid to export it"
        )

    def labels(raw_frame: int) -> tuple[np.ndarray, np.ndarray]:
        gtf = read_frame_gt(Path(gt_root), seq_id, raw_frame)
        flow = np.zeros(gtf.occupancy.shape + (2,), np.float16)
        for tid, v in zip(gtf.track_id, gtf.velocity_base):
            flow[gtf.occupancy_instance == tid] = np.asarray(v, np.float32)[:2]
        return np.ascontiguousarray(gtf.occupancy, dtype=np.uint8), flow

    return labels
