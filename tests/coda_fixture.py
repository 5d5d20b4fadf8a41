"""A tiny CODa-layout dataset built in a test's tmp_path, laid out as a CODa download holds it.

Calibration from CODa's documented example (coda-devkit docs/DATA_REPORT.md): the cam0 intrinsics
(K, plumb-bob D), the os1 -> cam0 extrinsic and cam0 -> cam1 in its ``{R, T}`` form; the stereo
rectification R0, R1 and the projection matrices P0 = [K' | 0], P1 = [K' | -fx' B] are made here
(a rectified x axis along the baseline), so R != I and P != K as in a real download. Sweeps are
5-channel with the time in nanoseconds; ``present`` leaves files out of frames as a split download.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import yaml

POINTS = 128 * 1024

#: coda-devkit docs/DATA_REPORT.md, "Calibration Files (With Examples)"
K_CAM0 = np.array(
    [[730.271578753826, 0, 610.90462936767], [0, 729.707285068689, 537.715474717007], [0, 0, 1]]
)
D_CAM0 = np.array(
    [
        -0.0559502131995934,
        0.123761456061624,
        0.00114530935813615,
        -0.00367111451580028,
        -0.0636070725936968,
    ]
)
K_RECT = np.array(
    [
        [730.93414758424547, 0, 606.62505340576172],
        [0, 730.93414758424547, 531.60715866088867],
        [0, 0, 1],
    ]
)
T_CAM0_FROM_OS1 = np.array(
    [
        [-0.0050614, -0.9999872, 0.0000000, 0.03],
        [-0.1556502, 0.0007878, -0.9878119, -0.05],
        [0.9877993, -0.0049997, -0.1556522, 0],
        [0, 0, 0, 1],
    ]
)
R_CAM1_FROM_CAM0 = np.array(
    [
        [0.999607939093204, -0.00728019495660303, 0.0270363988583955],
        [0.00661202516157305, 0.999672512844786, 0.024721411485882],
        [-0.0272075214802657, -0.0245329538373475, 0.999328717165135],
    ]
)
T_CAM1_FROM_CAM0_T = np.array([-0.197673440251558, 0.00128769601558891, 0.00253652872125049])


def _matrix(rows: int, cols: int, values) -> dict:
    return {"rows": rows, "cols": cols, "data": [float(v) for v in np.asarray(values).reshape(-1)]}


def _orthonormal(R: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(R)
    return u @ vt


def stereo_calibration() -> dict:
    """Raw intrinsics, rectification and projection of both cameras, and the extrinsics."""
    R01 = _orthonormal(R_CAM1_FROM_CAM0)
    T01 = np.eye(4)
    T01[:3, :3], T01[:3, 3] = R01, T_CAM1_FROM_CAM0_T
    c1 = -R01.T @ T_CAM1_FROM_CAM0_T  # cam1 centre in cam0's frame (about +0.198 m along x)
    e1 = c1 / np.linalg.norm(c1)
    e2 = np.cross([0.0, 0.0, 1.0], e1)
    e2 /= np.linalg.norm(e2)
    R0 = np.stack([e1, e2, np.cross(e1, e2)])  # rectified x along the baseline
    R1 = R0 @ R01.T  # both rectified frames parallel
    baseline = float(np.linalg.norm(c1))
    P0 = np.hstack([K_RECT, np.zeros((3, 1))])
    P1 = P0.copy()
    P1[0, 3] = -K_RECT[0, 0] * baseline
    K1 = K_CAM0 + np.array([[1.4, 0, 3.1], [0, 1.2, -7.4], [0, 0, 0]])
    D1 = D_CAM0 * 0.95
    T1 = T01 @ _orthonormal_T(T_CAM0_FROM_OS1)
    return {
        "cam0": (K_CAM0, D_CAM0, R0, P0, _orthonormal_T(T_CAM0_FROM_OS1)),
        "cam1": (K1, D1, R1, P1, T1),
        "T01": T01,
        "baseline": baseline,
    }


def _orthonormal_T(T: np.ndarray) -> np.ndarray:
    out = np.array(T, dtype=np.float64)
    out[:3, :3] = _orthonormal(out[:3, :3])
    return out


def write_calibration(root: Path, seq: int, base_file: bool = True) -> dict:
    cal = root / "calibrations" / str(seq)
    cal.mkdir(parents=True, exist_ok=True)
    st = stereo_calibration()
    for cam in ("cam0", "cam1"):
        K, D, R, P, T = st[cam]
        (cal / f"calib_{cam}_intrinsics.yaml").write_text(
            yaml.safe_dump(
                {
                    "image_width": 1224,
                    "image_height": 1024,
                    "camera_name": f"narrow_stereo/{cam}",
                    "camera_matrix": _matrix(3, 3, K),
                    "distortion_model": "plumb_bob",
                    "distortion_coefficients": _matrix(1, 5, D),
                    "rectification_matrix": _matrix(3, 3, R),
                    "projection_matrix": _matrix(3, 4, P),
                }
            )
        )
        if (
            cam == "cam0"
        ):  # cam1's os1 extrinsic: derived from cam0 and cam0_to_cam1, as the devkit does
            (cal / f"calib_os1_to_{cam}.yaml").write_text(
                yaml.safe_dump({"extrinsic_matrix": _matrix(4, 4, T)})
            )
    T01 = st["T01"]
    (cal / "calib_cam0_to_cam1.yaml").write_text(
        yaml.safe_dump(
            {
                "extrinsic_matrix": {
                    "R": _matrix(3, 3, T01[:3, :3]),
                    "T": [float(v) for v in T01[:3, 3]],
                }
            }
        )
    )
    if base_file:
        T_base = np.eye(4)
        T_base[2, 3] = 0.9
        (cal / "calib_os1_to_base.yaml").write_text(
            yaml.safe_dump({"extrinsic_matrix": _matrix(4, 4, T_base)})
        )
    return st


def pedestrian_box(track: int = 3, **overrides) -> dict:
    box = {
        "classId": "Pedestrian",
        "instanceId": f"Pedestrian:{track}",
        "labelAttributes": {"isOccluded": "Light"},
        "cX": 5.0,
        "cY": 1.0,
        "cZ": 0.0,
        "l": 2.0,
        "w": 0.5,
        "h": 1.8,
        "r": 0.0,
        "p": 0.0,
        "y": float(np.pi / 2),
    }
    box.update(overrides)
    return box


def make_coda(
    root: Path,
    seq: int = 0,
    frames: int = 4,
    channels: int = 5,
    image_ext: str = ".jpg",
    pose_folder: str = "dense_global",
    lidar_source: str = "3d_comp",
    present=None,
    base_file: bool = True,
    boxes: list[dict] | None = None,
    intensity_zero: bool = False,
    metadata: dict | None = None,
    image_size: tuple[int, int] | None = None,
) -> Path:
    """Write a sequence of ``frames`` raw frames (timestamps and poses for all of them; sweeps,
    images, boxes and terrain labels for the frames in ``present``, default all) under root.
    image_size: (width, height) of real (black) images; None writes placeholder bytes."""
    rng = np.random.default_rng(seq)
    s = str(seq)
    present = list(range(frames)) if present is None else sorted(present)
    for f in present:
        pts = np.zeros((POINTS, channels), np.float32)
        n = 2000  # a few returns; the rest are no-returns (zeros)
        idx = rng.choice(POINTS, n, replace=False)
        pts[idx, 0] = rng.uniform(2, 20, n)
        pts[idx, 1] = rng.uniform(-5, 5, n)
        pts[idx, 2] = rng.uniform(-1, 2, n)
        pts[idx[: n // 2], 2] = -0.9  # half the returns on the ground, 0.9 m below the sensor
        pts[idx, 3] = 0.0 if intensity_zero else rng.uniform(1, 255, n)
        if channels == 5:  # nanoseconds since the first column, as the devkit's decoder writes
            pts[:, 4] = np.tile(np.arange(1024) * 97_656.25, 128)
        path = root / lidar_source / "os1" / s / f"{lidar_source}_os1_{s}_{f}.bin"
        path.parent.mkdir(parents=True, exist_ok=True)
        pts.tofile(path)
        for cam in ("cam0", "cam1"):
            img = root / "2d_rect" / cam / s / f"2d_rect_{cam}_{s}_{f}{image_ext}"
            img.parent.mkdir(parents=True, exist_ok=True)
            if image_size is None:
                img.write_bytes(b"not-a-real-image")
            else:
                from PIL import Image

                Image.new("RGB", image_size).save(img)
        bp = root / "3d_bbox" / "os1" / s / f"3d_bbox_os1_{s}_{f}.json"
        bp.parent.mkdir(parents=True, exist_ok=True)
        bp.write_text(json.dumps({"3dbbox": boxes if boxes is not None else [pedestrian_box()]}))
        sp = root / "3d_semantic" / "os1" / s / f"3d_semantic_os1_{s}_{f}.bin"
        sp.parent.mkdir(parents=True, exist_ok=True)
        labels = np.zeros(POINTS, np.uint8)
        labels[idx] = np.where(pts[idx, 2] < 0, 1, 0)  # Concrete below the sensor, else Unlabeled
        labels.tofile(sp)
    stamps = 1.6e9 + 0.1 * np.arange(frames)
    (root / "timestamps").mkdir(parents=True, exist_ok=True)
    (root / "timestamps" / f"{s}.txt").write_text("".join(f"{t:.6f}\n" for t in stamps))
    (root / "poses" / pose_folder).mkdir(parents=True, exist_ok=True)
    (root / "poses" / pose_folder / f"{s}.txt").write_text(
        "".join(f"{t:.6f} {0.1 * k:.3f} 0 0 1 0 0 0\n" for k, t in enumerate(stamps))
    )
    write_calibration(root, seq, base_file)
    (root / "metadata").mkdir(parents=True, exist_ok=True)
    meta = {
        "lighting": "normal",
        "ObjectTracking": {
            "training": [f"3d_bbox/os1/{s}/3d_bbox_os1_{s}_{f}.json" for f in present],
            "validation": [],
            "testing": [],
        },
    }
    meta.update(metadata or {})
    (root / "metadata" / f"{s}.json").write_text(json.dumps(meta))
    return root
