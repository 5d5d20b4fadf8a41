"""One RGB image -> :class:`tasks.perception.types.ImagePerception`, from the parts of a setup.

Parts (any may be absent): a person ``detector`` (YOLOX, decoded boxes) or boxes handed in
(``proposals``, e.g. the LiDAR boxes projected into the camera); top-down ``keypoints``
(ViTPose / RTMPose); instance ``masks`` (Mask2Former-style); a Cityscapes ``semantic`` model;
``blazepose`` landmarks, which give keypoints and masks at once and check each box (a box whose
pose flag is under its settings' ``min_pose_flag`` is dropped: its region shows no person; the others' scores
are multiplied by their flag). Without a mask
model the masks are the semantic person pixels in each box when a semantic model is present,
else all False (consumers fall back to the box); ``mask_source`` picks one explicitly. Without a semantic model the semantic image is
255 (ignore) everywhere; without a keypoint model keypoints are zero with confidence 0.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from tasks.perception.models.blazepose import BlazePoseLandmarks
from tasks.perception.models.detector import Detections
from tasks.perception.models.image import check_image
from tasks.perception.models.segmentation import semantic_person_masks
from tasks.perception.types import NUM_KEYPOINTS, ImagePerception


@dataclass
class ModelPerception:
    detector: Callable[[np.ndarray], Detections] | None = None
    keypoints: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None
    masks: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None
    semantic: Callable[[np.ndarray], np.ndarray] | None = None
    blazepose: BlazePoseLandmarks | None = None
    #: where masks come from: "masks" (the mask model), "blazepose", "semantic" (person pixels
    #: in the box), "none", or "auto" (the first of those three that the setup has)
    mask_source: str = "auto"

    def __call__(
        self,
        image: np.ndarray,
        proposals: Detections | None = None,
        semantic: np.ndarray | None = None,
    ) -> ImagePerception:
        """Perception of one (H, W, 3) uint8 RGB image; ``proposals`` replaces the detector,
        ``semantic`` (H, W) uint8 train ids the semantic model."""
        check_image(image)
        H, W = image.shape[:2]
        semantic_given = semantic is not None
        if proposals is not None:
            dets = proposals
        elif self.detector is not None:
            dets = self.detector(image)
        else:
            raise ValueError(
                "no person boxes: the setup has no detector and no proposals were given"
            )
        boxes = np.asarray(dets.boxes_xyxy, np.float32).reshape(-1, 4)
        scores = np.asarray(dets.scores, np.float32).reshape(-1)
        if semantic is None:
            semantic = (
                np.full((H, W), 255, np.uint8)
                if self.semantic is None
                else np.asarray(self.semantic(image), np.uint8)
            )
        semantic = np.asarray(semantic, np.uint8)
        kp = np.zeros((len(boxes), NUM_KEYPOINTS, 3), np.float32)
        masks = None
        if self.blazepose is not None:
            kp, masks, flag = self.blazepose(image, boxes)
            keep = flag >= self.blazepose.settings.min_pose_flag
            boxes, scores, kp, masks = boxes[keep], scores[keep] * flag[keep], kp[keep], masks[keep]
        if self.keypoints is not None:
            kp = np.asarray(self.keypoints(image, boxes), np.float32)
        source = self.mask_source
        if source == "auto":
            source = (
                "masks"
                if self.masks is not None
                else "blazepose"
                if self.blazepose is not None
                else "semantic"
                if self.semantic is not None or semantic_given
                else "none"
            )
        if source == "masks":
            masks = np.asarray(self.masks(image, boxes), bool)
        elif source == "semantic":
            masks = semantic_person_masks(semantic, boxes)
        elif source != "blazepose" or masks is None:
            masks = np.zeros((len(boxes), H, W), bool)
        return ImagePerception(
            boxes_xyxy=boxes,
            scores=np.clip(scores, 0, 1).astype(np.float32),
            keypoints=kp.astype(np.float32),
            masks=masks,
            semantic=semantic,
        )
