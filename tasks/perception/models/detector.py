"""Person detection: the YOLOX family (the paper's detector) and a generic decoded-boxes form.

YOLOX (Ge et al. 2021; Megvii-BaseDetection/YOLOX ``tools/export_onnx.py``, ``demo/ONNXRuntime``):
one input (1, 3, H, W) float32 BGR 0-255, *not* normalised (YOLOX >= 0.2), the image letterboxed
at the top-left (ratio min(H / h, W / w), padding 114); one output (1, A, 5 + C) rows
(x, y, w, h, objectness, class scores...), objectness and classes already through a sigmoid.
Exported without ``--decode_in_inference`` (the default) the boxes are raw: over the strides
8, 16, 32, anchor a at grid cell (gx, gy) of stride s decodes to centre ((x + gx) s, (y + gy) s)
and size (e^w s, e^h s); ``decoded=True`` for exports that did it in the graph. Score =
objectness x class score of the person class; boxes below ``score_threshold`` drop, NMS at
``nms_iou``, boxes mapped back by the letterbox ratio.

Decoded boxes (mmdeploy's end-to-end detector exports, and any export with NMS inside): outputs
``dets`` (1, N, 5) = (x0, y0, x1, y1, score) in input pixels and ``labels`` (1, N) class ids;
the same letterbox in, the person class filtered, a final NMS (a no-op after the graph's own).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tasks.perception.models.image import letterbox, nms, normalize
from tasks.perception.models.runner import ModelRunner, expect, input_hw
from tasks.perception.models.settings import DetectorSettings

YOLOX_STRIDES = (8, 16, 32)


@dataclass(frozen=True)
class Detections:
    """boxes_xyxy (D, 4) float32 image px, scores (D,) float32, by decreasing score."""

    boxes_xyxy: np.ndarray
    scores: np.ndarray

    @staticmethod
    def empty() -> Detections:
        return Detections(np.zeros((0, 4), np.float32), np.zeros(0, np.float32))


def yolox_grid_decode(
    raw: np.ndarray, height: int, width: int, strides=YOLOX_STRIDES
) -> np.ndarray:
    """Decode raw YOLOX rows (A, 5 + C) of a (height, width) input: rows in the order the head
    concatenates them (stride by stride, row-major over the grid). Returns (A, 5 + C) with
    (cx, cy, w, h) in input pixels, scores unchanged."""
    grids, steps = [], []
    for s in strides:
        gh, gw = height // s, width // s
        gy, gx = np.mgrid[0:gh, 0:gw]
        grids.append(np.stack([gx.ravel(), gy.ravel()], 1))
        steps.append(np.full((gh * gw, 1), s))
    grid = np.concatenate(grids).astype(np.float64)
    step = np.concatenate(steps).astype(np.float64)
    if len(grid) != len(raw):
        raise ValueError(
            f"YOLOX output has {len(raw)} rows; a {height} x {width} input with strides "
            f"{tuple(strides)} has {len(grid)} (export decoded already? set decoded)"
        )
    out = np.array(raw, np.float64)
    out[:, :2] = (out[:, :2] + grid) * step
    out[:, 2:4] = np.exp(out[:, 2:4]) * step
    return out


def _select(
    boxes: np.ndarray, scores: np.ndarray, score_threshold: float, nms_iou: float
) -> Detections:
    keep = scores >= score_threshold
    boxes, scores = boxes[keep], scores[keep]
    order = nms(boxes, scores, nms_iou)
    return Detections(boxes[order].astype(np.float32), scores[order].astype(np.float32))


class YoloxDetector:
    """YOLOX person detector on a runner (see the module docstring)."""

    def __init__(
        self,
        runner: ModelRunner,
        settings: DetectorSettings,
        mean=(0.0, 0.0, 0.0),
        std=(1.0, 1.0, 1.0),
        bgr: bool = True,
    ):
        """settings: the person class, score threshold, NMS IoU and whether the export decoded
        its boxes already (``decoded``)."""
        expect(runner, "YOLOX", {"*": (1, 3, None, None)}, {"*": (1, None, None)})
        s = settings
        self.runner, self.person_class, self.decoded = runner, s.person_class, s.decoded
        self.score_threshold, self.nms_iou = s.score_threshold, s.nms_iou
        self.mean, self.std, self.bgr = mean, std, bgr
        self.input = next(iter(runner.input_shapes))
        self.height, self.width = input_hw(runner, self.input)

    def __call__(self, image: np.ndarray) -> Detections:
        x, lb = letterbox(image, self.height, self.width, 114.0, center=False)
        out = next(
            iter(
                self.runner(
                    {self.input: normalize(x, self.mean, self.std, self.bgr)[None]}
                ).values()
            )
        )[0]
        if out.shape[1] < 6 + self.person_class:
            raise ValueError(
                f"{self.runner.source}: output rows have {out.shape[1]} values, fewer than "
                f"5 + person_class + 1 = {6 + self.person_class}"
            )
        rows = out if self.decoded else yolox_grid_decode(out, self.height, self.width)
        xy, wh = rows[:, :2], rows[:, 2:4]
        boxes = lb.to_image(
            np.concatenate([xy - wh / 2, xy + wh / 2], 1).reshape(-1, 2, 2)
        ).reshape(-1, 4)
        scores = rows[:, 4] * rows[:, 5 + self.person_class]
        return _select(boxes, scores, self.score_threshold, self.nms_iou)


class DecodedBoxesDetector:
    """A detector export that outputs final boxes: ``dets`` (1, N, 5), ``labels`` (1, N)."""

    def __init__(
        self,
        runner: ModelRunner,
        settings: DetectorSettings,
        mean=(0.0, 0.0, 0.0),
        std=(1.0, 1.0, 1.0),
        bgr: bool = True,
        center: bool = False,
        pad_value: float = 114.0,
    ):
        expect(
            runner,
            "decoded-boxes detector",
            {"*": (1, 3, None, None)},
            {"dets": (1, None, 5), "labels": (1, None)},
        )
        self.runner, self.person_class = runner, settings.person_class
        self.score_threshold, self.nms_iou = settings.score_threshold, settings.nms_iou
        self.mean, self.std, self.bgr, self.center, self.pad_value = (
            mean,
            std,
            bgr,
            center,
            pad_value,
        )
        self.input = next(iter(runner.input_shapes))
        self.height, self.width = input_hw(runner, self.input)

    def __call__(self, image: np.ndarray) -> Detections:
        x, lb = letterbox(image, self.height, self.width, self.pad_value, center=self.center)
        out = self.runner({self.input: normalize(x, self.mean, self.std, self.bgr)[None]})
        dets, labels = np.asarray(out["dets"][0], np.float64), np.asarray(out["labels"][0])
        person = labels == self.person_class
        boxes = lb.to_image(dets[person, :4].reshape(-1, 2, 2)).reshape(-1, 4)
        return _select(boxes, dets[person, 4], self.score_threshold, self.nms_iou)
