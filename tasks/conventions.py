"""Conventions fixed once for the whole project; every other module refers here.

Frames (all right-handed, metres, seconds as integer nanoseconds unless a name says otherwise):

- ``lidar``: the Ouster OS1-128 frame, x forward, y left, z up.
- ``base``: the robot base frame on the ground below the sensor, x forward, y left, z up.
  The occupancy grids of the dataset are robot-local: they live in ``base``.
- ``cam`` (cam0 / cam1): OpenCV camera frame, x right, y down, z forward (optical axis).
- ``world``: the map frame of a sequence; poses are ``T_world_from_lidar``.

Arrays:

- points ``(N, 3) float32``; intensities ``(N,) float32``; per-point labels ``(N,) uint8``.
- rigid transforms ``(4, 4) float64``, named ``T_target_from_source`` so that
  ``p_target = T_target_from_source @ p_source`` (homogeneous column vectors).
- quaternions ``(w, x, y, z)``; angles in radians; image pixels ``(u, v)`` with u to the right.
- voxel grids ``[x, y, z]`` axis order (Occ3D): the index of a point p is
  ``floor((p - range_min) / voxel_size_m)``.

Classes (Occ3D convention, free last so Occ3D's metric code applies unchanged): 0 pedestrian,
1 car, 2 other-structure, 3 pole, 4 road, 5 terrain, 6 truck, 7 two-wheeler, 8 vegetation (the
9 semantic classes, ``range(NUM_SEMANTIC_CLASSES)``), 9 unclassified (occupied, class unknown: a
voxel holding LiDAR returns that no class was given to, e.g. with no image segmenter; Occ3D's
"others"), 10 free. Occupied is ``< FREE``. Unknown is not a class: it is where the visibility
masks are 0.
"""

from __future__ import annotations

import numpy as np

CLASS_NAMES: tuple[str, ...] = (
    "pedestrian",
    "car",
    "other-structure",
    "pole",
    "road",
    "terrain",
    "truck",
    "two-wheeler",
    "vegetation",
    "unclassified",
    "free",
)
PEDESTRIAN = 0
CAR = 1
OTHER_STRUCTURE = 2
POLE = 3
ROAD = 4
TERRAIN = 5
TRUCK = 6
TWO_WHEELER = 7
VEGETATION = 8
#: occupied, class unknown: returns that got no class (no segmenter, a removed person with no body)
UNCLASSIFIED = 9
FREE = 10
NUM_CLASSES = 11
#: the classes with a meaning, 0..8 (mIoU's classes); occupied classes are 0..UNCLASSIFIED
NUM_SEMANTIC_CLASSES = UNCLASSIFIED
#: label for "no class" in per-point label arrays (e.g. a point outside the image with the
#: ``unknown`` fallback); never written into a voxel grid.
UNLABELED = 255

#: RGB colours (0-255) per class, Cityscapes palette as in the paper's figures.
CLASS_COLORS: np.ndarray = np.array(
    [
        [255, 26, 78],  # pedestrian
        [0, 0, 185],  # car
        [133, 133, 203],  # other-structure
        [199, 199, 199],  # pole
        [166, 83, 166],  # road
        [198, 255, 198],  # terrain
        [0, 0, 91],  # truck
        [0, 0, 255],  # two-wheeler
        [139, 185, 46],  # vegetation
        [255, 170, 0],  # unclassified
        [255, 255, 255],  # free
    ],
    dtype=np.uint8,
)
UNKNOWN_COLOR = np.array([128, 128, 128], dtype=np.uint8)

# Cityscapes train ids (19 classes, 255 = ignore), as semantic segmenters emit them.
CITYSCAPES_TRAIN_IDS: dict[str, int] = {
    "road": 0,
    "sidewalk": 1,
    "building": 2,
    "wall": 3,
    "fence": 4,
    "pole": 5,
    "traffic light": 6,
    "traffic sign": 7,
    "vegetation": 8,
    "terrain": 9,
    "sky": 10,
    "person": 11,
    "rider": 12,
    "car": 13,
    "truck": 14,
    "bus": 15,
    "train": 16,
    "motorcycle": 17,
    "bicycle": 18,
}
CITYSCAPES_IGNORE = 255

#: Default lookup Cityscapes train id -> our class id (UNLABELED where the id has no class,
#: e.g. sky). Index with a uint8 image: ``CITYSCAPES_TO_CLASS[semantic_image]``. The map stage
#: takes its table from the config; this is the table the default config spells out.
CITYSCAPES_TO_CLASS: np.ndarray = np.full(256, UNLABELED, dtype=np.uint8)
for _name, _cls in {
    "road": ROAD,
    "sidewalk": ROAD,
    "building": OTHER_STRUCTURE,
    "wall": OTHER_STRUCTURE,
    "fence": OTHER_STRUCTURE,
    "pole": POLE,
    "traffic light": POLE,
    "traffic sign": POLE,
    "vegetation": VEGETATION,
    "terrain": TERRAIN,
    "person": PEDESTRIAN,
    "rider": PEDESTRIAN,
    "car": CAR,
    "truck": TRUCK,
    "bus": TRUCK,
    "train": TRUCK,
    "motorcycle": TWO_WHEELER,
    "bicycle": TWO_WHEELER,
}.items():
    CITYSCAPES_TO_CLASS[CITYSCAPES_TRAIN_IDS[_name]] = _cls

#: Our class id -> the Cityscapes train id a renderer paints for it (inverse of the table above).
CLASS_TO_CITYSCAPES: np.ndarray = np.array(
    [11, 13, 2, 5, 0, 9, 14, 18, 8, CITYSCAPES_IGNORE, CITYSCAPES_IGNORE], dtype=np.uint8
)

# COCO-17 keypoints (ViTPose order).
COCO17_NAMES: tuple[str, ...] = (
    "nose",
    "left_eye",
    "right_eye",
    "left_ear",
    "right_ear",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_hip",
    "right_hip",
    "left_knee",
    "right_knee",
    "left_ankle",
    "right_ankle",
)

# SMPL kinematic tree (24 joints).
SMPL_JOINT_NAMES: tuple[str, ...] = (
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_hand",
    "right_hand",
)
SMPL_PARENTS: tuple[int, ...] = (
    -1,
    0,
    0,
    0,
    1,
    2,
    3,
    4,
    5,
    6,
    7,
    8,
    9,
    9,
    9,
    12,
    13,
    14,
    16,
    17,
    18,
    19,
    20,
    21,
)
#: COCO-17 index -> SMPL joint index for the body keypoints that correspond directly.
COCO_TO_SMPL_JOINT: dict[int, int] = {
    5: 16,
    6: 17,
    7: 18,
    8: 19,
    9: 20,
    10: 21,
    11: 1,
    12: 2,
    13: 4,
    14: 5,
    15: 7,
    16: 8,
}
#: COCO-17 face keypoints given by SMPL vertex ids (official SMPL topology).
COCO_TO_SMPL_VERTEX: dict[int, int] = {0: 332, 1: 2800, 2: 6260, 3: 583, 4: 4071}
#: the arrays every SMPL-format body model holds (the official model files' keys; their shapes:
#: tasks.body.model); a file may hold more (e.g. ``coco_vertex_ids``)
SMPL_MODEL_KEYS: tuple[str, ...] = (
    "v_template",
    "f",
    "shapedirs",
    "posedirs",
    "weights",
    "kintree_table",
    "J_regressor",
)
