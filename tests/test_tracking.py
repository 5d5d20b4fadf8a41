"""PedestrianTracker (OC-SORT) on scripted scenarios with known ids."""

from __future__ import annotations

import numpy as np
import pytest

from tasks.track.ocsort import PedestrianTracker


def _box(cx: float, cy: float = 200.0, w: float = 40.0, h: float = 100.0) -> list[float]:
    return [cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2]


def _run(tracker: PedestrianTracker, frames: list[list[list[float]]], scores=None) -> list[np.ndarray]:
    out = []
    for f, boxes in enumerate(frames):
        s = np.full(len(boxes), 0.9) if scores is None else np.asarray(scores[f])
        out.append(tracker.update(np.asarray(boxes, np.float32).reshape(-1, 4), s))
    return out


def test_two_people_crossing_keep_their_ids():
    # A walks right, B walks left; they pass each other (boxes overlap) around frame 20.
    frames = [[_box(100 + 10 * f), _box(500 - 10 * f, cy=210)] for f in range(40)]
    ids = _run(PedestrianTracker(), frames)
    # ids come back aligned with the input rows (row 0 = A, row 1 = B)
    assert all(row.dtype == np.int64 for row in ids)
    assert {tuple(row) for row in ids[1:]} == {(1, 2)}
    # input order reversed: ids follow the rows
    tracker = PedestrianTracker()
    rev = _run(tracker, [b[::-1] for b in frames])
    assert len({tuple(row) for row in rev[1:]}) == 1 and rev[-1][0] != rev[-1][1]


def test_occluded_for_ten_frames_is_refound_with_same_id():
    frames = []
    for f in range(40):
        boxes = [_box(600, cy=300)]  # a standing person, always seen
        if not 10 <= f < 20:
            boxes.append(_box(100 + 5 * f))  # walker, hidden for frames 10..19
        frames.append(boxes)
    ids = _run(PedestrianTracker(), frames)
    assert [row.tolist() for row in ids[1:10]] == [[1, 2]] * 9
    assert [row.tolist() for row in ids[10:20]] == [[1]] * 10
    assert [row.tolist() for row in ids[20:]] == [[1, 2]] * 20


def test_reference_mode_reconfirms_after_a_miss():
    # keep_confirmed_ids=False: OC-SORT reference output, id hidden while the streak rebuilds
    frames = [[_box(100 + 5 * f)] if f != 5 else [] for f in range(10)]
    ids = _run(PedestrianTracker(keep_confirmed_ids=False), frames)
    assert [row.tolist() for row in ids] == [[-1], [1], [1], [1], [1], [], [-1], [-1], [1], [1]]


def test_empty_frames_and_empty_sequence():
    tracker = PedestrianTracker()
    out = tracker.update(np.zeros((0, 4), np.float32), np.zeros(0, np.float32))
    assert out.shape == (0,) and out.dtype == np.int64
    frames = [[_box(100 + 5 * f)] if f != 5 else [] for f in range(10)]
    ids = _run(tracker, frames)
    assert ids[5].shape == (0,)
    assert [row.tolist() for f, row in enumerate(ids) if f not in (0, 5)] == [[1]] * 8


def test_false_positive_burst_creates_no_track_and_steals_no_id():
    rng = np.random.default_rng(0)
    frames, scores = [], []
    for f in range(30):
        boxes, s = [_box(100 + 5 * f)], [0.9]
        if f in (10, 12, 14):  # scattered high-score FPs, never twice in the same place
            for _ in range(5):
                boxes.append(_box(rng.uniform(300, 1000), cy=rng.uniform(100, 600)))
                s.append(0.8)
        if 15 <= f < 25:  # a steady low-score FP below det_thresh
            boxes.append(_box(900, cy=500))
            s.append(0.4)
        frames.append(boxes)
        scores.append(s)
    # a real person appearing after the burst gets id 2, not a later number
    for f in range(20, 30):
        frames[f].append(_box(1200 - 5 * f, cy=400))
        scores[f].append(0.9)
    ids = _run(PedestrianTracker(), frames, scores)
    assert all(row[0] == 1 for row in ids[1:])
    assert all((row[1:] == -1).all() for row in ids[:20])
    assert ids[29][-1] == 2
    confirmed = set(np.concatenate(ids).tolist()) - {-1}
    assert confirmed == {1, 2}


def test_instances_are_independent_and_deterministic():
    frames = [[_box(100 + 5 * f), _box(600 - 5 * f, cy=400)] for f in range(15)]
    first = _run(PedestrianTracker(), frames)
    other = PedestrianTracker()
    _run(other, [[_box(50 + 3 * f)] * 1 for f in range(10)])  # another sequence advancing
    second = _run(PedestrianTracker(), frames)
    assert [r.tolist() for r in first] == [r.tolist() for r in second]
    assert first[-1].tolist() == [1, 2]


def test_bad_input():
    with pytest.raises(ValueError, match="2 boxes but 1 scores"):
        PedestrianTracker().update(np.zeros((2, 4)), np.ones(1))
    with pytest.raises(ValueError, match="NaN"):
        PedestrianTracker().update(np.full((1, 4), np.nan), np.ones(1))
