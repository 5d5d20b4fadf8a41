"""Manual detection QA, as the paper checked its labels (Table 4 bottom: 300 frames over crowded,
uncrowded and night conditions).

A reviewer looks at a frame's camera image with the dataset's pedestrians drawn on it (the rows
of the instances table: one 2D box and one body per track) and marks

- each labelled person: ``T`` (a real person, correctly labelled) or ``W`` (not a person: a
  false positive that became pedestrian voxels);
- each person the labels missed, by a click on the image at (u, v): ``M_vis`` (visible: it
  should have been found) or ``M_occ`` (mostly occluded).

The counts per condition are :class:`tasks.metrics.detection.DetectionCounts` (recall = T /
(T + M_vis), precision = T / (T + W)), the same table as the automatic detection figures.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from tasks.metrics.detection import DetectionCounts

#: what a mark says about a person (the columns of the paper's table)
MARK_KINDS: tuple[str, ...] = ("T", "M_vis", "M_occ", "W")
#: marks of a labelled person (one per track in the frame) and of a missed one (a click)
LABELLED_KINDS, MISSED_KINDS = ("T", "W"), ("M_vis", "M_occ")
CONDITIONS: tuple[str, ...] = ("crowded", "uncrowded", "night")


class QAMarkError(ValueError):
    """Marks of a frame that cannot be saved (an unmarked or unknown person, a bad kind or click);
    the message names the sequence, frame and value."""


@dataclass(frozen=True)
class Mark:
    """One verdict: ``kind`` in MARK_KINDS; ``track_id`` the labelled person (T / W), None for a
    miss; ``u``, ``v`` the click on the image in pixels (misses), None otherwise."""

    kind: str
    track_id: int | None = None
    u: float | None = None
    v: float | None = None


def frame_condition(is_night: bool, crowd: str | None, persons: int, crowded_min: int) -> str:
    """The QA condition of a frame: "night" at night; else the sequence's recorded crowd
    ("crowded" / "uncrowded", the simulator's metadata and evaluate's grouping) when it has one;
    else "crowded" when at least ``crowded_min`` persons are labelled in the frame."""
    if is_night:
        return "night"
    if crowd in ("crowded", "uncrowded"):
        return crowd
    return "crowded" if persons >= crowded_min else "uncrowded"


def sample_frames(conditions: Sequence[str], per_condition: int) -> list[int]:
    """Positions (into ``conditions``, one entry per candidate frame in dataset order) of the QA
    sample: per condition ``per_condition`` frames evenly spread over that condition's frames
    (all of them when there are fewer), ascending. Deterministic, so a pass can resume."""
    if per_condition < 1:
        raise QAMarkError(f"frames per condition must be >= 1, got {per_condition}")
    conditions = list(conditions)
    picked: list[int] = []
    for cond in sorted(set(conditions)):
        pos = [i for i, c in enumerate(conditions) if c == cond]
        n = min(per_condition, len(pos))
        picked += [pos[int(k)] for k in np.unique(np.linspace(0, len(pos) - 1, n).round())]
    return sorted(picked)


def check_marks(
    where: str,
    track_ids: Iterable[int],
    marks: Sequence[Mark],
    image_size: tuple[int, int] | None = None,
) -> None:
    """Raise QAMarkError unless ``marks`` are a whole verdict on a frame: every labelled person
    (``track_ids``) marked once as T or W, no other track, misses with a click inside the image
    (``image_size`` (width, height) px, when known). ``where`` names the frame in the message."""
    expected = {int(t) for t in track_ids}
    seen: dict[int, str] = {}
    for m in marks:
        if m.kind not in MARK_KINDS:
            raise QAMarkError(f"{where}: mark kind {m.kind!r}, expected one of {MARK_KINDS}")
        if m.kind in LABELLED_KINDS:
            if m.track_id is None:
                raise QAMarkError(f"{where}: a {m.kind} mark needs the track_id of the person")
            tid = int(m.track_id)
            if tid not in expected:
                raise QAMarkError(
                    f"{where}: track {tid} is not labelled in this frame (tracks {sorted(expected)})"
                )
            if tid in seen:
                raise QAMarkError(f"{where}: track {tid} marked twice ({seen[tid]}, {m.kind})")
            seen[tid] = m.kind
        else:
            if m.track_id is not None:
                raise QAMarkError(
                    f"{where}: a missed person ({m.kind}) has no track; got track_id {m.track_id}"
                )
            if m.u is None or m.v is None or not (np.isfinite(m.u) and np.isfinite(m.v)):
                raise QAMarkError(f"{where}: a missed person ({m.kind}) needs its click (u, v)")
            if image_size is not None and not (
                0 <= m.u < image_size[0] and 0 <= m.v < image_size[1]
            ):
                raise QAMarkError(
                    f"{where}: click ({m.u:.1f}, {m.v:.1f}) is outside the "
                    f"{image_size[0]} x {image_size[1]} image"
                )
    missing = sorted(expected - set(seen))
    if missing:
        raise QAMarkError(f"{where}: labelled person(s) {missing} not marked T or W")


def counts_by_condition(
    conditions: Sequence[str], kinds: Sequence[str]
) -> dict[str, DetectionCounts]:
    """Marks (one condition and one kind per mark) -> {condition: DetectionCounts}, conditions
    in CONDITIONS order (others after, sorted), then "all" (as the automatic detection table)."""
    out: dict[str, DetectionCounts] = {}
    for cond, kind in zip(conditions, kinds):
        if kind not in MARK_KINDS:
            continue  # a checked frame with nobody in it carries no mark
        c = out.get(cond, DetectionCounts())
        out[cond] = c + DetectionCounts(**{k: int(k == kind) for k in MARK_KINDS})
    order = [c for c in CONDITIONS if c in out] + sorted(set(out) - set(CONDITIONS))
    result = {c: out[c] for c in order}
    if result:
        total = DetectionCounts()
        for c in result.values():
            total = total + c
        result["all"] = total
    return result
