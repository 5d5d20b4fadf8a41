"""The fitting objective's weights (paper appendix B table): torch-free, so the config and the
planner read them without importing torch (tasks/fit/losses.py holds the terms)."""

from __future__ import annotations

from dataclasses import dataclass, replace


@dataclass(frozen=True)
class FitWeights:
    """Scalar weights and thresholds of the objective (paper appendix B table).

    rho_px: Geman-McClure scale of L_J (pixels). lambda_*: term weights. w: backface threshold
    (see :func:`tasks.fit.visibility.visibility_masks`). j_conf: keypoint-confidence threshold
    of the part filter. conf_power: L_J weights are ``confidence ** conf_power``.
    square_lambdas: multiply the terms by ``lambda ** 2`` instead of ``lambda`` (the paper does
    not say which; SMPLify squares its prior weights). Default True: on the synthetic benchmark
    (Ouster-128, 3DPW preset, 16 persons, vertex cap 3 cm) squared weights gave MPJPE 22 mm vs
    119 mm unsquared, because with L_J in pixels^2 and L_3D in m^2 the unsquared lambda_3D = 800
    leaves L_3D too weak.
    """

    rho_px: float
    lambda_theta: float
    lambda_a: float
    lambda_beta: float
    lambda_3d: float
    lambda_occ: float
    w: float
    j_conf: float
    conf_power: float = 2.0
    square_lambdas: bool = True

    def scale(self, name: str) -> float:
        """The multiplier of term ``name`` ('theta', 'a', 'beta', '3d', 'occ')."""
        value = float(getattr(self, f"lambda_{name}"))
        return value * value if self.square_lambdas else value

    def with_(self, **changes) -> FitWeights:
        """A copy with some fields changed (ablations: ``weights.with_(lambda_3d=0.0)``)."""
        return replace(self, **changes)


#: Presets from the paper's appendix table (rho, lambda_theta, lambda_a, lambda_beta,
#: lambda_3D, lambda_occ, w, J_conf), one per dataset; the config chooses one by name
#: (``fit.preset``) and may add its own (``fit.presets``).
FIT_PRESETS: dict[str, FitWeights] = {
    "3dpw": FitWeights(100.0, 2.2, 11.0, 5.0, 800.0, 35.0, 0.2, 0.6),
    "sloper4d": FitWeights(100.0, 0.75, 8.5, 1.0, 500.0, 55.0, 0.2, 0.7),
    "humanm3": FitWeights(100.0, 1.0, 3.0, 17.5, 600.0, 135.0, -1.0, 0.6),
    "ut_campus": FitWeights(100.0, 1.4, 10.0, 10.0, 300.0, 50.0, 0.2, 0.7),
}
