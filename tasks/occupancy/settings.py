"""Settings of the occupancy kernels (map and fuse stages): one home for their defaults."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

from annotated_types import Interval

from tasks.bounds import AtLeastOne, Count, NonNegative, Positive, Probability, VoxelSize, Widening


@dataclass(frozen=True)
class FreeSpaceParams:
    """The free / unknown map's sensor model (OctoMap's defaults) and resolution.

    voxel_size_m: its own resolution (memory grows with the volume the rays cross: keep 0.1-0.2
    m; the fused grid may still be finer). max_range_m: rays are cut here (OctoMap's maxrange).
    discretize: OctoMap's ``discretize``, one ray per distinct endpoint voxel.
    """

    voxel_size_m: VoxelSize = 0.2
    prob_hit: Annotated[float, Interval(gt=0.5, lt=1)] = 0.7
    prob_miss: Annotated[float, Interval(gt=0, lt=0.5)] = 0.4
    clamp_min: Annotated[float, Interval(gt=0, lt=0.5)] = 0.1192
    clamp_max: Annotated[float, Interval(gt=0.5, lt=1)] = 0.971
    occupancy_threshold: Annotated[float, Interval(gt=0, lt=1)] = 0.5
    max_range_m: Positive = 20.0
    discretize: bool = False


@dataclass(frozen=True)
class MapParams:
    """The static semantic map's settings.

    outside_image_fallback: label of points outside the image ("nearest" in-view label at the same
    level, see :func:`lift_image_semantics`, or "unknown"); fallback_ground_lateral_scale > 1:
    out-of-view ground points match in-view ground with the lateral axis stretched (ground classes
    run in strips along the robot's path), 1 = plain nearest neighbour. pedestrian_box_margin_m
    grows the LiDAR pedestrian boxes whose points are removed. lidar_person_min_score: outside the
    camera's view a LiDAR pedestrian box removes points only with a score of at least this (the
    lidar-clusters detector's person score; in view an image detection must confirm the box), so
    an unconfirmed candidate on a post or a bush leaves its returns in the map (issue 39; 0: every
    box, as before). Ground consistency: road / terrain
    votes farther than ground_max_deviation_m from the local ground height (per ground_cell_m cell,
    pooled over ground_neighbourhood_cells neighbouring cells, vote-weighted ground_quantile) are
    rejected; a voxel needs min_votes votes.

    min_fragment_voxels: after voting, a set of voxels of one class connected through faces,
    edges or corners (26-neighbourhood) that holds fewer voxels than this is dropped (1: off). No
    static object of any class is that small at the map's resolution (5 voxels of 0.2 m: 0.04
    m^3); such fragments are the returns of a passer-by that no detector removed, voted a wrong
    class by the image, or single noisy labels in porous vegetation (issue 30, crowded night:
    40 two-wheeler and 42 other-structure voxels where the ground truth is free).

    person_ground_keep_m: points of a person (in a LiDAR box, an instance mask, labelled
    pedestrian) at most this far above the local ground (the lowest point around them) are the
    ground the person stands on: they stay in the map with a ground label (0: removed with the
    person, and the ground under people who stand still is never mapped). person_edge_m: points
    within this distance of a removed person point are the same person's too (0: off). A body's
    outline seen by the LiDAR projects partly just outside its image mask (pixel edges, the
    LiDAR-to-camera parallax); when no confirmed LiDAR box holds the person, those returns took the
    background's label (pole, wall) and left a trail of stray voxels along the person's walk
    (issue 30, exact inputs).

    Surfaces (tasks/occupancy/surface.py): a voxel holds a surface where one passes through it,
    not where the range noise of a surface in the voxel behind it throws some of its returns.
    surface_noise_m: the LiDAR's range noise (1 sigma, m): points at most 3 sigma in front of a
    neighbouring voxel's fitted plane that does not pass through their voxel are that plane's
    noise, and the voxel is dropped (0: keep every voxel with votes); it also bounds the spread
    (2 sigma) of a voxel's own points for them to be a plane. surface_min_points: points a voxel
    needs to fit its own plane.

    Tiles (tasks/occupancy/tiles.py): both maps are built, stored and read by square tiles of
    tile_m (a whole number of map voxels and of 8-voxel occupancy blocks), so memory does not grow
    with the sequence. window_frames (sweeps per window) and region_tiles (a region is
    region_tiles x region_tiles tiles) set how the map stage splits its work into parallel tasks;
    the maps do not depend on them.
    """

    voxel_size_m: VoxelSize = 0.2
    outside_image_fallback: Literal["nearest", "unknown"] = "nearest"
    fallback_ground_lateral_scale: Widening = 4.0
    pedestrian_box_margin_m: NonNegative = 0.15
    lidar_person_min_score: Probability = 0.5
    person_ground_keep_m: NonNegative = 0.03
    person_edge_m: NonNegative = 0.1
    ground_max_deviation_m: Positive = 0.3
    ground_cell_m: Positive = 1.0
    ground_neighbourhood_cells: Count = 1
    ground_quantile: Probability = 0.5
    min_votes: AtLeastOne = 1
    min_fragment_voxels: AtLeastOne = 5
    surface_noise_m: NonNegative = 0.01
    surface_min_points: AtLeastOne = 8
    tile_m: Positive = 25.6
    window_frames: AtLeastOne = 100
    region_tiles: AtLeastOne = 4


@dataclass(frozen=True)
class FuseSettings:
    """How the fuse stage makes its masks (:func:`tasks.occupancy.fuse.fuse_frame`).

    camera_mask: make mask_camera (False: all 0). camera_method: exact per-pixel ray walks
    ("rays"), a depth buffer ("zbuffer"), or "auto" (rays for voxels >= 0.1 m). camera_pixel_stride:
    rays every this many pixels (None: from the voxel size, 13 px at 0.2 m, which misses grazing
    ground voxels; they project to ~2 px at 10 m).

    velocity: "vertex": a pedestrian voxel's velocity is the mean velocity of the body surface in
    it, each vertex's from the posed bodies of the track's neighbouring frames
    (tasks/body/motion.py); "person": every voxel of a person takes the person's velocity;
    "articulated": the person's velocity plus the surface's velocity relative to the body's
    pelvis (tasks/body/motion.py).
    velocity_max_gap_s: a neighbouring frame counts for the vertex velocities when it lies at most
    this far in time (the direct neighbours at 5 Hz, up to one missing frame at 10 Hz): across a
    longer gap a swinging limb's difference shrinks to its mean (at 0.4 s apart a 1 Hz gait swing
    keeps ~25 % of its speed); without a neighbour the vertices take the person's velocity.
    velocity_neighbours: fits on each side of a frame in each vertex's derivative (1: the
    central difference; 2: the slope of the quartic through five fits, tasks/track/velocity.py).
    """

    camera_mask: bool = True
    camera_method: Literal["auto", "rays", "zbuffer"] = "auto"
    camera_pixel_stride: AtLeastOne | None = 2
    velocity: Literal["vertex", "person", "articulated"] = "vertex"
    velocity_max_gap_s: Positive = 0.25
    velocity_neighbours: AtLeastOne = 1
