"""Cityscapes semantic segmentation and person instance masks.

- Semantic (any Cityscapes-trained export, e.g. mmsegmentation's SegFormer / DeepLabV3+ /
  Mask2Former-semantic through mmdeploy): one input (1, 3, h, w), the image resized to it (no
  aspect kept: Cityscapes frames and the models' inputs share 1:2 or the model is dynamic),
  ImageNet mean / std on RGB; output either logits (1, 19, h', w') over the 19 train ids,
  resized bilinearly to the image and arg-maxed, or labels (1, h', w') / (1, 1, h', w') (an
  export with the arg-max inside), resized nearest.
- Instance masks, Mask2Former style (Cheng et al. 2022; its ``instance_inference``): outputs class
  logits (1, Q, C + 1) (last = no object) and mask logits (1, Q, h', w'). A query's score is
  softmax(class)[person] x the mean sigmoid inside its binary mask (logit > 0 after resizing to
  the image); queries under ``score_threshold`` drop. Each detection box takes the query whose
  mask's bounding box overlaps it most (IoU >= ``min_box_iou``, one query per box, boxes in
  score order).
- Fallback without an instance model: the semantic person pixels (train ids 11 person, 12 rider)
  inside each detection box; a pixel inside several boxes goes to the box whose bottom edge is
  lowest in the image (on flat ground the nearest person occludes the others).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from tasks.geometry import box_iou
from tasks.perception.models.image import IMAGENET_MEAN, IMAGENET_STD, normalize, resize
from tasks.perception.models.runner import ModelRunner, expect, input_hw
from tasks.perception.models.settings import MaskSettings, SemanticSettings

NUM_CITYSCAPES = 19
#: Cityscapes train ids of people (person, rider)
PERSON_TRAIN_IDS = (11, 12)


def _resized_input(image: np.ndarray, height: int, width: int, mean, std) -> np.ndarray:
    x = np.moveaxis(resize(np.moveaxis(image, -1, 0), height, width), 0, -1)
    return normalize(x, mean, std)[None]


def labels_from_output(out: np.ndarray, height: int, width: int) -> np.ndarray:
    """A semantic export's output -> (height, width) uint8 train ids (255 where the model gave an
    id outside 0..18). Logits (1, 19, h, w): bilinear resize then arg-max; labels (1, h, w) or
    (1, 1, h, w): nearest resize (pixel centres)."""
    a = np.asarray(out)
    if a.ndim == 4 and a.shape[1] == NUM_CITYSCAPES:
        logits = torch.as_tensor(a, dtype=torch.float32)
        up = F.interpolate(logits, size=(height, width), mode="bilinear", align_corners=False)
        return up[0].argmax(0).numpy().astype(np.uint8)
    lab = a.reshape(a.shape[-2:])
    rows = np.minimum(
        ((np.arange(height) + 0.5) * lab.shape[0] / height).astype(int), lab.shape[0] - 1
    )
    cols = np.minimum(
        ((np.arange(width) + 0.5) * lab.shape[1] / width).astype(int), lab.shape[1] - 1
    )
    out_lab = lab[rows][:, cols].astype(np.int64)
    return np.where((out_lab >= 0) & (out_lab < NUM_CITYSCAPES), out_lab, 255).astype(np.uint8)


class SemanticSegmenter:
    """Cityscapes train ids per pixel from a segmentation export (module docstring)."""

    def __init__(
        self,
        runner: ModelRunner,
        settings: SemanticSettings,
        mean=IMAGENET_MEAN,
        std=IMAGENET_STD,
    ):
        """settings.input_size: (height, width) for an export with a dynamic input (None: the
        export's)."""
        expect(runner, "Cityscapes segmentation", {"*": (1, 3, None, None)}, 1)
        shape = next(iter(runner.output_shapes.values()))
        if not (len(shape) == 3 or (len(shape) == 4 and shape[1] in (None, 1, NUM_CITYSCAPES))):
            raise ValueError(
                f"{runner.source}: not a Cityscapes segmentation export: output shape {shape}, "
                f"expected logits (1, {NUM_CITYSCAPES}, h, w) or labels (1, h, w)"
            )
        self.runner, self.mean, self.std = runner, mean, std
        self.input = next(iter(runner.input_shapes))
        self.height, self.width = settings.input_size or input_hw(runner, self.input)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """(H, W) uint8 train ids."""
        out = next(
            iter(
                self.runner(
                    {
                        self.input: _resized_input(
                            image, self.height, self.width, self.mean, self.std
                        )
                    }
                ).values()
            )
        )
        return labels_from_output(out, image.shape[0], image.shape[1])


def mask_boxes(masks: np.ndarray) -> np.ndarray:
    """Tight pixel boxes (M, 4) xyxy of masks (M, H, W) (pixel centres; empty mask -> zeros)."""
    out = np.zeros((len(masks), 4), np.float64)
    for i, m in enumerate(masks):
        rows, cols = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
        if rows.size:
            out[i] = [cols[0], rows[0], cols[-1], rows[-1]]
    return out


def assign_masks(boxes_xyxy: np.ndarray, masks: np.ndarray, min_box_iou: float) -> np.ndarray:
    """Give each box (D, 4) (in priority order) the unclaimed mask of ``masks`` (M, H, W) whose
    bounding box overlaps it most, if that IoU >= min_box_iou. Returns (D, H, W) bool."""
    D = len(boxes_xyxy)
    out = np.zeros((D,) + masks.shape[1:], bool)
    if D == 0 or len(masks) == 0:
        return out
    iou = box_iou(boxes_xyxy, mask_boxes(masks))
    free = np.ones(len(masks), bool)
    for d in range(D):
        cand = np.where(free, iou[d], -1.0)
        j = int(cand.argmax())
        if cand[j] >= min_box_iou:
            out[d], free[j] = masks[j], False
    return out


def query_masks(
    class_logits: np.ndarray,
    mask_logits: np.ndarray,
    height: int,
    width: int,
    person_class: int,
    score_threshold: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Mask2Former query outputs (Q, C + 1), (Q, h, w) -> person masks (M, height, width) bool and
    their scores (M,), by decreasing score (module docstring)."""
    logits = torch.as_tensor(np.asarray(class_logits, np.float32))
    prob = logits.softmax(-1)[:, person_class].numpy()
    keep = np.flatnonzero(prob >= score_threshold)  # the mask factor is <= 1: a cheap pre-filter
    if keep.size == 0:
        return np.zeros((0, height, width), bool), np.zeros(0, np.float32)
    up = F.interpolate(
        torch.as_tensor(np.asarray(mask_logits, np.float32)[keep])[None],
        size=(height, width),
        mode="bilinear",
        align_corners=False,
    )[0]
    binary = up > 0
    sig = up.sigmoid()
    mask_score = (sig * binary).flatten(1).sum(1) / binary.flatten(1).sum(1).clamp(min=1)
    score = prob[keep] * mask_score.numpy()
    ok = (score >= score_threshold) & binary.flatten(1).any(1).numpy()
    order = np.argsort(-score[ok], kind="stable")
    return binary.numpy()[ok][order], score[ok][order].astype(np.float32)


class QueryInstanceMasks:
    """Person masks for detection boxes from a Mask2Former-style export (module docstring)."""

    def __init__(
        self,
        runner: ModelRunner,
        settings: MaskSettings,
        min_box_iou: float = 0.5,
        mean=IMAGENET_MEAN,
        std=IMAGENET_STD,
        input_size: tuple[int, int] | None = None,
    ):
        expect(runner, "Mask2Former-style instance", {"*": (1, 3, None, None)}, 2)
        if sorted(len(s) for s in runner.output_shapes.values()) != [3, 4]:
            raise ValueError(
                f"{runner.source}: not a Mask2Former-style export: outputs "
                f"{dict(runner.output_shapes)}, expected class logits (1, Q, C + 1) and "
                "mask logits (1, Q, h, w)"
            )
        self.runner, self.person_class = runner, settings.person_class
        self.score_threshold, self.min_box_iou, self.mean, self.std = (
            settings.score_threshold,
            min_box_iou,
            mean,
            std,
        )
        self.input = next(iter(runner.input_shapes))
        self.height, self.width = input_size or input_hw(runner, self.input)

    def __call__(self, image: np.ndarray, boxes_xyxy: np.ndarray) -> np.ndarray:
        """(D, H, W) bool, one mask per box (all False where no query matches)."""
        H, W = image.shape[:2]
        out = sorted(
            self.runner(
                {self.input: _resized_input(image, self.height, self.width, self.mean, self.std)}
            ).values(),
            key=np.ndim,
        )
        cls, masks = out[0][0], out[1][0]
        if self.person_class >= cls.shape[-1] - 1:
            raise ValueError(
                f"{self.runner.source}: person_class {self.person_class} but the export has "
                f"{cls.shape[-1] - 1} classes (+ no-object)"
            )
        found, _ = query_masks(cls, masks, H, W, self.person_class, self.score_threshold)
        return assign_masks(
            np.asarray(boxes_xyxy, np.float64).reshape(-1, 4), found, self.min_box_iou
        )


def semantic_person_masks(
    semantic: np.ndarray, boxes_xyxy: np.ndarray, person_ids=PERSON_TRAIN_IDS
) -> np.ndarray:
    """The fallback: person pixels of ``semantic`` (H, W) inside each box (D, 4); a pixel in
    several boxes goes to the box with the lowest bottom edge. Returns (D, H, W) bool."""
    H, W = semantic.shape
    boxes = np.asarray(boxes_xyxy, np.float64).reshape(-1, 4)
    person = np.isin(semantic, person_ids)
    owner = np.full((H, W), -1, np.int64)
    # paint boxes from the farthest (highest bottom edge) to the nearest: the nearest wins
    for d in np.argsort(boxes[:, 3], kind="stable"):
        u0, v0 = max(int(np.ceil(boxes[d, 0])), 0), max(int(np.ceil(boxes[d, 1])), 0)
        u1, v1 = min(int(np.floor(boxes[d, 2])) + 1, W), min(int(np.floor(boxes[d, 3])) + 1, H)
        if u1 > u0 and v1 > v0:
            owner[v0:v1, u0:u1] = d
    return (owner[None] == np.arange(len(boxes))[:, None, None]) & person[None]
