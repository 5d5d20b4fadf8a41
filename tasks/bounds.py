"""Bounds of settings fields, written beside their defaults in the kernels' settings dataclasses.

PEP 593 metadata (annotated-types): to Python and the kernels a ``Positive`` field is a plain
float; the config (configs/schema.py) validates every section against these bounds, so a value
out of range is an error that names its key, never a kernel's surprise.
"""

from __future__ import annotations

from typing import Annotated

from annotated_types import Ge, Gt, Interval

#: > 0
Positive = Annotated[float, Gt(0)]
#: >= 0
NonNegative = Annotated[float, Ge(0)]
#: in [0, 1]
Probability = Annotated[float, Interval(ge=0, le=1)]
#: a whole number >= 0
Count = Annotated[int, Ge(0)]
#: a whole number >= 1
AtLeastOne = Annotated[int, Ge(1)]
#: a factor >= 1 (a gate that may only widen)
Widening = Annotated[float, Ge(1)]
#: in (0, 1]
PositiveFraction = Annotated[float, Interval(gt=0, le=1)]
#: a voxel edge in metres: 2 cm to 1 m
VoxelSize = Annotated[float, Interval(ge=0.02, le=1.0)]


# ---- plausibility bounds of inputs, per source (issue 41) ----------------------------------------
# A value beyond one of these is not a measurement: its frame (a sweep) or its sequence (a
# calibration, a pose track) fails with a line naming the file or topic, the frame and the value,
# before memory is spent on it. The readers (storage/sources) call the checks below.

#: a LiDAR point farther than this from the sensor on any axis (metres): OS1-128 ranges to 120 m
MAX_POINT_COORDINATE_M = 1.0e4
#: a sensor-to-sensor (or sensor-to-base) calibration translation longer than this (metres)
MAX_CALIBRATION_TRANSLATION_M = 100.0
#: max |R R^T - I| of a rotation read from a file (CODa's calibration tolerance too)
ROTATION_TOLERANCE = 1e-3
#: a robot faster than this between two poses (metres per second) is a broken pose, a jump
MAX_POSE_SPEED_M_S = 20.0
#: pose translations beyond this distance from the map origin are not a campus-scale map
MAX_POSITION_M = 1.0e5


def sweep_problem(points) -> str:
    """Why a sweep's (N, 3) point coordinates (metres, sensor frame) are implausible ("" when
    they are not): a coordinate beyond MAX_POINT_COORDINATE_M, or every point at (0, 0, 0) (a
    sweep of no returns written as zeros: an organised sweep stores a no-return as zeros, but
    not all of them). Empty input is normal input."""
    import numpy as np

    xyz = np.asarray(points)
    if xyz.size == 0:
        return ""
    far = np.abs(xyz).max(axis=1) > MAX_POINT_COORDINATE_M
    if far.any():
        first = int(np.flatnonzero(far)[0])
        return (
            f"{int(far.sum())} point(s) beyond {MAX_POINT_COORDINATE_M:g} m (first at point "
            f"{first}: {xyz[first].tolist()})"
        )
    if not xyz.any():
        return f"all {len(xyz)} points are at (0, 0, 0) (no return at all)"
    return ""


def rigid_problem(T, what: str = "transform", max_translation_m: float | None = None) -> str:
    """Why a 4 x 4 rigid transform is implausible ("" when it is not): non-finite values, a
    rotation not orthonormal with determinant +1 (ROTATION_TOLERANCE), a translation longer than
    ``max_translation_m`` (default MAX_CALIBRATION_TRANSLATION_M)."""
    import numpy as np

    T = np.asarray(T, dtype=np.float64)
    limit = MAX_CALIBRATION_TRANSLATION_M if max_translation_m is None else max_translation_m
    if T.shape != (4, 4) or not np.isfinite(T).all():
        return f"{what} has non-finite values or is not 4 x 4"
    R = T[:3, :3]
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    if err > ROTATION_TOLERANCE or float(np.linalg.det(R)) < 0:
        return (
            f"{what} rotation is not orthonormal with determinant +1 (max |R R^T - I| = "
            f"{err:.3g}, det {float(np.linalg.det(R)):.3g})"
        )
    t = float(np.linalg.norm(T[:3, 3]))
    if t > limit:
        return f"{what} translation is {t:.6g} m, more than the {limit:g} m a rig spans"
    return ""


def pose_track_problem(stamps_ns, translations) -> str:
    """Why a pose track is implausible ("" when it is not): a non-finite translation, or a jump
    faster than MAX_POSE_SPEED_M_S between consecutive stamps. stamps_ns (M,) int ns increasing,
    translations (M, 3) metres. Names the index of the first bad pose."""
    import numpy as np

    t = np.asarray(translations, dtype=np.float64).reshape(-1, 3)
    bad = ~np.isfinite(t).all(axis=1)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        return f"pose {k} is not finite ({t[k].tolist()})"
    if len(t) < 2:
        return ""
    dt = np.diff(np.asarray(stamps_ns, dtype=np.float64)) / 1e9
    step = np.linalg.norm(np.diff(t, axis=0), axis=1)
    speed = step / np.maximum(dt, 1e-3)
    jump = speed > MAX_POSE_SPEED_M_S
    if jump.any():
        k = int(np.flatnonzero(jump)[0])
        return (
            f"pose {k + 1} jumps {step[k]:.6g} m in {dt[k]:.3g} s ({speed[k]:.6g} m/s, more than "
            f"{MAX_POSE_SPEED_M_S:g} m/s)"
        )
    return ""


#: the most raw frames `simulate` writes per sequence: one hour at 10 Hz (each frame is a full
#: sweep and images in memory while written; 1e9 frames grew memory past 4 GB)
MAX_SIMULATED_FRAMES = 36_000
