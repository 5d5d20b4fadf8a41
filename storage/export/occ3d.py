"""Occ3D export: ``gts/<scene>/<sample_token>/labels.npz`` and ``annotations.json``.

labels.npz (written deterministically, np.load reads it): ``semantics``, ``mask_lidar``,
``mask_camera``, uint8, shape (X, Y, Z) in [x, y, z] order, free = 9 (last class); masks 0/1.
Scene names and sample tokens equal those of the nuScenes export, so trainers that look labels up
by nuScenes sample token (BEVDet, FlashOcc) find them.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from storage.dataset import open_dataset
from storage.export.common import (
    CAM_CHANNEL,
    pose_record,
    mat4,
    sample_file_name,
    sample_token,
    scene_name,
    sequence_info,
)
from storage.npzio import save_npz_deterministic
from storage.occupancy_store import open_layout, read_frames

LABEL_KEYS = ("semantics", "mask_lidar", "mask_camera")


def export_occ3d(
    dataset_root: str | os.PathLike,
    out_dir: str | os.PathLike,
    scene_prefix: str = "coda",
    val_sequences: Iterable[str] = (),
    sequences: Iterable[str] | None = None,
) -> Path:
    """Export the published dataset at ``dataset_root`` to Occ3D format under ``out_dir``.

    val_sequences: sequences listed in ``val_split`` (the rest go to ``train_split``).
    sequences: restrict to these (default: all published). Returns the annotations.json path.
    """
    ds = open_dataset(dataset_root)
    out = Path(out_dir)
    val = set(val_sequences)
    unknown = val - set(ds.sequences)
    if unknown:
        raise ValueError(f"export_occ3d: val_sequences {sorted(unknown)} are not in the dataset {list(ds.sequences)}")
    chosen = list(ds.sequences if sequences is None else sequences)
    scene_infos: dict[str, dict] = {}
    for seq in chosen:
        info = sequence_info(ds, seq)
        scene = scene_name(scene_prefix, seq)
        store = ds.store_path(seq)
        layout = open_layout(store)
        if len(info.frames) != layout.num_frames:
            raise ValueError(
                f"export_occ3d: sequence {seq!r} has {len(info.frames)} frame rows but "
                f"{layout.num_frames} frames in {store}"
            )
        tokens = [sample_token(seq, row["frame"]) for row in info.frames]
        cam = pose_record(info.T_base_from_cam0)
        samples: dict[str, dict] = {}
        for start, stop in layout.write_units():  # read whole chunks: zarr is slow on small reads
            grids = read_frames(store, slice(start, stop), LABEL_KEYS)
            for i in range(start, stop):
                row = info.frames[i]
                tok = tokens[i]
                gt_rel = f"gts/{scene}/{tok}/labels.npz"
                save_npz_deterministic(
                    out / gt_rel, compressed=True, **{k: np.ascontiguousarray(grids[k][i - start]) for k in LABEL_KEYS}
                )
                stamp_us = int(row["stamp_ns"]) // 1000
                ego = pose_record(mat4(row["T_world_from_base"]))
                ext = Path(row["cam0_path"]).suffix if row["cam0_path"] else ".png"
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
    annotations = {
        "train_split": [scene_name(scene_prefix, s) for s in chosen if s not in val],
        "val_split": [scene_name(scene_prefix, s) for s in chosen if s in val],
        "scene_infos": scene_infos,
    }
    path = out / "annotations.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(".tmp-annotations.json")
    tmp.write_text(json.dumps(annotations, indent=1, sort_keys=True))
    os.replace(tmp, path)
    return path
