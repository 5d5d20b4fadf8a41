"""Initial body estimates with CLIFF (Li et al. 2022; huawei-noah/noah-research ``CLIFF``).

An export with two inputs, the crop (N, 3, h, w) (CLIFF: 256 x 192) RGB with the ImageNet
mean / std, and ``bbox_info`` (N, 3); three outputs, joint rotations (N, 24, 3, 3), betas
(N, 10) and the crop camera (N, 3) = (s, tx, ty). The crop is CLIFF's ``bbox_from_detector``:
centred on the box, height b = max(w h_in / w_in, h) x ``rescale`` (1.1), width b w_in / h_in.
bbox_info is the paper's Eq. 5 with CLIFF's normalisation constants:
((cx - px) / f x 2.8, (cy - py) / f x 2.8, (b - 0.24 f) / (0.06 f)), using the calibrated focal
length f and principal point (px, py) (CLIFF's demo estimates them from the image size when
unknown). The outputs convert to our parameters with the same K by
:func:`tasks.fit.init_oracle.cliff_to_params`.
"""

from __future__ import annotations

import numpy as np

from tasks.body.params import BodyParams
from tasks.fit.init_oracle import cliff_to_params
from tasks.perception.models.image import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    crop_affine,
    normalize,
    warp_crops,
)
from tasks.perception.models.runner import ModelRunner, input_hw, run_batched

#: CLIFF's crop tightness around a detection box (``bbox_from_detector(rescale=1.1)``)
CLIFF_RESCALE = 1.1


def cliff_bbox_info(center: np.ndarray, size: np.ndarray, K: np.ndarray) -> np.ndarray:
    """CLIFF's normalised bounding-box input (N, 3) float32 for crops centred at ``center``
    (N, 2) px with height ``size`` (N,) px, intrinsics K (3, 3)."""
    K = np.asarray(K, np.float64)
    f = K[0, 0]
    c = np.asarray(center, np.float64).reshape(-1, 2)
    b = np.asarray(size, np.float64).reshape(-1)
    return np.stack(
        [(c[:, 0] - K[0, 2]) / f * 2.8, (c[:, 1] - K[1, 2]) / f * 2.8, (b - 0.24 * f) / (0.06 * f)],
        1,
    ).astype(np.float32)


class CliffEstimator:
    """CLIFF on detection boxes (module docstring)."""

    def __init__(
        self, runner: ModelRunner, rescale: float = CLIFF_RESCALE, crops_per_run: int = 16
    ):
        ins = list(runner.input_shapes.items())
        outs = dict(runner.output_shapes)
        rot = [s for s in outs.values() if len(s) == 4]
        if (
            len(ins) != 2
            or sorted(len(s) for _, s in ins) != [2, 4]
            or sorted(len(s) for s in outs.values()) != [2, 2, 4]
            or any(d not in (None, w) for d, w in zip(rot[0][1:], (24, 3, 3)))
        ):
            raise ValueError(
                f"{runner.source}: not a CLIFF export: inputs {dict(runner.input_shapes)}, outputs "
                f"{outs}; expected inputs image (N, 3, h, w) and bbox_info (N, 3), outputs "
                "rotations (N, 24, 3, 3), betas (N, 10), crop camera (N, 3)"
            )
        self.runner, self.rescale, self.crops_per_run = runner, rescale, crops_per_run
        self.image_input = next(n for n, s in ins if len(s) == 4)
        self.info_input = next(n for n, s in ins if len(s) == 2)
        self.height, self.width = input_hw(runner, self.image_input)

    def crops(self, boxes_xyxy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Crop centres (N, 2) and heights b (N,) px of some boxes."""
        b = np.asarray(boxes_xyxy, np.float64).reshape(-1, 4)
        center = (b[:, :2] + b[:, 2:]) / 2
        size = (
            np.maximum((b[:, 2] - b[:, 0]) * self.height / self.width, b[:, 3] - b[:, 1])
            * self.rescale
        )
        return center, size

    def __call__(self, image: np.ndarray, boxes_xyxy: np.ndarray, K: np.ndarray) -> BodyParams:
        """Initial bodies (cam frame) of the persons in some boxes (D, 4), intrinsics K (3, 3)."""
        center, size = self.crops(boxes_xyxy)
        if len(center) == 0:
            return BodyParams.empty()
        A = crop_affine(
            center,
            np.stack([size * self.width / self.height, size], 1),
            (self.height, self.width),
            udp=False,
        )
        x = normalize(warp_crops(image, A, (self.height, self.width)), IMAGENET_MEAN, IMAGENET_STD)
        out = run_batched(
            self.runner,
            {self.image_input: x, self.info_input: cliff_bbox_info(center, size, K)},
            self.crops_per_run,
        )
        rot = next(v for v in out.values() if v.ndim == 4).reshape(-1, 24, 3, 3)
        flat = [v for v in out.values() if v.ndim == 2]
        betas = next(v for v in flat if v.shape[1] == 10)
        cam = next(v for v in flat if v.shape[1] == 3)
        return cliff_to_params(rot, betas, cam, center, size, K)
