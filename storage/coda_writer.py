"""Write a sequence in the CODa raw layout (see /work/shared/reference/coda-and-formats.md).

Under ``root``: ``3d_raw/os1/{SEQ}/3d_raw_os1_{SEQ}_{FRAME}.bin`` (131072 x 5 float32 x y z
intensity time, zeros for no return), ``2d_rect/{cam}/{SEQ}/2d_rect_{cam}_{SEQ}_{FRAME}.png``,
``3d_bbox/os1/{SEQ}/3d_bbox_os1_{SEQ}_{FRAME}.json``, ``calibrations/{SEQ}/*.yaml``,
``poses/dense_global/{SEQ}.txt``, ``timestamps/{SEQ}.txt``, ``metadata/{SEQ}.json``.
SEQ and FRAME are integers without padding. Every file is written to a temporary name and renamed,
so a killed run never leaves a truncated file under its final name; the bytes depend only on the
inputs (PNG via Pillow, JSON with sorted keys, YAML via safe_dump).
"""

from __future__ import annotations

import json
import os
from io import BytesIO
from pathlib import Path

import numpy as np
import yaml
from PIL import Image

from storage.model import Box3D, Calibration

NUM_POINTS = 128 * 1024
CHANNELS = 5


def _atomic_write(path: Path, data: bytes) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_bytes(data)
    os.replace(tmp, path)
    return path


def lidar_path(root: Path, seq: int, frame: int) -> Path:
    return Path(root) / "3d_raw" / "os1" / str(seq) / f"3d_raw_os1_{seq}_{frame}.bin"


def image_path(root: Path, seq: int, cam: str, frame: int) -> Path:
    return Path(root) / "2d_rect" / cam / str(seq) / f"2d_rect_{cam}_{seq}_{frame}.png"


def bbox_path(root: Path, seq: int, frame: int) -> Path:
    return Path(root) / "3d_bbox" / "os1" / str(seq) / f"3d_bbox_os1_{seq}_{frame}.json"


def write_lidar(root: Path, seq: int, frame: int, points_lidar: np.ndarray, intensity: np.ndarray,
                time_s: np.ndarray) -> Path:
    """One organised sweep: points_lidar (131072, 3) float32 m (zeros = no return), intensity and
    time_s (131072,) float32. Written as little-endian float32 x y z intensity time."""
    for name, a, shape in (("points_lidar", points_lidar, (NUM_POINTS, 3)),
                           ("intensity", intensity, (NUM_POINTS,)), ("time_s", time_s, (NUM_POINTS,))):
        if a.shape != shape:
            raise ValueError(f"sequence {seq} frame {frame}: {name} has shape {a.shape}, expected {shape}")
    data = np.empty((NUM_POINTS, CHANNELS), dtype="<f4")
    data[:, :3] = points_lidar
    data[:, 3] = intensity
    data[:, 4] = time_s
    return _atomic_write(lidar_path(root, seq, frame), data.tobytes())


def png_bytes(image: np.ndarray) -> bytes:
    """PNG of an (H, W, 3) uint8, (H, W) uint8 or (H, W) uint16 image."""
    pil = Image.fromarray(np.ascontiguousarray(image))
    buf = BytesIO()
    pil.save(buf, format="PNG", compress_level=6)
    return buf.getvalue()


def write_image(root: Path, seq: int, cam: str, frame: int, rgb: np.ndarray) -> Path:
    """A rectified image (H, W, 3) uint8 RGB as PNG."""
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"sequence {seq} frame {frame} {cam}: expected (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    return _atomic_write(image_path(root, seq, cam, frame), png_bytes(rgb))


def box_record(box: Box3D) -> dict:
    """A Box3D as a CODa 3d_bbox json record."""
    cx, cy, cz = (float(v) for v in box.center)
    l, w, h = (float(v) for v in box.size)
    r, p, y = (float(v) for v in box.rpy)
    return {"classId": box.class_name, "instanceId": box.instance_id,
            "labelAttributes": {"isOccluded": box.occlusion},
            "cX": _r6(cx), "cY": _r6(cy), "cZ": _r6(cz),
            "l": _r6(l), "w": _r6(w), "h": _r6(h),
            "r": _r6(r), "p": _r6(p), "y": _r6(y)}


def _r6(v: float) -> float:
    """6 decimals (micrometres, microradians) keep the json small and readable."""
    return round(float(v), 6)


def write_boxes(root: Path, seq: int, frame: int, boxes: list[Box3D]) -> Path:
    """The 3D boxes of a frame (os1 frame) as CODa json ``{"3dbbox": [...]}``."""
    doc = {"3dbbox": [box_record(b) for b in boxes]}
    return _atomic_write(bbox_path(root, seq, frame), (json.dumps(doc, sort_keys=True, indent=1) + "\n").encode())


def _matrix(a: np.ndarray) -> dict:
    a = np.asarray(a, dtype=np.float64)
    return {"rows": int(a.shape[0]), "cols": int(a.shape[1]), "data": [float(v) for v in a.reshape(-1)]}


def _yaml(path: Path, doc: dict) -> Path:
    return _atomic_write(path, yaml.safe_dump(doc, sort_keys=True, default_flow_style=None).encode())


def write_calibration(root: Path, seq: int, calib: Calibration) -> list[Path]:
    """Intrinsics (rectified: identity R, P = [K | 0] for cam0 and [K | -fx b] for cam1) and the
    extrinsics os1 -> cam0 / cam1 / base, plus cam0 -> cam1."""
    d = Path(root) / "calibrations" / str(seq)
    out = []
    cam0 = calib.cameras["cam0"]
    for name, cam in calib.cameras.items():
        T_cam_from_cam0 = cam.T_cam_from_lidar @ np.linalg.inv(cam0.T_cam_from_lidar)
        P = np.zeros((3, 4))
        P[:, :3] = cam.K
        P[0, 3] = cam.K[0, 0] * T_cam_from_cam0[0, 3]  # rectified stereo: Tx = -fx * baseline
        out.append(_yaml(d / f"calib_{name}_intrinsics.yaml", {
            "camera_name": name, "image_width": int(cam.width), "image_height": int(cam.height),
            "camera_matrix": _matrix(cam.K), "distortion_model": "plumb_bob",
            "distortion_coefficients": _matrix(np.asarray(cam.distortion, float).reshape(1, 5)),
            "rectification_matrix": _matrix(np.eye(3)), "projection_matrix": _matrix(P)}))
        out.append(_yaml(d / f"calib_os1_to_{name}.yaml", {"extrinsic_matrix": _matrix(cam.T_cam_from_lidar)}))
    if "cam1" in calib.cameras:
        T = calib.cameras["cam1"].T_cam_from_lidar @ np.linalg.inv(cam0.T_cam_from_lidar)
        out.append(_yaml(d / "calib_cam0_to_cam1.yaml", {"extrinsic_matrix": _matrix(T)}))
    out.append(_yaml(d / "calib_os1_to_base.yaml", {"extrinsic_matrix": _matrix(calib.T_base_from_lidar)}))
    return out


def _stamp_str(stamp_ns: int) -> str:
    """Unix seconds with 6 decimals, exact from integer nanoseconds."""
    stamp_ns = int(stamp_ns)
    return f"{stamp_ns // 1_000_000_000}.{(stamp_ns % 1_000_000_000) // 1000:06d}"


def write_timestamps(root: Path, seq: int, stamps_ns: np.ndarray) -> Path:
    """timestamps/{SEQ}.txt: one Unix time in seconds (%.6f) per frame."""
    text = "".join(_stamp_str(s) + "\n" for s in stamps_ns)
    return _atomic_write(Path(root) / "timestamps" / f"{seq}.txt", text.encode())


def write_poses(root: Path, seq: int, stamps_ns: np.ndarray, poses: np.ndarray) -> Path:
    """poses/dense_global/{SEQ}.txt: ``ts x y z qw qx qy qz`` per frame, T_world_from_os1."""
    from scipy.spatial.transform import Rotation

    if len(stamps_ns) != len(poses):
        raise ValueError(f"sequence {seq}: {len(stamps_ns)} stamps but {len(poses)} poses")
    lines = []
    for s, T in zip(stamps_ns, poses):
        x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
        q = np.array([w, x, y, z]) * (1.0 if w >= 0 else -1.0)
        vals = [*T[:3, 3], *q]
        lines.append(_stamp_str(s) + " " + " ".join(f"{v:.9f}" for v in vals) + "\n")
    return _atomic_write(Path(root) / "poses" / "dense_global" / f"{seq}.txt", "".join(lines).encode())


def write_metadata(root: Path, seq: int, metadata: dict) -> Path:
    """metadata/{SEQ}.json (sorted keys)."""
    return _atomic_write(Path(root) / "metadata" / f"{seq}.json",
                         (json.dumps(metadata, sort_keys=True, indent=1) + "\n").encode())


# ---------------------------------------------------------------- read-back (tests, show)
def read_lidar(root: Path, seq: int, frame: int) -> np.ndarray:
    """(131072, 5) float32 x y z intensity time of a written sweep."""
    path = lidar_path(root, seq, frame)
    data = np.fromfile(path, dtype="<f4")
    if data.size != NUM_POINTS * CHANNELS:
        raise ValueError(f"{path}: {data.size} floats, expected {NUM_POINTS * CHANNELS}")
    return data.reshape(NUM_POINTS, CHANNELS)


def read_image(root: Path, seq: int, cam: str, frame: int) -> np.ndarray:
    """(H, W, 3) uint8 of a written rectified image."""
    return np.asarray(Image.open(image_path(root, seq, cam, frame)).convert("RGB"))


def read_camera(root: Path, seq: int, cam: str = "cam0") -> tuple[np.ndarray, np.ndarray]:
    """(K (3, 3), T_cam_from_lidar (4, 4)) float64 of a written calibration."""
    d = Path(root) / "calibrations" / str(seq)
    intr = yaml.safe_load((d / f"calib_{cam}_intrinsics.yaml").read_text())
    extr = yaml.safe_load((d / f"calib_os1_to_{cam}.yaml").read_text())
    K = np.asarray(intr["camera_matrix"]["data"], float).reshape(3, 3)
    T = np.asarray(extr["extrinsic_matrix"]["data"], float).reshape(4, 4)
    return K, T
