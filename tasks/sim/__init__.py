"""Synthetic campus sequences with exact ground truth (scene, sensors, ground truth kernels).

Entry point: :class:`tasks.sim.frame.Simulator` built from :class:`tasks.sim.scene.SimOptions`.
"""

from tasks.sim.frame import PeopleFrame, SimFrame, Simulator
from tasks.sim.groundtruth import GridSpec
from tasks.sim.scene import SimOptions

__all__ = ["GridSpec", "PeopleFrame", "SimFrame", "SimOptions", "Simulator"]
