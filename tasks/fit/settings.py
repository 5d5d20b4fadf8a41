"""How the fit stage fits: iterations, gates, batching (the objective's weights: tasks.fit.losses)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from tasks.bounds import AtLeastOne, Count, NonNegative, Positive, PositiveFraction, Probability

#: at most this many Adam steps: 100 x the default. A CPU core fits ~5 person-frames per second
#: at 100 steps (docs/fit-benchmark.md), ~2 ms per person-frame and step: 10,000 steps are
#: ~20 s per person-frame, and a sequence has thousands of them
MAX_ITERATIONS = 10_000
#: measured CPU seconds per person-frame and Adam step (one core; docs/fit-benchmark.md)
SECONDS_PER_PERSON_STEP = 2e-3


@dataclass(frozen=True)
class FitSettings:
    """Settings of the body fit (defaults measured on the synthetic benchmark, docs/fit-benchmark.md).

    iterations / learning_rate: Adam steps and step size. nn_every: recompute the Chamfer nearest
    pairs and the pose blend shapes every this many steps (no gradient flows through the blend
    shapes in between; 1 = the exact gradient every step; 5 measured as accurate as 1 and several
    times faster). converge_rtol: a person stops when its objective fell by less than this
    fraction between two refreshes (None: always ``iterations`` steps; on cold starts 1e-2 saved
    ~9 % of the steps at the same MPJPE, 1e-3 none). chamfer_vertex_max_m: cap of the vertex -> point distances in L_3D: a
    visible vertex with no LiDAR return this close is treated as unobserved (None = the paper's
    uncapped Chamfer; the cap removed a ~30 mm pull towards the sensor). min_points: detections
    with fewer LiDAR points in the image are not fitted (keypoints alone leave depth free); 0 fits
    all. max_shift_m: fits whose root moved farther from the initial estimate are dropped (latched
    onto someone else's points, or floated off; None keeps all). batch_persons: persons per
    batched optimisation (a person's fit does not depend on its batch). device: cpu, cuda or auto.
    warm_start: start a track's fit from its previous frame's fit (beyond the paper; frames then
    run in order), with warm_iterations Adam steps instead of ``iterations``. shared_shape: one
    shape per track (tasks/fit/shape.py), held while the track is refined. seed: of the
    optimiser and the oracle's initial estimates. iterations 0: no Adam step at all (the
    initial estimates, aligned only: configs/ground-truth-inputs.yaml); below 0 is refused.
    """

    iterations: Count = 100
    learning_rate: Positive = 0.02
    nn_every: AtLeastOne = 5
    converge_rtol: Positive | None = None
    chamfer_vertex_max_m: Positive | None = 0.03
    min_points: Count = 10
    max_shift_m: Positive | None = 1.5
    batch_persons: AtLeastOne = 64
    device: Literal["cpu", "cuda", "auto"] = "auto"
    warm_start: bool = False
    warm_iterations: Count = 30
    shared_shape: bool = True
    seed: int = 0
    #: ICP and L_3D read at most this many of the visible vertices, spread evenly over the
    #: template's surface (tasks.fit.optimize.uniform_vertex_subset; None: every visible vertex)
    data_vertices: AtLeastOne | None = 1500


@dataclass(frozen=True)
class InitLidarSettings:
    """Settings of the weight-free start (defaults measured on the fit benchmark's persons,
    docs/fit-benchmark.md).

    yaw_candidates: headings tried (evenly spaced over 360 deg; the fit's ICP corrects up to 30).
    min_lidar_points: fewer LiDAR points: place and turn the body by the keypoints alone.
    keypoint_min_confidence: keypoints below this confidence are not used.
    lidar_sigma_m: scale of the LiDAR term (m; its Chamfer distances are capped at
    ``lidar_cap_m``); keypoint_sigma: scale of the keypoint term (fraction of the person's height
    in pixels). The facing cost is chamfer / lidar_sigma^2 + keypoint_weight * mean GM(error /
    height; keypoint_sigma). limb_radius_m: depth from the surface a LiDAR point sees to the
    bone inside. foreshortening: a limb bone whose keypoints span at least this fraction of its
    length across the view is taken to lie across it (its depth from the keypoints is
    ill-conditioned); a shorter one points towards or away from the camera, which of the two
    the LiDAR points decide. max_points / max_vertices: subsampling of the scoring (speed).
    """

    yaw_candidates: AtLeastOne = 24
    min_lidar_points: AtLeastOne = 5
    keypoint_min_confidence: Probability = 0.3
    lidar_sigma_m: Positive = 0.03
    lidar_cap_m: Positive = 0.10
    keypoint_sigma: Positive = 0.1
    keypoint_weight: NonNegative = 4.0
    limb_radius_m: NonNegative = 0.05
    foreshortening: PositiveFraction = 0.85
    score_points: AtLeastOne = 256
    score_vertices: AtLeastOne = 500


@dataclass(frozen=True)
class FlipSettings:
    """How left / right swaps are decided (defaults measured on the benchmark, docs/fit-benchmark.md).

    enabled: decide (False: keypoints as detected, each row's cheapest heading). motion_weight /
    smooth_weight / cost_weight: weights of the walking-direction, smoothness and facing-cost
    terms (the facing cost is in units of :class:`tasks.fit.init_lidar.InitLidarSettings`).
    walking_min_speed_mps / walking_full_speed_mps: the walking direction counts from the first speed and fully
    from the second. velocity_window_s: half-width of the window whose positions give a row's
    velocity (a least-squares line). smooth_max_step_s: rows farther apart are not tied by smoothness.
    min_margin: a smaller difference between the two labellings' min-marginal costs keeps the
    keypoints as detected. follow_start: with a provider's start (not the weight-free one, which
    is built from the chosen labelling), relabel the face, arms and legs each towards the start's
    projected keypoints (tasks.fit.flips.chains_towards) in the rows left undecided
    ('undecided'), in every row ('always') or nowhere ('never'); start_margin: by at least this
    mean distance (fraction of the start's projected height). start_max_distance: with
    follow_start on, keypoints farther than this from the start's (fraction of its projected
    height) are dropped (tasks.fit.flips.far_from_start; None: none). Off by default: with the
    simulator's keypoints (the default config) the track's own decision is the better judge
    (benchmark sequence 1: MPJPE 43.4 mm off, 45.4 on); with a real network's keypoints it is
    not (bundled BlazePose, 4 sequences: 77.1 -> 64.8 mm), so configs/bundled-models.yaml turns
    it on (docs/fit-benchmark.md, "What BlazePose gets wrong").
    """

    enabled: bool = True
    motion_weight: NonNegative = 4.0
    smooth_weight: NonNegative = 4.0
    cost_weight: NonNegative = 1.0
    walking_min_speed_mps: NonNegative = 0.3
    walking_full_speed_mps: Positive = 0.8
    velocity_window_s: Positive = 0.45
    smooth_max_step_s: Positive = 0.5
    min_margin: NonNegative = 0.5
    follow_start: Literal["never", "undecided", "always"] = "never"
    start_margin: NonNegative = 0.05
    start_max_distance: Positive | None = 0.2


@dataclass(frozen=True)
class RefineSettings:
    """Settings of the track refinement (defaults measured on the track benchmark,
    docs/fit-benchmark.md).

    enabled: refine (False: per-frame fits as they are). iterations / learning_rate: Adam steps
    and step size of the refit (it starts from converged per-frame fits). joint_weight /
    root_weight: w_joints and w_root of L_acc (objective units per (m/frame^2)^2; the keypoint
    term is in pixels^2); torso_weight: w_torso of the spine, neck, head, collars and shoulders,
    which move nearly with the pelvis (joint_weight is then w_limbs). tie_max_step_s: neighbours farther apart are not tied. window_frames /
    overlap_frames: the windows of a long track. batch_rows: rows per batched refit.
    root_cutoff_hz / orient_cutoff_hz / pose_cutoff_hz: the refit's closed-form start, each
    track's pelvis path, global orientation (both in a world-fixed frame) and local joint
    rotations through a Whittaker smoother that halves a sine of this frequency, the same at any
    frame rate (tasks/fit/refine.py smooth_tracks; 0: that part starts as fitted).
    """

    enabled: bool = True
    iterations: Count = 30
    learning_rate: Positive = 0.002
    joint_weight: NonNegative = 100.0
    torso_weight: NonNegative = 0.0
    root_weight: NonNegative = 2.0e4
    tie_max_step_s: Positive = 0.5
    window_frames: AtLeastOne = 48
    overlap_frames: Count = 8
    batch_rows: AtLeastOne = 256
    root_cutoff_hz: NonNegative = 3.0
    orient_cutoff_hz: NonNegative = 3.0
    pose_cutoff_hz: NonNegative = 3.0


@dataclass(frozen=True)
class GapSettings:
    """Gap filling (defaults measured on the benchmark's night sequence, docs/fit-benchmark.md).

    enabled: fill gaps. max_gap_frames: longest run of missing frames filled (a longer one is
    left empty). support_radius_m / min_support_points / align_max_m: the check against the
    missing frame's sweep (module docstring). behind_margin_m: how far past (or before) the
    body's surface a return must lie to count as seen through (or in front)."""

    enabled: bool = True
    max_gap_frames: AtLeastOne = 2
    support_radius_m: Positive = 0.08
    min_support_points: AtLeastOne = 5
    align_max_m: NonNegative = 0.3
    behind_margin_m: Positive = 0.3
