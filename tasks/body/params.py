"""The body-parameter bundle every stage passes around: SMPL parameters of B persons.

Whoever holds a :class:`BodyParams` says its frame: the camera frame (OpenCV) inside the fit and
its initial estimates, the LiDAR frame of the frame in the fit's ``Bodies`` product and in the
ground truth. Records that carry the same four arrays beside others (the fit's ``FitResult``
extends this class; the simulator's people, the ground-truth frame and the ``Bodies`` product
are flat file records) give theirs with :meth:`BodyParams.of`.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np


@dataclass(frozen=True)
class BodyParams:
    """SMPL parameters of B persons, float32 numpy: betas (B, 10), global_orient (B, 3) and
    body_pose (B, 69) axis-angle (rad), transl (B, 3) m."""

    betas: np.ndarray
    global_orient: np.ndarray
    body_pose: np.ndarray
    transl: np.ndarray

    #: the parameter arrays, in this order (also the positional order of the constructor)
    FIELDS: ClassVar[tuple[str, ...]] = ("betas", "global_orient", "body_pose", "transl")

    def __len__(self) -> int:
        return int(self.betas.shape[0])

    def take(self, idx) -> BodyParams:
        """Rows ``idx`` of every array."""
        return BodyParams(*(getattr(self, f)[idx] for f in BodyParams.FIELDS))

    @classmethod
    def of(cls, source: Any) -> BodyParams:
        """The four arrays of anything that carries them, as attributes (a ground-truth frame, a
        ``Bodies`` product, a fit result) or as keys (a mapping of arrays)."""
        if isinstance(source, Mapping):
            return BodyParams(*(source[f] for f in BodyParams.FIELDS))
        return BodyParams(*(getattr(source, f) for f in BodyParams.FIELDS))

    @classmethod
    def concat(cls, parts: Iterable[BodyParams]) -> BodyParams:
        """The rows of several bundles, one after another (at least one bundle)."""
        parts = list(parts)
        return BodyParams(
            *(np.concatenate([getattr(p, f) for p in parts]) for f in BodyParams.FIELDS)
        )

    @classmethod
    def empty(cls) -> BodyParams:
        """No persons: (0, ...) float32 arrays."""
        return BodyParams(*(np.zeros((0, n), np.float32) for n in (10, 3, 69, 3)))
