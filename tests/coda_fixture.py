"""A tiny CODa-layout dataset built in a test's tmp_path: a few frames of synthetic values."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import yaml

POINTS = 128 * 1024


def _matrix(rows: int, cols: int, values) -> dict:
    return {"rows": rows, "cols": cols, "data": [float(v) for v in np.asarray(values).reshape(-1)]}


def make_coda(root: Path, seq: int = 0, frames: int = 4, channels: int = 5,
              image_ext: str = ".png", pose_folder: str = "dense_global",
              lidar_source: str = "3d_raw") -> Path:
    """Write `frames` raw frames of sequence `seq` under root; returns root."""
    rng = np.random.default_rng(seq)
    s = str(seq)
    for f in range(frames):
        pts = np.zeros((POINTS, channels), np.float32)
        n = 2000  # a few returns; the rest are no-returns (zeros)
        idx = rng.choice(POINTS, n, replace=False)
        pts[idx, 0] = rng.uniform(2, 20, n)
        pts[idx, 1] = rng.uniform(-5, 5, n)
        pts[idx, 2] = rng.uniform(-1, 2, n)
        pts[idx, 3] = rng.uniform(0, 1, n)
        path = root / lidar_source / "os1" / s / f"{lidar_source}_os1_{s}_{f}.bin"
        path.parent.mkdir(parents=True, exist_ok=True)
        pts.tofile(path)
        for cam in ("cam0", "cam1"):
            img = root / "2d_rect" / cam / s / f"2d_rect_{cam}_{s}_{f}{image_ext}"
            img.parent.mkdir(parents=True, exist_ok=True)
            img.write_bytes(b"not-a-real-image")
        box = {"3dbbox": [{"classId": "Pedestrian", "instanceId": "Pedestrian:3",
                           "labelAttributes": {"isOccluded": "Light"},
                           "cX": 5.0, "cY": 1.0, "cZ": 0.0, "l": 2.0, "w": 0.5, "h": 1.8,
                           "r": 0.0, "p": 0.0, "y": float(np.pi / 2)}]}
        bp = root / "3d_bbox" / "os1" / s / f"3d_bbox_os1_{s}_{f}.json"
        bp.parent.mkdir(parents=True, exist_ok=True)
        bp.write_text(json.dumps(box))
    stamps = 1.6e9 + 0.1 * np.arange(frames)
    (root / "timestamps").mkdir(parents=True, exist_ok=True)
    (root / "timestamps" / f"{s}.txt").write_text("".join(f"{t:.6f}\n" for t in stamps))
    (root / "poses" / pose_folder).mkdir(parents=True, exist_ok=True)
    (root / "poses" / pose_folder / f"{s}.txt").write_text(
        "".join(f"{t:.6f} {0.1 * k:.3f} 0 0 1 0 0 0\n" for k, t in enumerate(stamps)))
    cal = root / "calibrations" / s
    cal.mkdir(parents=True, exist_ok=True)
    K = [[730, 0, 612], [0, 730, 512], [0, 0, 1]]
    T_cam = [[0, -1, 0, 0], [0, 0, -1, -0.1], [1, 0, 0, -0.1], [0, 0, 0, 1]]
    for cam in ("cam0", "cam1"):
        (cal / f"calib_{cam}_intrinsics.yaml").write_text(yaml.safe_dump({
            "image_width": 1224, "image_height": 1024,
            "camera_matrix": _matrix(3, 3, K), "distortion_model": "plumb_bob",
            "distortion_coefficients": _matrix(1, 5, [0, 0, 0, 0, 0]),
            "rectification_matrix": _matrix(3, 3, np.eye(3)),
            "projection_matrix": _matrix(3, 4, np.hstack([K, np.zeros((3, 1))])),
        }))
        (cal / f"calib_os1_to_{cam}.yaml").write_text(
            yaml.safe_dump({"extrinsic_matrix": _matrix(4, 4, T_cam)}))
    T_base = np.eye(4)
    T_base[2, 3] = 0.9
    (cal / "calib_os1_to_base.yaml").write_text(
        yaml.safe_dump({"extrinsic_matrix": _matrix(4, 4, T_base)}))
    (root / "metadata").mkdir(parents=True, exist_ok=True)
    (root / "metadata" / f"{s}.json").write_text(json.dumps({"lighting": "day"}))
    return root
