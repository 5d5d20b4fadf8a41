"""Write a sequence in the CODa raw layout, as the CODa downloads hold it (ut-amrl/coda-devkit,
docs/DATA_REPORT.md).

Under ``root``: ``3d_comp/os1/{SEQ}/3d_comp_os1_{SEQ}_{FRAME}.bin`` (131072 x 5 float32 x y z
intensity t, t in nanoseconds since the sweep's first column as the devkit's decoder writes it,
zeros for no return), ``2d_rect/{cam}/{SEQ}/2d_rect_{cam}_{SEQ}_{FRAME}.jpg`` (or ``.png``),
``3d_bbox/os1/{SEQ}/3d_bbox_os1_{SEQ}_{FRAME}.json``, ``3d_semantic/os1/{SEQ}/3d_semantic_os1_{SEQ}_
{FRAME}.bin`` (one CODa terrain id per point), ``calibrations/{SEQ}/*.yaml`` (raw intrinsics with
the stereo rectification R and projection P; os1 -> camera extrinsics of the raw camera frames;
``calib_cam0_to_cam1.yaml`` in CODa's ``{R, T}`` form), ``poses/dense_global/{SEQ}.txt``,
``timestamps/{SEQ}.txt``, ``metadata/{SEQ}.json``.

SEQ and FRAME are integers without padding. Every file is written to a temporary name and renamed,
so a killed run never leaves a truncated file under its final name; the bytes depend only on the
inputs (JPEG / PNG via Pillow, JSON with sorted keys, YAML via safe_dump).
"""

from __future__ import annotations

import json
from io import BytesIO
from pathlib import Path

import numpy as np
import yaml
from PIL import Image

from storage.atomic import atomic_write_bytes
from storage.sequence_data import Box3D, Calibration

NUM_POINTS = 128 * 1024
CHANNELS = 5
LIDAR_SOURCE = "3d_comp"
IMAGE_EXTS = (".jpg", ".png")
JPEG_QUALITY = 95


def _name(root: Path, modality: str, sensor: str, seq: int, frame: int, ext: str) -> Path:
    return Path(root) / modality / sensor / str(seq) / f"{modality}_{sensor}_{seq}_{frame}{ext}"


def lidar_path(root: Path, seq: int, frame: int, source: str = LIDAR_SOURCE) -> Path:
    return _name(root, source, "os1", seq, frame, ".bin")


def image_path(root: Path, seq: int, cam: str, frame: int, ext: str = ".jpg") -> Path:
    return _name(root, "2d_rect", cam, seq, frame, ext)


def bbox_path(root: Path, seq: int, frame: int) -> Path:
    return _name(root, "3d_bbox", "os1", seq, frame, ".json")


def semantic_path(root: Path, seq: int, frame: int) -> Path:
    return _name(root, "3d_semantic", "os1", seq, frame, ".bin")


def write_lidar(
    root: Path,
    seq: int,
    frame: int,
    points_lidar: np.ndarray,
    intensity: np.ndarray,
    time_s: np.ndarray,
) -> Path:
    """One organised sweep: points_lidar (131072, 3) float32 m (zeros = no return), intensity and
    time_s (131072,) float32 (seconds since the first column). Written as little-endian float32
    x y z intensity t with t in nanoseconds."""
    for name, a, shape in (
        ("points_lidar", points_lidar, (NUM_POINTS, 3)),
        ("intensity", intensity, (NUM_POINTS,)),
        ("time_s", time_s, (NUM_POINTS,)),
    ):
        if a.shape != shape:
            raise ValueError(
                f"sequence {seq} frame {frame}: {name} has shape {a.shape}, expected {shape}"
            )
    data = np.empty((NUM_POINTS, CHANNELS), dtype="<f4")
    data[:, :3] = points_lidar
    data[:, 3] = intensity
    data[:, 4] = np.round(np.asarray(time_s, np.float64) * 1e9)
    return atomic_write_bytes(lidar_path(root, seq, frame), data.tobytes())


def image_bytes(image: np.ndarray, ext: str = ".png") -> bytes:
    """PNG (any of (H, W, 3) uint8, (H, W) uint8 / uint16) or JPEG ((H, W, 3) uint8) bytes."""
    pil = Image.fromarray(np.ascontiguousarray(image))
    buf = BytesIO()
    if ext == ".png":
        pil.save(buf, format="PNG", compress_level=6)
    elif ext == ".jpg":
        pil.save(buf, format="JPEG", quality=JPEG_QUALITY)
    else:
        raise ValueError(f"image extension {ext!r}: expected one of {IMAGE_EXTS}")
    return buf.getvalue()


def write_image(
    root: Path, seq: int, cam: str, frame: int, rgb: np.ndarray, ext: str = ".jpg"
) -> Path:
    """A rectified image (H, W, 3) uint8 RGB as JPEG (CODa's downloads) or PNG (the devkit's tools)."""
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(
            f"sequence {seq} frame {frame} {cam}: expected (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}"
        )
    return atomic_write_bytes(image_path(root, seq, cam, frame, ext), image_bytes(rgb, ext))


def write_semantic(root: Path, seq: int, frame: int, ids: np.ndarray) -> Path:
    """A 3d_semantic file: (131072,) uint8 CODa terrain ids, one per organised point."""
    ids = np.asarray(ids)
    if ids.shape != (NUM_POINTS,) or ids.dtype != np.uint8:
        raise ValueError(
            f"sequence {seq} frame {frame}: semantic ids {ids.shape} {ids.dtype}, "
            f"expected ({NUM_POINTS},) uint8"
        )
    return atomic_write_bytes(semantic_path(root, seq, frame), ids.tobytes())


def box_record(box: Box3D) -> dict:
    """A Box3D as a CODa 3d_bbox json record."""
    cx, cy, cz = (float(v) for v in box.center)
    l, w, h = (float(v) for v in box.size)
    r, p, y = (float(v) for v in box.rpy)
    return {
        "classId": box.class_name,
        "instanceId": box.instance_id,
        "labelAttributes": {"isOccluded": box.occlusion},
        "cX": _r6(cx),
        "cY": _r6(cy),
        "cZ": _r6(cz),
        "l": _r6(l),
        "w": _r6(w),
        "h": _r6(h),
        "r": _r6(r),
        "p": _r6(p),
        "y": _r6(y),
    }


def _r6(v: float) -> float:
    """6 decimals (micrometres, microradians) keep the json small and readable."""
    return round(float(v), 6)


def write_boxes(root: Path, seq: int, frame: int, boxes: list[Box3D]) -> Path:
    """The 3D boxes of a frame (os1 frame) as CODa json ``{"3dbbox": [...]}``."""
    doc = {"3dbbox": [box_record(b) for b in boxes]}
    return atomic_write_bytes(
        bbox_path(root, seq, frame), (json.dumps(doc, sort_keys=True, indent=1) + "\n").encode()
    )


def _matrix(a: np.ndarray) -> dict:
    a = np.asarray(a, dtype=np.float64)
    return {
        "rows": int(a.shape[0]),
        "cols": int(a.shape[1]),
        "data": [float(v) for v in a.reshape(-1)],
    }


def _yaml(path: Path, doc: dict) -> Path:
    return atomic_write_bytes(
        path, yaml.safe_dump(doc, sort_keys=True, default_flow_style=None).encode()
    )


def write_calibration(root: Path, seq: int, calib: Calibration) -> list[Path]:
    """The calibration files of a sequence, as CODa's.

    A camera with ``raw`` (storage.sequence_data.RawCameraCalibration) is written from it:
    intrinsics K, D, rectification R and projection P, and the raw camera's extrinsic; one without
    is written as an already rectified camera (K, R = I, P = [K | p4]). p4 = -fx * baseline on
    cam1 (ROS / OpenCV stereo convention), 0 on cam0. Also os1 -> base and, with cam1, cam0 -> cam1
    as ``{R, T}``."""
    d = Path(root) / "calibrations" / str(seq)
    out = []
    cam0 = calib.cameras["cam0"]
    raw_T = {}
    for name, cam in calib.cameras.items():
        T_rect_from_rect0 = cam.T_cam_from_lidar @ np.linalg.inv(cam0.T_cam_from_lidar)
        if cam.raw is not None:
            K, D, R, P, T_raw = (
                cam.raw.K,
                cam.raw.distortion,
                cam.raw.R_rect,
                cam.raw.P_rect,
                cam.raw.T_cam_from_lidar,
            )
        else:
            K, D, R, T_raw = cam.K, cam.distortion, np.eye(3), cam.T_cam_from_lidar
            P = np.hstack([cam.K, np.zeros((3, 1))])
            P[0, 3] = cam.K[0, 0] * T_rect_from_rect0[0, 3]  # rectified stereo: Tx = -fx * baseline
        raw_T[name] = T_raw
        out.append(
            _yaml(
                d / f"calib_{name}_intrinsics.yaml",
                {
                    "camera_name": name,
                    "image_width": int(cam.width),
                    "image_height": int(cam.height),
                    "camera_matrix": _matrix(K),
                    "distortion_model": "plumb_bob",
                    "distortion_coefficients": _matrix(np.asarray(D, float).reshape(1, 5)),
                    "rectification_matrix": _matrix(R),
                    "projection_matrix": _matrix(P),
                },
            )
        )
        out.append(_yaml(d / f"calib_os1_to_{name}.yaml", {"extrinsic_matrix": _matrix(T_raw)}))
    if "cam1" in calib.cameras:
        T = raw_T["cam1"] @ np.linalg.inv(raw_T["cam0"])
        out.append(
            _yaml(
                d / "calib_cam0_to_cam1.yaml",
                {"extrinsic_matrix": {"R": _matrix(T[:3, :3]), "T": [float(v) for v in T[:3, 3]]}},
            )
        )
    out.append(
        _yaml(d / "calib_os1_to_base.yaml", {"extrinsic_matrix": _matrix(calib.T_base_from_lidar)})
    )
    return out


def _stamp_str(stamp_ns: int) -> str:
    """Unix seconds with 6 decimals, exact from integer nanoseconds."""
    stamp_ns = int(stamp_ns)
    return f"{stamp_ns // 1_000_000_000}.{(stamp_ns % 1_000_000_000) // 1000:06d}"


def write_timestamps(root: Path, seq: int, stamps_ns: np.ndarray) -> Path:
    """timestamps/{SEQ}.txt: one Unix time in seconds (%.6f) per frame."""
    text = "".join(_stamp_str(s) + "\n" for s in stamps_ns)
    return atomic_write_bytes(Path(root) / "timestamps" / f"{seq}.txt", text.encode())


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
    return atomic_write_bytes(
        Path(root) / "poses" / "dense_global" / f"{seq}.txt", "".join(lines).encode()
    )


def annotation_lists(seq: int, bbox_frames, semantic_frames) -> dict:
    """The metadata's ObjectTracking / SemanticSegmentation lists (paths relative to the root,
    all under "training") for the frames that have 3d_bbox / 3d_semantic files."""
    rel = lambda p: str(p.as_posix())  # noqa: E731
    return {
        "ObjectTracking": {
            "training": [rel(bbox_path(Path(), seq, f)) for f in bbox_frames],
            "validation": [],
            "testing": [],
        },
        "SemanticSegmentation": {
            "training": [rel(semantic_path(Path(), seq, f)) for f in semantic_frames],
            "validation": [],
            "testing": [],
        },
    }


def write_metadata(root: Path, seq: int, metadata: dict) -> Path:
    """metadata/{SEQ}.json (sorted keys)."""
    return atomic_write_bytes(
        Path(root) / "metadata" / f"{seq}.json",
        (json.dumps(metadata, sort_keys=True, indent=1) + "\n").encode(),
    )


# ---------------------------------------------------------------- read-back (tests, show)
def _existing(candidates: list[Path]) -> Path:
    for p in candidates:
        if p.exists():
            return p
    raise FileNotFoundError(
        f"{candidates[0]}: missing (also looked for {', '.join(p.name for p in candidates[1:])})"
    )


def read_lidar(root: Path, seq: int, frame: int) -> np.ndarray:
    """(131072, 5) float32 x y z intensity t (ns) of a written sweep (3d_comp, else 3d_raw)."""
    path = _existing([lidar_path(root, seq, frame, s) for s in (LIDAR_SOURCE, "3d_raw")])
    data = np.fromfile(path, dtype="<f4")
    if data.size != NUM_POINTS * CHANNELS:
        raise ValueError(f"{path}: {data.size} floats, expected {NUM_POINTS * CHANNELS}")
    return data.reshape(NUM_POINTS, CHANNELS)


def read_image(root: Path, seq: int, cam: str, frame: int) -> np.ndarray:
    """(H, W, 3) uint8 of a written rectified image (.jpg or .png)."""
    path = _existing([image_path(root, seq, cam, frame, e) for e in IMAGE_EXTS])
    return np.asarray(Image.open(path).convert("RGB"))


def read_camera(root: Path, seq: int, cam: str = "cam0") -> tuple[np.ndarray, np.ndarray]:
    """(K (3, 3), T_cam_from_lidar (4, 4)) float64 of the rectified camera of a written calibration
    (storage.coda.rectified_camera: the pinhole that projects onto the 2d_rect image)."""
    from storage.coda import read_extrinsic, read_intrinsics, rectified_camera

    d = Path(root) / "calibrations" / str(seq)
    intr = read_intrinsics(d / f"calib_{cam}_intrinsics.yaml")
    T_raw, _ = read_extrinsic(d / f"calib_os1_to_{cam}.yaml")
    return rectified_camera(intr["R"], intr["P"], T_raw)
