"""LiDAR odometry with KISS-ICP (Vizzo et al., RA-L 2023; PyPI ``kiss-icp``, MIT): the poses of a
log that has none, from its sweeps alone.

One :class:`LidarOdometry` per sequence, one :meth:`LidarOdometry.step` per sweep at the sensor
rate (every sweep, not only the picked frames: ICP needs small motions between scans). Poses are
``T_first_from_lidar``: the LiDAR at each sweep in the LiDAR frame of the first sweep. The
configuration is built here from plain values (``model_construct``: KISS-ICP's settings class
would otherwise read ``KISS_ICP_*`` environment variables), and registration runs on one thread so
the trajectory is the same bytes on every machine.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tasks.bounds import AtLeastOne, NonNegative, Positive


@dataclass(frozen=True)
class OdometrySettings:
    """KISS-ICP's settings (its defaults, but the range limits and deskewing).

    scan_min_range_m, scan_max_range_m: the returns registered (metres from the sensor).
    voxel_size_m: map voxel size; None = scan_max_range_m / 100 (KISS-ICP's rule). deskew: correct
    each sweep's motion with its per-point times (real spinning LiDARs; off for sweeps taken at
    one instant, as the simulator's). max_points_per_voxel, initial_threshold_m, min_motion_m:
    KISS-ICP's map and adaptive-threshold settings; icp_max_iterations, convergence: its ICP loop.
    two_way: see :func:`two_way`.
    """

    scan_min_range_m: NonNegative = 0.5
    scan_max_range_m: Positive = 100.0
    voxel_size_m: Positive | None = None
    deskew: bool = True
    max_points_per_voxel: AtLeastOne = 20
    initial_threshold_m: Positive = 2.0
    min_motion_m: NonNegative = 0.1
    icp_max_iterations: AtLeastOne = 500
    convergence: Positive = 1e-4
    #: also run backwards from the last sweep and take each sweep's motion from the pass that is
    #: further from its own start (:func:`two_way`): a pass under-estimates its first metres
    #: while its motion model has no speed yet (along corridors and facades most)
    two_way: bool = True


def _config(s: OdometrySettings):
    from kiss_icp.config import KISSConfig
    from kiss_icp.config.config import (
        AdaptiveThresholdConfig,
        DataConfig,
        MappingConfig,
        RegistrationConfig,
    )

    return KISSConfig.model_construct(
        out_dir="",
        data=DataConfig(
            max_range=s.scan_max_range_m, min_range=s.scan_min_range_m, deskew=s.deskew
        ),
        registration=RegistrationConfig(
            max_num_iterations=s.icp_max_iterations,
            convergence_criterion=s.convergence,
            max_num_threads=1,
        ),
        mapping=MappingConfig(
            voxel_size=s.voxel_size_m if s.voxel_size_m is not None else s.scan_max_range_m / 100.0,
            max_points_per_voxel=s.max_points_per_voxel,
        ),
        adaptive_threshold=AdaptiveThresholdConfig(
            initial_threshold=s.initial_threshold_m, min_motion_th=s.min_motion_m
        ),
    )


class LidarOdometry:
    """KISS-ICP over a sequence's sweeps, one :meth:`step` per sweep in stamp order."""

    def __init__(self, settings: OdometrySettings = OdometrySettings()):
        from kiss_icp.kiss_icp import KissICP

        self.settings = settings
        self._icp = KissICP(_config(settings))

    def step(self, points_lidar: np.ndarray, time_s: np.ndarray | None = None) -> np.ndarray:
        """The sweep's pose T_first_from_lidar (4, 4) float64. points_lidar (N, 3) LiDAR frame,
        metres; time_s (N,) seconds within the sweep (normalised to [0, 1] for deskewing), or
        None."""
        pts = np.asarray(points_lidar, dtype=np.float64)
        if time_s is not None and self.settings.deskew and len(time_s):
            t = np.asarray(time_s, np.float64)
            span = float(t.max() - t.min())
            stamps = (t - t.min()) / span if span > 0 else np.zeros_like(t)
        else:
            stamps = np.zeros(0, np.float64)
        self._icp.register_frame(pts, stamps)
        return np.array(self._icp.last_pose, dtype=np.float64)


def two_way(forward: np.ndarray, backward: np.ndarray) -> np.ndarray:
    """(K, 4, 4) T_first_from_lidar from a forward pass (K, 4, 4) T_first_from_lidar and a
    backward pass over the reversed sweeps, given per sweep as (K, 4, 4) T_last_from_lidar.

    Each pass under-estimates the motion of its first sweeps (its constant-velocity prediction
    starts at zero speed), so sweep k's motion from sweep k - 1 is the forward pass's in the
    second half of the sequence and the backward pass's in the first half; the poses are those
    motions chained from the first sweep (identity)."""
    n = len(forward)
    if n == 0:
        return np.zeros((0, 4, 4))
    out = np.tile(np.eye(4), (n, 1, 1))
    for k in range(1, n):
        src = forward if k >= n // 2 else backward
        out[k] = out[k - 1] @ (np.linalg.inv(src[k - 1]) @ src[k])
    return out


def lidar_odometry(sweeps, settings: OdometrySettings = OdometrySettings()) -> np.ndarray:
    """(K, 4, 4) float64 T_first_from_lidar of K sweeps, each (points (N, 3), time_s (N,) | None),
    a list (two_way needs them again in reverse)."""
    if not sweeps:
        return np.zeros((0, 4, 4))
    odo = LidarOdometry(settings)
    forward = np.stack([odo.step(p, t) for p, t in sweeps])
    if not settings.two_way:
        return forward
    back = LidarOdometry(settings)
    backward = np.stack([back.step(p, None if t is None else -t) for p, t in reversed(sweeps)])
    return two_way(forward, backward[::-1])
