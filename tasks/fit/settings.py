"""How the fit stage fits: iterations, gates, batching (the objective's weights: tasks.fit.losses)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from tasks.bounds import AtLeastOne, Count, Positive


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
    run in order). seed: of the optimiser and the oracle's initial estimates.
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
    seed: int = 0
