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
