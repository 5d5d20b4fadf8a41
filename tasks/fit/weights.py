"""The fitting objective's weights (paper appendix B table): torch-free, so the config and the
planner read them without importing torch (tasks/fit/losses.py holds the terms).

One name per weight from the YAML to its term: ``fit.presets.<name>.lambda_3d`` is
:attr:`LossWeights.lambda_3d`, and the objective multiplies L_3D by
``weights.factor(weights.lambda_3d)`` (tasks/fit/optimize.py).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Annotated

from annotated_types import Interval

from tasks.bounds import NonNegative, Positive, Probability


@dataclass(frozen=True)
class LossWeights:
    """One row of the paper's appendix B table (a preset: ``fit.preset`` / ``fit.presets``).

    rho_px: Geman-McClure scale of L_J (pixels). lambda_*: term weights. w: backface threshold
    (see :func:`tasks.fit.visibility.visibility_masks`). j_conf: keypoint-confidence threshold
    of the part filter.
    """

    rho_px: Positive
    lambda_theta: NonNegative
    lambda_a: NonNegative
    lambda_beta: NonNegative
    lambda_3d: NonNegative
    lambda_occ: NonNegative
    w: Annotated[float, Interval(ge=-1, le=1)]
    j_conf: Probability


@dataclass(frozen=True)
class ObjectiveSettings:
    """How the objective uses any preset's weights (``fit.conf_power``, ``fit.square_lambdas``).

    conf_power: L_J weights are ``confidence ** conf_power``. square_lambdas: multiply the terms
    by ``lambda ** 2`` instead of ``lambda`` (the paper does not say which; SMPLify squares its
    prior weights). Default True: on the synthetic benchmark (Ouster-128, 3DPW preset, 16
    persons, vertex cap 3 cm) squared weights gave MPJPE 22 mm vs 119 mm unsquared, because with
    L_J in pixels^2 and L_3D in m^2 the unsquared lambda_3D = 800 leaves L_3D too weak.
    """

    conf_power: float = 2.0
    square_lambdas: bool = True


@dataclass(frozen=True)
class FitWeights(ObjectiveSettings, LossWeights):
    """What the objective reads: a preset's :class:`LossWeights` (fields first, in the table's
    order) and the :class:`ObjectiveSettings`."""

    @staticmethod
    def of(preset: LossWeights, objective: ObjectiveSettings) -> FitWeights:
        """A preset's weights with the objective's settings."""
        return FitWeights(
            **{f.name: getattr(preset, f.name) for f in fields(LossWeights)},
            **{f.name: getattr(objective, f.name) for f in fields(ObjectiveSettings)},
        )

    def factor(self, lam: float) -> float:
        """The multiplier of a term whose weight is ``lam`` (one of the ``lambda_*`` fields)."""
        value = float(lam)
        return value * value if self.square_lambdas else value

    def with_(self, **changes) -> FitWeights:
        """A copy with some fields changed (ablations: ``weights.with_(lambda_3d=0.0)``)."""
        return replace(self, **changes)


#: Presets from the paper's appendix table (rho_px, lambda_theta, lambda_a, lambda_beta,
#: lambda_3D, lambda_occ, w, J_conf), one per dataset; the config chooses one by name
#: (``fit.preset``) and may add its own (``fit.presets``).
FIT_PRESETS: dict[str, FitWeights] = {
    "3dpw": FitWeights(100.0, 2.2, 11.0, 5.0, 800.0, 35.0, 0.2, 0.6),
    "sloper4d": FitWeights(100.0, 0.75, 8.5, 1.0, 500.0, 55.0, 0.2, 0.7),
    "humanm3": FitWeights(100.0, 1.0, 3.0, 17.5, 600.0, 135.0, -1.0, 0.6),
    "ut_campus": FitWeights(100.0, 1.4, 10.0, 10.0, 300.0, 50.0, 0.2, 0.7),
}
