"""The tracking gates at the frame rate the sequence is tracked at.

OC-SORT's ``max_age``, ``delta_t`` and ``min_hits``, the stitcher's ``stitch_max_gap`` and the world
check's ``window`` count frames. Their defaults were measured at 5 Hz (tasks/track/offline.py);
tracked at another rate (``dataset.rate_hz``: 10 Hz = every sensor frame) a count keeps its
*duration*: n frames at ``gates_rate_hz`` become round(n * rate_hz / gates_rate_hz) (at least the
smallest value the kernel accepts). So a lost track survives the same 6 s, the motion direction
looks back the same 0.6 s, fragments are joined across the same 2 s and the constant-velocity
prediction is fitted over the same 1 s of positions. Gates in metres and seconds (WorldCheck's
tol_m, speed_sigma_mps, max_speed_mps) need nothing. At gates_rate_hz itself every value is
unchanged.

``min_hits`` is different: it asks for consecutive detections, and a detector's misses are not
slower at a higher rate, so doubling it doubles the chance that a short run of misses keeps a real
person unconfirmed; its job, keeping sporadic false positives out, needs a count of independent
detections, which is rate-free for a per-frame detector. It is scaled only with
``scale_min_hits`` (a detector whose false positives persist in time, e.g. a sign seen as a
person for a second, would want it scaled). Measured on the 4-sequence benchmark: README,
"Labels at the sensor rate".
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from tasks.bounds import Positive
from tasks.track.ocsort import TrackerParams
from tasks.track.offline import OfflineParams, WorldCheck


@dataclass(frozen=True)
class GateRate:
    """gates_rate_hz: the frame rate at which the frame-counted gates are given (their defaults
    were measured at 5 Hz). scale_min_hits: scale OC-SORT's min_hits with the rate too."""

    gates_rate_hz: Positive = 5.0
    scale_min_hits: bool = False


def frames_at(count: int, scale: float, minimum: int) -> int:
    """A frame count kept in duration: round(count * scale) (halves up), at least ``minimum``;
    0 stays 0 (a gate switched off)."""
    if count == 0:
        return 0
    return max(minimum, math.floor(count * scale + 0.5))


def gates_at_rate(
    tracker: TrackerParams,
    offline: OfflineParams,
    check: WorldCheck,
    rate_hz: float,
    gate: GateRate = GateRate(),
) -> tuple[TrackerParams, OfflineParams, WorldCheck]:
    """The three settings objects with their frame counts at ``rate_hz`` (Hz, > 0)."""
    if not rate_hz > 0 or not gate.gates_rate_hz > 0:
        raise ValueError(
            f"gates_at_rate: rates must be > 0, got rate_hz={rate_hz}, "
            f"gates_rate_hz={gate.gates_rate_hz}"
        )
    s = rate_hz / gate.gates_rate_hz
    tracker = dataclasses.replace(
        tracker,
        max_age=frames_at(tracker.max_age, s, 1),
        delta_t=frames_at(tracker.delta_t, s, 1),
        min_hits=frames_at(tracker.min_hits, s, 1) if gate.scale_min_hits else tracker.min_hits,
    )
    offline = dataclasses.replace(offline, stitch_max_gap=frames_at(offline.stitch_max_gap, s, 1))
    check = dataclasses.replace(check, window=frames_at(check.window, s, 1))
    return tracker, offline, check
