"""CODa calibration files: camera intrinsics, extrinsics, the rectified pinhole, a sequence's
:class:`storage.sequence_data.Calibration`.

Cameras. ``2d_rect`` images are made by the devkit with ``cv2.initUndistortRectifyMap(K, D, R, P)``,
whose map uses ``P[:, :3] @ R`` (the 4th column of P is not read), so a LiDAR point x lands on the
rectified pixel ``P[:, :3] @ R @ T_cam_from_lidar @ x``. Each camera is therefore exposed as the
pinhole (``K = P[:, :3]``, ``T_cam_from_lidar = [[R, 0], [0, 1]] @ T_cam_from_lidar``) of its
rectified frame (storage.sequence_data.CameraCalibration); the files' values stay on ``.raw``.

Checked when read: finite numbers, rotations orthonormal with determinant +1, positive focal
lengths, whole positive image sizes; every error a CodaFormatError naming the file and the key.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from storage.files import InputError, read_text
from storage.sequence_data import Calibration, CameraCalibration, RawCameraCalibration
from storage.sources.coda.layout import ROTATION_TOLERANCE, CodaFormatError, _present
from tasks.bounds import MAX_CALIBRATION_TRANSLATION_M
from tasks.poses.rotations import quat_wxyz_to_matrix

__all__ = ["quat_wxyz_to_matrix", "read_calibration", "read_extrinsic", "read_intrinsics"]


def rectified_camera(
    R_rect: np.ndarray, P_rect: np.ndarray, T_cam_from_lidar: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The pinhole of a rectified image: (K (3, 3), T_rect_from_lidar (4, 4)) float64.

    R_rect (3, 3) rectification_matrix, P_rect (3, 4) projection_matrix, T_cam_from_lidar (4, 4)
    the raw camera's extrinsic. ``initUndistortRectifyMap(K, D, R, P)`` maps the rectified pixel
    (u, v) through ``(P[:, :3] @ R)^-1``, so K = P[:, :3] and T_rect_from_lidar = [[R, 0], [0, 1]]
    @ T_cam_from_lidar; P's 4th column (-fx * baseline on the right camera of a stereo pair)
    belongs to projecting points given in the *left* rectified frame and is not used here.
    """
    K = np.array(P_rect, dtype=np.float64)[:, :3].copy()
    R4 = np.eye(4)
    R4[:3, :3] = R_rect
    return K, R4 @ np.asarray(T_cam_from_lidar, dtype=np.float64)


def read_calibration(
    folder: Path,
    cameras_wanted: tuple[str, ...],
    image_source: str,
    lidar_height_m: float | None,
    warnings: list[str],
) -> Calibration:
    """The calibration of one sequence from its ``calibrations/{SEQ}/`` folder.

    Each camera is exposed as the pinhole of its image source: ``2d_rect`` through
    :func:`rectified_camera`, ``2d_raw`` as the raw camera (its distortion noted in ``warnings``).
    cam0 is required, the others optional; cam1's extrinsic may come from ``calib_cam0_to_cam1``
    (as the devkit's gen_calibrations.py). Without ``calib_os1_to_base.yaml``,
    ``lidar_height_m`` gives T_base_from_lidar (a pure lift, noted in ``warnings``); None makes
    the file required.
    """
    c01_path = folder / "calib_cam0_to_cam1.yaml"
    T_cam1_from_cam0 = read_extrinsic(c01_path)[0] if _present(c01_path) else None
    cameras = {}
    for cam in cameras_wanted:
        intr_path = folder / f"calib_{cam}_intrinsics.yaml"
        ext_path = folder / f"calib_os1_to_{cam}.yaml"
        if cam != "cam0" and not _present(intr_path):
            continue  # only cam0 is required
        intr = read_intrinsics(intr_path)
        if _present(ext_path):
            T, P_l2r = read_extrinsic(ext_path)
        elif cam == "cam1" and T_cam1_from_cam0 is not None and "cam0" in cameras:
            # as the devkit's gen_calibrations.py: T_os1_to_cam1 = T_cam0_to_cam1 @ T_os1_to_cam0
            T, P_l2r = T_cam1_from_cam0 @ cameras["cam0"].raw.T_cam_from_lidar, None
        else:
            T, P_l2r = read_extrinsic(ext_path)  # raises: file is missing
        raw = RawCameraCalibration(intr["K"], intr["distortion"], intr["R"], intr["P"], T, P_l2r)
        if image_source == "2d_rect":
            if not intr["has_rect"]:
                warnings.append(
                    f"{intr_path}: no rectification_matrix / projection_matrix; 2d_rect "
                    "images are projected with camera_matrix and the raw extrinsic"
                )
            K, T_cam = rectified_camera(intr["R"], intr["P"], T)
            cameras[cam] = CameraCalibration(
                cam, K, np.zeros(5), intr["width"], intr["height"], T_cam, raw, rectified=True
            )
        else:
            if np.any(intr["distortion"] != 0):
                warnings.append(
                    f"{cam}: 2d_raw images are distorted ({intr_path.name} k1={intr['distortion'][0]:.4g}) "
                    "and the pipeline projects with a pinhole; use 2d_rect"
                )
            cameras[cam] = CameraCalibration(
                cam,
                intr["K"],
                intr["distortion"],
                intr["width"],
                intr["height"],
                T,
                raw,
                rectified=False,
            )
    base_path = folder / "calib_os1_to_base.yaml"
    if _present(base_path) or lidar_height_m is None:
        T_base, base_default = read_extrinsic(base_path)[0], False
    else:
        T_base, base_default = np.eye(4), True
        T_base[2, 3] = float(lidar_height_m)
        warnings.append(
            f"{base_path} is missing: T_base_from_lidar = the LiDAR "
            f"{lidar_height_m:g} m above the ground, axes aligned "
            "(dataset.lidar_height_m)"
        )
    return Calibration(
        cameras=cameras,
        T_base_from_lidar=T_base,
        base_is_default=base_default,
        T_cam1_from_cam0=T_cam1_from_cam0,
    )


def read_intrinsics(path: Path) -> dict:
    """A ``calib_{cam}_intrinsics.yaml`` -> dict(width, height, K (3, 3), distortion (5,), R (3, 3),
    P (3, 4), has_rect). R defaults to identity and P to [K | 0] where the file lacks them
    (has_rect False)."""
    data = _read_yaml(path)
    K = _yaml_matrix(data, "camera_matrix", (3, 3), path)
    dist = _yaml_matrix(data, "distortion_coefficients", None, path).reshape(-1)
    if dist.size not in (4, 5, 8):
        raise CodaFormatError(
            f"{path}: distortion_coefficients has {dist.size} values, expected 5 "
            "(plumb_bob k1 k2 p1 p2 k3)"
        )
    if np.any(dist[5:] != 0):
        raise CodaFormatError(
            f"{path}: distortion_coefficients {dist.tolist()}: only plumb_bob "
            "(k1 k2 p1 p2 k3) is supported"
        )
    dist = np.pad(dist[:5], (0, 5 - min(dist.size, 5)))
    width = _positive_int(data, "image_width", path)
    height = _positive_int(data, "image_height", path)
    has_rect = "rectification_matrix" in data and "projection_matrix" in data
    R = (
        _yaml_matrix(data, "rectification_matrix", (3, 3), path)
        if "rectification_matrix" in data
        else np.eye(3)
    )
    _check_rotation(R, path, "rectification_matrix")
    P = (
        _yaml_matrix(data, "projection_matrix", (3, 4), path)
        if "projection_matrix" in data
        else np.hstack([K, np.zeros((3, 1))])
    )
    for name, M in (("camera_matrix", K), ("projection_matrix", P)):
        if not (M[0, 0] > 0 and M[1, 1] > 0 and np.allclose(M[2, :3], [0, 0, 1])):
            raise CodaFormatError(
                f"{path}: {name} {M.tolist()} is not a camera matrix "
                "(expected fx, fy > 0 and a last row 0 0 1)"
            )
    return {
        "width": width,
        "height": height,
        "K": K,
        "distortion": dist,
        "R": R,
        "P": P,
        "has_rect": has_rect,
    }


def read_extrinsic(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """An extrinsic YAML -> (T_target_from_source (4, 4) float64, projection_matrix (3, 4) or None).

    ``extrinsic_matrix`` is either ``{rows: 4, cols: 4, data: [16]}`` (row-major; 3 x 4 accepted)
    or, as CODa's ``calib_cam0_to_cam1.yaml``, ``{R: {rows: 3, cols: 3, data: [9]}, T: [3]}``.
    A top-level ``projection_matrix`` (3 x 4, the devkit's P R T) is returned when present.
    """
    data = _read_yaml(path)
    node = _yaml_key(data, "extrinsic_matrix", path)
    T = np.eye(4)
    if isinstance(node, dict) and "R" in node and "T" in node:
        T[:3, :3] = _yaml_matrix(node, "R", (3, 3), path, "extrinsic_matrix.R")
        T[:3, 3] = _yaml_matrix(node, "T", (3, 1), path, "extrinsic_matrix.T").reshape(3)
    else:
        values = _yaml_matrix(data, "extrinsic_matrix", None, path).reshape(-1)
        if values.size not in (12, 16):
            raise CodaFormatError(
                f"{path}: extrinsic_matrix has {values.size} values, expected 4x4 "
                "(rows/cols/data) or {R: 3x3, T: [3]}"
            )
        T[:3] = values[:12].reshape(3, 4)
        if values.size == 16 and not np.allclose(values[12:], [0, 0, 0, 1], atol=1e-9):
            raise CodaFormatError(
                f"{path}: extrinsic_matrix last row {values[12:].tolist()}, expected 0 0 0 1"
            )
    _check_rotation(T[:3, :3], path, "extrinsic_matrix rotation")
    length = float(np.linalg.norm(T[:3, 3]))
    if length > MAX_CALIBRATION_TRANSLATION_M:  # tasks/bounds.py
        raise CodaFormatError(
            f"{path}: extrinsic_matrix translation is {length:.6g} m, more than the "
            f"{MAX_CALIBRATION_TRANSLATION_M:g} m a sensor rig spans",
            path,
        )
    P = (
        _yaml_matrix(data, "projection_matrix", (3, 4), path)
        if "projection_matrix" in data
        else None
    )
    return T, P


def _check_rotation(R: np.ndarray, path: Path, name: str) -> None:
    """A rotation: orthonormal (R R^T = I) with determinant +1, within ROTATION_TOLERANCE."""
    err = float(np.max(np.abs(R @ R.T - np.eye(3))))
    if err > ROTATION_TOLERANCE:
        raise CodaFormatError(
            f"{path}: {name} is not orthonormal (max |R R^T - I| = {err:.3g}, a scaled, sheared "
            f"or zero matrix): {np.round(R, 6).tolist()}",
            path,
        )
    det = float(np.linalg.det(R))
    if abs(det - 1.0) > ROTATION_TOLERANCE:
        raise CodaFormatError(
            f"{path}: {name} has determinant {det:.4f}, expected +1 (a reflection, not a "
            f"rotation): {np.round(R, 6).tolist()}",
            path,
        )


def _read_yaml(path: Path) -> dict:
    try:
        data = yaml.load(read_text(path, None, "calibration file"), Loader=_YamlLoader)
    except InputError as exc:
        raise CodaFormatError(str(exc), path) from None
    except yaml.YAMLError as exc:
        raise CodaFormatError(f"{path}: invalid YAML ({exc})", path) from None
    if not isinstance(data, dict):
        raise CodaFormatError(f"{path}: expected a YAML mapping", path)
    return data


#: libyaml's safe loader where PyYAML has it (the calibration files are parsed at every open)
_YamlLoader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def _yaml_key(data: dict, key: str, path: Path, name: str | None = None):
    if key not in data:
        raise CodaFormatError(f"{path}: calibration key {name or key!r} is missing")
    return data[key]


def _positive_int(data: dict, key: str, path: Path) -> int:
    value = _yaml_key(data, key, path)
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float))
        or value <= 0
        or value != int(value)
    ):
        raise CodaFormatError(
            f"{path}: {key} is {value!r}, expected a positive whole number of pixels"
        )
    return int(value)


def _yaml_matrix(
    data: dict, key: str, shape: tuple[int, int] | None, path: Path, name: str | None = None
) -> np.ndarray:
    name = name or key
    node = _yaml_key(data, key, path, name)
    values = node.get("data") if isinstance(node, dict) else node
    try:
        arr = np.asarray(values, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise CodaFormatError(f"{path}: {name} is not a list of numbers") from None
    if shape is not None:
        if arr.size != shape[0] * shape[1]:
            raise CodaFormatError(
                f"{path}: {name} has {arr.size} values, expected {shape[0]}x{shape[1]}"
            )
        arr = arr.reshape(shape)
    if not np.isfinite(arr).all():
        raise CodaFormatError(f"{path}: {name} has non-finite values")
    return arr
