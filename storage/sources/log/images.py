"""Camera images of robot logs: ``sensor_msgs/CompressedImage`` and ``sensor_msgs/Image`` to RGB,
and raw images undistorted and rectified with their ``sensor_msgs/CameraInfo``.

CompressedImage: JPEG and PNG (``format`` "jpeg", "png", or image_transport's "bgr8; jpeg
compressed bgr8" forms), decoded with Pillow, as the CODa reader decodes image files (the same
bytes give the same pixels on both paths). Image: rgb8, bgr8, rgba8, bgra8, mono8, mono16 (the
high byte), and the 8-bit Bayer patterns (demosaiced with OpenCV); ``step`` padding is skipped.

Rectification (OpenCV, as ``image_proc`` does): ``cv2.initUndistortRectifyMap(K, D, R, P)`` maps
each rectified pixel through ``(P[:, :3] R)^-1``, so the rectified image is the pinhole ``K' =
P[:, :3]`` seen from the rectified camera frame ``[[R, 0], [0, 1]] T_cam_from_lidar`` (the same
convention as CODa's ``2d_rect``; P's 4th column, the stereo baseline term, is not used).
Distortion models: plumb_bob and rational_polynomial (cv2's 5- / 8-coefficient model), equidistant
(cv2.fisheye).
"""

from __future__ import annotations

from dataclasses import dataclass
from io import BytesIO

import numpy as np


class ImageDecodeError(ValueError):
    """An image message that cannot be decoded (the reader adds file, topic and stamp)."""


RAW_ENCODINGS = (
    "rgb8",
    "bgr8",
    "rgba8",
    "bgra8",
    "mono8",
    "mono16",
    "bayer_rggb8",
    "bayer_bggr8",
    "bayer_gbrg8",
    "bayer_grbg8",
)
DISTORTION_MODELS = ("plumb_bob", "rational_polynomial", "equidistant")


def decode_compressed(fmt: str, data) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a CompressedImage (``format``, ``data``)."""
    from PIL import Image, UnidentifiedImageError

    from storage.images import rgb8

    kind = fmt.lower()
    if "compresseddepth" in kind:
        raise ImageDecodeError(
            f"format {fmt!r} is a compressed depth image; expected a colour or mono JPEG / PNG"
        )
    if kind and not any(w in kind for w in ("jpeg", "jpg", "png")):
        raise ImageDecodeError(f"format {fmt!r}: expected jpeg or png")
    try:
        with Image.open(BytesIO(bytes(data))) as im:
            return rgb8(im)  # 16-bit PNGs scaled, never read as white
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as exc:
        raise ImageDecodeError(f"format {fmt!r}: image cannot be decoded ({exc})") from None


def decode_raw(encoding: str, height: int, width: int, step: int, data, bigendian=False):
    """(H, W, 3) uint8 RGB of a ``sensor_msgs/Image``."""
    enc = encoding.lower()
    if enc not in RAW_ENCODINGS:
        raise ImageDecodeError(
            f"encoding {encoding!r} is not supported; expected one of {', '.join(RAW_ENCODINGS)}"
        )
    channels = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4}.get(enc, 1)
    itemsize = 2 if enc == "mono16" else 1
    row = width * channels * itemsize
    buf = np.frombuffer(bytes(data) if not isinstance(data, np.ndarray) else data, np.uint8)
    if step < row or buf.size < height * step:
        raise ImageDecodeError(
            f"{encoding} {width} x {height}: step {step} and {buf.size} data bytes; expected "
            f"step >= {row} and {height} x step bytes (a cut message?)"
        )
    rows = buf[: height * step].reshape(height, step)[:, :row]
    if enc == "mono16":
        px = rows.copy().view(">u2" if bigendian else "<u2").reshape(height, width)
        gray = (px >> 8).astype(np.uint8)
        return np.repeat(gray[:, :, None], 3, axis=2)
    img = np.ascontiguousarray(rows).reshape(height, width, channels)
    if enc == "rgb8":
        return img
    if enc in ("bgr8", "bgra8"):
        return np.ascontiguousarray(img[:, :, 2::-1])
    if enc == "rgba8":
        return np.ascontiguousarray(img[:, :, :3])
    if enc == "mono8":
        return np.repeat(img, 3, axis=2)
    import cv2

    code = {
        "bayer_rggb8": cv2.COLOR_BayerRGGB2RGB,
        "bayer_bggr8": cv2.COLOR_BayerBGGR2RGB,
        "bayer_gbrg8": cv2.COLOR_BayerGBRG2RGB,
        "bayer_grbg8": cv2.COLOR_BayerGRBG2RGB,
    }[enc]
    # OpenCV's *RGGB* names give the pattern from the top-left pixel, as ROS's encodings do
    return cv2.cvtColor(img[:, :, 0], code)


@dataclass(frozen=True)
class CameraInfo:
    """A ``sensor_msgs/CameraInfo``: width, height px; K (3, 3), D (n,), R (3, 3), P (3, 4)
    float64; distortion_model; frame_id (the camera's optical frame)."""

    width: int
    height: int
    K: np.ndarray
    D: np.ndarray
    R: np.ndarray
    P: np.ndarray
    distortion_model: str
    frame_id: str

    def needs_rectifying(self) -> bool:
        """Whether raw images of this camera differ from the rectified pinhole P[:, :3]."""
        return bool(
            np.any(self.D != 0)
            or not np.allclose(self.R, np.eye(3), atol=0, rtol=0)
            or not np.array_equal(self.P[:, :3], self.K)
        )

    def check(self) -> str | None:
        """What is wrong with it (None when usable): sizes, matrices, distortion model."""
        if self.width <= 0 or self.height <= 0:
            return f"image size {self.width} x {self.height} (an uncalibrated camera?)"
        for name, M in (("K", self.K), ("P", self.P[:, :3])):
            if not (M[0, 0] > 0 and M[1, 1] > 0 and np.allclose(M[2], [0, 0, 1])):
                return f"{name} {M.tolist()} is not a camera matrix (fx, fy > 0, last row 0 0 1)"
        if not np.isfinite(self.D).all() or not np.isfinite(self.P).all():
            return "non-finite D or P"
        if np.any(self.D != 0) and self.distortion_model not in DISTORTION_MODELS:
            return (
                f"distortion_model {self.distortion_model!r}; expected one of "
                f"{', '.join(DISTORTION_MODELS)}"
            )
        err = float(np.max(np.abs(self.R @ self.R.T - np.eye(3))))
        if err > 1e-3:
            return f"R is not a rotation (max |R R^T - I| = {err:.3g})"
        return None


class Rectifier:
    """Undistort and rectify raw images of one camera (maps made once)."""

    def __init__(self, info: CameraInfo):
        import cv2

        size = (info.width, info.height)
        P = np.asarray(info.P, np.float64)[:, :3]
        if info.distortion_model == "equidistant":
            self.maps = cv2.fisheye.initUndistortRectifyMap(
                info.K, info.D[:4], info.R, P, size, cv2.CV_32FC1
            )
        else:
            self.maps = cv2.initUndistortRectifyMap(info.K, info.D, info.R, P, size, cv2.CV_32FC1)
        self.size = size

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        import cv2

        return cv2.remap(rgb, self.maps[0], self.maps[1], cv2.INTER_LINEAR)
