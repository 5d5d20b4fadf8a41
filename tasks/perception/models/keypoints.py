"""Top-down COCO-17 keypoints on detection boxes: ViTPose (heatmaps) and RTMPose (SimCC).

Both follow mmpose's top-down pipeline: each box becomes a crop (centre, size x ``padding`` 1.25,
the short side grown to the input's aspect ratio), warped to the model input (N, 3, h, w),
RGB normalised with the ImageNet mean / std; decoded keypoints go back through the inverse crop.

- ViTPose (Xu et al. 2022; mmpose ``td-hm_ViTPose-*_8xb64-210e_coco-256x192``): output heatmaps
  (N, 17, h/4, w/4). ``udp=True`` (ViTPose's training codec, mmpose ``UDPHeatmap``): the crop maps
  a box length to ``in - 1`` pixels, the heatmap maximum is refined by DARK on the log of the
  heatmap blurred with an 11-tap Gaussian (one Newton step, mmpose
  ``refine_keypoints_dark_udp``) and heatmap pixel k maps to input k (in - 1) / (hm - 1).
  ``udp=False`` (SimpleBaseline / HRNet ``MSRAHeatmap``): standard crop, the maximum moves a
  quarter pixel towards the higher neighbour, heatmap k maps to input k in / hm. Confidence: the
  heatmap maximum.
- RTMPose (Jiang et al. 2023; mmpose ``SimCCLabel``, split ratio 2): outputs simcc_x (N, 17, 2 w)
  and simcc_y (N, 17, 2 h); each coordinate is the arg-max bin / 2 in input pixels (standard
  crop); confidence the smaller of the two maxima (mmpose ``get_simcc_maximum``).
Confidences are clipped to [0, 1] (the ImagePerception contract).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from tasks.perception.models.image import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    apply_affine,
    box_center_scale,
    crop_affine,
    invert_affine,
    normalize,
    warp_crops,
)
from tasks.perception.models.runner import ModelRunner, expect, input_hw, run_batched
from tasks.perception.models.settings import KeypointSettings

NUM_KEYPOINTS = 17
#: mmpose's blur kernel for DARK-UDP (cv2.GaussianBlur size 11, sigma from the size: 2.0)
DARK_KERNEL = 11


def heatmap_argmax(heatmaps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """heatmaps (N, K, H, W) -> integer maxima (N, K, 2) float64 (x, y) and values (N, K)."""
    n, k, h, w = heatmaps.shape
    flat = heatmaps.reshape(n, k, -1)
    idx = flat.argmax(axis=2)
    xy = np.stack([idx % w, idx // w], axis=-1).astype(np.float64)
    return xy, np.take_along_axis(flat, idx[..., None], axis=2)[..., 0].astype(np.float64)


def refine_quarter(heatmaps: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Move each integer maximum a quarter pixel towards its higher neighbour along x and y, where
    both neighbours exist (the classic 'default' post-processing of SimpleBaseline / HRNet)."""
    n, k, h, w = heatmaps.shape
    out = xy.copy()
    for i in range(n):
        for j in range(k):
            x, y = int(xy[i, j, 0]), int(xy[i, j, 1])
            hm = heatmaps[i, j]
            if 0 < x < w - 1 and 0 < y < h - 1:
                out[i, j] += 0.25 * np.sign(
                    [hm[y, x + 1] - hm[y, x - 1], hm[y + 1, x] - hm[y - 1, x]]
                )
    return out


def refine_dark_udp(
    heatmaps: np.ndarray, xy: np.ndarray, blur_kernel: int = DARK_KERNEL
) -> np.ndarray:
    """DARK refinement (Zhang et al. 2020) as ViTPose's UDP codec does it: blur each heatmap with a
    Gaussian (``blur_kernel`` taps, cv2's sigma for that size, zero border, rescaled to keep its
    maximum), take the log (values clipped to [1e-3, 50]), and take one Newton step from the
    integer maximum with central differences (edge-replicated border). ``blur_kernel`` 0 skips
    the blur. Returns (N, K, 2) float64 heatmap pixels."""
    hm = np.asarray(heatmaps, np.float64)
    if blur_kernel:
        sigma = 0.3 * ((blur_kernel - 1) * 0.5 - 1) + 0.8
        radius = (blur_kernel - 1) // 2
        peak = hm.max(axis=(2, 3), keepdims=True)
        hm = ndimage.gaussian_filter(
            hm, sigma=(0, 0, sigma, sigma), mode="constant", cval=0.0, truncate=radius / sigma
        )
        hm *= peak / np.maximum(hm.max(axis=(2, 3), keepdims=True), 1e-12)
    logs = np.log(np.clip(hm, 1e-3, 50.0))
    pad = np.pad(logs, ((0, 0), (0, 0), (1, 1), (1, 1)), mode="edge")
    x = xy[..., 0].astype(int) + 1
    y = xy[..., 1].astype(int) + 1
    n, k = xy.shape[:2]
    ii, jj = np.meshgrid(np.arange(n), np.arange(k), indexing="ij")
    at = lambda dy, dx: pad[ii, jj, y + dy, x + dx]
    c = at(0, 0)
    dx = 0.5 * (at(0, 1) - at(0, -1))
    dy = 0.5 * (at(1, 0) - at(-1, 0))
    dxx = at(0, 1) - 2 * c + at(0, -1)
    dyy = at(1, 0) - 2 * c + at(-1, 0)
    dxy = 0.25 * (at(1, 1) - at(1, -1) - at(-1, 1) + at(-1, -1))
    hess = np.stack([np.stack([dxx, dxy], -1), np.stack([dxy, dyy], -1)], -2)
    hess = hess + np.finfo(np.float32).eps * np.eye(2)
    step = np.linalg.solve(hess, np.stack([dx, dy], -1)[..., None])[..., 0]
    return xy - step


def decode_heatmaps(
    heatmaps: np.ndarray, input_hw: tuple[int, int], udp: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Heatmaps (N, K, h, w) -> keypoints (N, K, 2) in model-input pixels and confidences (N, K)
    (see the module docstring for the two codecs)."""
    hm = np.asarray(heatmaps, np.float64)
    n, k, h, w = hm.shape
    xy, val = heatmap_argmax(hm)
    if udp:
        xy = refine_dark_udp(hm, xy) * [(input_hw[1] - 1) / (w - 1), (input_hw[0] - 1) / (h - 1)]
    else:
        xy = refine_quarter(hm, xy) * [input_hw[1] / w, input_hw[0] / h]
    return xy, val


def decode_simcc(
    simcc_x: np.ndarray, simcc_y: np.ndarray, split_ratio: float = 2.0
) -> tuple[np.ndarray, np.ndarray]:
    """SimCC vectors (N, K, Wx), (N, K, Wy) -> keypoints (N, K, 2) input pixels (arg-max bin /
    split_ratio) and confidences (N, K) = min of the two maxima; -1 where that is <= 0."""
    sx, sy = np.asarray(simcc_x, np.float64), np.asarray(simcc_y, np.float64)
    xy = np.stack([sx.argmax(-1), sy.argmax(-1)], -1).astype(np.float64) / split_ratio
    val = np.minimum(sx.max(-1), sy.max(-1))
    xy[val <= 0] = -1
    return xy, val


#: the output form of each top-down keypoint model
FORMS = {"vitpose": "heatmap", "rtmpose": "simcc"}


class TopDownKeypoints:
    """COCO-17 keypoints of boxes with a ViTPose (``kind='vitpose'``: heatmaps) or RTMPose
    (``kind='rtmpose'``: SimCC) export: one image input (N, 3, h, w), heatmaps (N, 17, h', w') or
    simcc_x (N, 17, Wx), simcc_y (N, 17, Wy). settings: the kind, ViTPose's ``udp`` codec and
    the crops per run (``batch_size``)."""

    def __init__(
        self,
        runner: ModelRunner,
        settings: KeypointSettings,
        padding: float = 1.25,
        split_ratio: float = 2.0,
        mean=IMAGENET_MEAN,
        std=IMAGENET_STD,
    ):
        if settings.kind not in FORMS:
            raise ValueError(
                f"keypoints kind {settings.kind!r}: expected one of {sorted(FORMS)} (a top-down "
                "ONNX export)"
            )
        form, udp, batch_size = FORMS[settings.kind], settings.udp, settings.batch_size
        if form == "heatmap":
            expect(
                runner,
                "ViTPose heatmap",
                {"*": (None, 3, None, None)},
                {"*": (None, NUM_KEYPOINTS, None, None)},
            )
        elif form == "simcc":
            expect(
                runner,
                "RTMPose SimCC",
                {"*": (None, 3, None, None)},
                {"*": (None, NUM_KEYPOINTS, None), "**": (None, NUM_KEYPOINTS, None)},
            )
        else:
            raise ValueError(
                f"keypoint form {form!r}: expected 'heatmap' (ViTPose) or 'simcc' (RTMPose)"
            )
        self.runner, self.form, self.udp = runner, form, udp and form == "heatmap"
        self.padding, self.split_ratio, self.batch_size = padding, split_ratio, batch_size
        self.mean, self.std = mean, std
        self.input = next(iter(runner.input_shapes))
        self.height, self.width = input_hw(runner, self.input)

    def crops(self, boxes_xyxy: np.ndarray) -> np.ndarray:
        """The crop maps (N, 2, 3) image -> model input of some boxes."""
        center, size = box_center_scale(boxes_xyxy, self.width / self.height, self.padding)
        return crop_affine(center, size, (self.height, self.width), udp=self.udp)

    def __call__(self, image: np.ndarray, boxes_xyxy: np.ndarray) -> np.ndarray:
        """Keypoints (D, 17, 3) float32: (u, v) image px and a confidence in [0, 1]."""
        boxes = np.asarray(boxes_xyxy, np.float64).reshape(-1, 4)
        if len(boxes) == 0:
            return np.zeros((0, NUM_KEYPOINTS, 3), np.float32)
        A = self.crops(boxes)
        x = normalize(warp_crops(image, A, (self.height, self.width)), self.mean, self.std)
        out = list(run_batched(self.runner, {self.input: x}, self.batch_size).values())
        if self.form == "heatmap":
            xy, conf = decode_heatmaps(out[0], (self.height, self.width), self.udp)
        else:
            xy, conf = decode_simcc(
                out[0], out[1], self.split_ratio
            )  # simcc_x first (mmpose export)
        uv = apply_affine(invert_affine(A), xy)
        return np.concatenate([uv, np.clip(conf, 0, 1)[..., None]], -1).astype(np.float32)
