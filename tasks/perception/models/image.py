"""Image operations the adapters share: letterbox, affine crops, paste-back, boxes, NMS.

Pixel convention: OpenCV (pixel (c, r) centred at (c, r)); see :mod:`tasks.perception.models`.
Resampling is bilinear (torch), as cv2.resize / cv2.warpAffine with INTER_LINEAR in the model
families' reference code; outside the image reads ``border`` (cv2's default 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from tasks.geometry import box_iou

#: ImageNet statistics in RGB order on 0-255 pixels (mmpose / mmseg / Mask2Former / CLIFF)
IMAGENET_MEAN = (123.675, 116.28, 103.53)
IMAGENET_STD = (58.395, 57.12, 57.375)


def check_image(image: np.ndarray) -> None:
    if (
        not isinstance(image, np.ndarray)
        or image.dtype != np.uint8
        or image.ndim != 3
        or image.shape[2] != 3
    ):
        got = f"{getattr(image, 'dtype', type(image).__name__)} {getattr(image, 'shape', '')}"
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got {got}")


def normalize(pixels: np.ndarray, mean, std, bgr: bool = False) -> np.ndarray:
    """(..., H, W, 3) RGB 0-255 -> (..., 3, H, W) float32 ``(x - mean) / std`` (channel order of
    mean / std: the model's, BGR when ``bgr``)."""
    x = np.asarray(pixels, np.float32)
    if bgr:
        x = x[..., ::-1]
    x = (x - np.asarray(mean, np.float32)) / np.asarray(std, np.float32)
    return np.ascontiguousarray(np.moveaxis(x, -1, -3))


def resize(array: np.ndarray, height: int, width: int) -> np.ndarray:
    """Bilinear resize (half-pixel centres, no antialias: cv2.INTER_LINEAR) of a (C, H, W) array
    to (C, height, width) float32."""
    t = torch.as_tensor(np.ascontiguousarray(array, np.float32))
    return F.interpolate(t[None], size=(height, width), mode="bilinear", align_corners=False)[
        0
    ].numpy()


@dataclass(frozen=True)
class Letterbox:
    """How an image was fitted into a model input: input = image * scale + (pad_x, pad_y)."""

    scale: float
    pad_x: float
    pad_y: float

    def to_image(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2) input pixels -> image pixels."""
        return (np.asarray(xy, np.float64) - [self.pad_x, self.pad_y]) / self.scale


def letterbox(
    image: np.ndarray, height: int, width: int, pad_value: float, center: bool
) -> tuple[np.ndarray, Letterbox]:
    """Fit an (H, W, 3) image into (height, width) keeping its aspect ratio.

    scale = min(height / H, width / W); the resized image (int(W * scale) x int(H * scale), as
    YOLOX rounds) sits at the top-left (YOLOX) or centred (MediaPipe), the rest is ``pad_value``.
    Returns the (height, width, 3) float32 input and the :class:`Letterbox` to map back.
    """
    check_image(image)
    H, W = image.shape[:2]
    s = min(height / H, width / W)
    rh, rw = int(H * s), int(W * s)
    resized = np.moveaxis(resize(np.moveaxis(image, -1, 0), rh, rw), 0, -1)
    out = np.full((height, width, 3), pad_value, np.float32)
    oy, ox = ((height - rh) // 2, (width - rw) // 2) if center else (0, 0)
    out[oy : oy + rh, ox : ox + rw] = resized
    return out, Letterbox(s, float(ox), float(oy))


def box_center_scale(
    boxes_xyxy: np.ndarray, aspect_w_over_h: float, padding: float
) -> tuple[np.ndarray, np.ndarray]:
    """Top-down crop boxes (mmpose ``bbox_xyxy2cs`` + ``_fix_aspect_ratio``): centre (N, 2) and
    size (N, 2) = (w, h) * padding, the short side grown to the model's aspect ratio."""
    b = np.asarray(boxes_xyxy, np.float64).reshape(-1, 4)
    center = (b[:, :2] + b[:, 2:]) / 2
    wh = (b[:, 2:] - b[:, :2]) * padding
    w = np.where(wh[:, 0] > wh[:, 1] * aspect_w_over_h, wh[:, 0], wh[:, 1] * aspect_w_over_h)
    h = np.where(wh[:, 0] > wh[:, 1] * aspect_w_over_h, wh[:, 0] / aspect_w_over_h, wh[:, 1])
    return center, np.stack([w, h], 1)


def crop_affine(
    center: np.ndarray,
    size: np.ndarray,
    out_hw: tuple[int, int],
    rotation: np.ndarray | None = None,
    *,
    udp: bool,
) -> np.ndarray:
    """Affine maps (N, 2, 3) from image pixels to crop pixels.

    center (N, 2) px, size (N, 2) = (w, h) px of the region, out_hw the crop's (height, width),
    rotation (N,) radians (the region's x axis turned by +rotation in the image: image v down, so
    positive turns clockwise on screen). Standard (mmpose ``get_warp_matrix``): the region's
    centre goes to (w_out / 2, h_out / 2), a length ``size`` to ``out``. UDP (``udp=True``, mmpose
    ``get_udp_warp_matrix``, ViTPose): a length ``size`` goes to ``out - 1`` and the centre to
    ((w_out - 1) / 2, (h_out - 1) / 2).
    """
    c = np.asarray(center, np.float64).reshape(-1, 2)
    s = np.asarray(size, np.float64).reshape(-1, 2)
    n = len(c)
    rot = np.zeros(n) if rotation is None else np.asarray(rotation, np.float64).reshape(n)
    h, w = out_hw
    span = np.array([w - 1, h - 1] if udp else [w, h], np.float64)
    k = span / s  # (N, 2) pixels of crop per pixel of image, along the region's axes
    cos, sin = np.cos(rot), np.sin(rot)
    A = np.zeros((n, 2, 3))
    # crop = K R^T (x - c) + span / 2, with R the rotation of the region's axes
    A[:, 0, 0], A[:, 0, 1] = k[:, 0] * cos, k[:, 0] * sin
    A[:, 1, 0], A[:, 1, 1] = -k[:, 1] * sin, k[:, 1] * cos
    A[:, :, 2] = span / 2 - np.einsum("nij,nj->ni", A[:, :, :2], c)
    return A


def invert_affine(A: np.ndarray) -> np.ndarray:
    """(N, 2, 3) -> the inverse maps (N, 2, 3)."""
    A = np.asarray(A, np.float64)
    Minv = np.linalg.inv(A[:, :, :2])
    return np.concatenate([Minv, -np.einsum("nij,nj->ni", Minv, A[:, :, 2])[:, :, None]], axis=2)


def apply_affine(A: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Points (N, K, 2) through maps (N, 2, 3) -> (N, K, 2) float64."""
    A = np.asarray(A, np.float64)
    return np.einsum("nij,nkj->nki", A[:, :, :2], np.asarray(xy, np.float64)) + A[:, None, :, 2]


def _sample(
    source: torch.Tensor, xs: torch.Tensor, ys: torch.Tensor, border: float
) -> torch.Tensor:
    """Bilinear samples of source (1, C, H, W) float32 at pixel coordinates xs, ys (h', w')."""
    H, W = source.shape[-2:]
    grid = torch.stack(
        [xs.float() * (2.0 / max(W - 1, 1)) - 1, ys.float() * (2.0 / max(H - 1, 1)) - 1], dim=-1
    )[None]
    if border:
        source = source - border
    out = F.grid_sample(source, grid, mode="bilinear", padding_mode="zeros", align_corners=True)[0]
    return out + border if border else out


def _grid(inv: np.ndarray, v0: int, v1: int, u0: int, u1: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Source coordinates (n, rows, cols) float32 of the pixels [v0, v1) x [u0, u1) through the
    maps ``inv`` (n, 2, 3) (destination -> source)."""
    inv = torch.as_tensor(np.asarray(inv, np.float64), dtype=torch.float32)
    gy, gx = torch.meshgrid(
        torch.arange(v0, v1, dtype=torch.float32),
        torch.arange(u0, u1, dtype=torch.float32),
        indexing="ij",
    )
    xs = inv[:, 0, 0, None, None] * gx + inv[:, 0, 1, None, None] * gy + inv[:, 0, 2, None, None]
    ys = inv[:, 1, 0, None, None] * gx + inv[:, 1, 1, None, None] * gy + inv[:, 1, 2, None, None]
    return xs, ys


def warp_crops(
    image: np.ndarray, A: np.ndarray, out_hw: tuple[int, int], border: float = 0.0
) -> np.ndarray:
    """Crops (N, h, w, 3) float32 0-255 of an (H, W, 3) image through maps ``A`` (N, 2, 3)
    (image -> crop), bilinear, ``border`` outside the image (cv2.warpAffine, INTER_LINEAR)."""
    check_image(image)
    h, w = out_hw
    n = len(A)
    if n == 0:
        return np.zeros((0, h, w, 3), np.float32)
    xs, ys = _grid(invert_affine(A), 0, h, 0, w)
    img = torch.from_numpy(image.astype(np.float32)).permute(2, 0, 1)[None]
    out = _sample(img, xs.reshape(n * h, w), ys.reshape(n * h, w), border)  # (3, N*h, w)
    return out.reshape(3, n, h, w).permute(1, 2, 3, 0).numpy()


def paste_back(
    crop_values: np.ndarray,
    A: np.ndarray,
    height: int,
    width: int,
    region_xyxy: np.ndarray | None = None,
) -> np.ndarray:
    """Values of crops (N, h, w) float brought back to the image: (N, height, width) float32,
    bilinear, 0 outside each crop. ``region_xyxy`` (N, 4) limits each result to a pixel box
    (the rest 0), which keeps the work proportional to the crops."""
    n, h, w = crop_values.shape
    out = np.zeros((n, height, width), np.float32)
    for i in range(n):
        if region_xyxy is None:
            u0, v0, u1, v1 = 0, 0, width, height
        else:
            r = region_xyxy[i]
            u0, v0 = max(int(np.floor(r[0])), 0), max(int(np.floor(r[1])), 0)
            u1, v1 = min(int(np.ceil(r[2])) + 1, width), min(int(np.ceil(r[3])) + 1, height)
        if u1 <= u0 or v1 <= v0:
            continue
        xs, ys = _grid(A[i : i + 1], v0, v1, u0, u1)
        vals = _sample(
            torch.as_tensor(crop_values[i], dtype=torch.float32)[None, None], xs[0], ys[0], 0.0
        )
        out[i, v0:v1, u0:u1] = vals[0].numpy()
    return out


def nms(boxes_xyxy: np.ndarray, scores: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Greedy non-maximum suppression: indices kept, by decreasing score (a box is dropped when
    its IoU with a kept, higher-scoring box exceeds ``iou_threshold``; torchvision.ops.nms)."""
    order = np.argsort(-np.asarray(scores), kind="stable")
    iou = box_iou(boxes_xyxy, boxes_xyxy)
    keep: list[int] = []
    alive = np.ones(len(order), bool)
    for rank, i in enumerate(order):
        if not alive[rank]:
            continue
        keep.append(int(i))
        alive[rank + 1 :] &= iou[i, order[rank + 1 :]] <= iou_threshold
    return np.array(keep, np.int64)
