"""PedestrianTracker (OC-SORT) on scripted scenarios with known ids."""

from __future__ import annotations

import numpy as np
import pytest

from tasks.track.ocsort import PedestrianTracker, TrackerParams


def _box(cx: float, cy: float = 200.0, w: float = 40.0, h: float = 100.0) -> list[float]:
    return [cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2]


def _run(
    tracker: PedestrianTracker, frames: list[list[list[float]]], scores=None
) -> list[np.ndarray]:
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
    ids = _run(PedestrianTracker(TrackerParams(keep_confirmed_ids=False)), frames)
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


# ---- offline refinement (tasks/track/offline.py) ----------------------------------------------

from tasks.track.offline import OfflineParams, backfill_ids, stitch_ids, track_offline  # noqa: E402


def _offline(frames, scores=None, backfill=True, stitch_max_gap=0, stitch_max_distance=0.5, **kw):
    tracker_kw = {k: kw.pop(k) for k in list(kw) if k in ("max_age", "min_hits", "iou_threshold")}
    s = [
        np.full(len(b), 0.9) if scores is None else np.asarray(scores[f])
        for f, b in enumerate(frames)
    ]
    boxes = [np.asarray(b, np.float32).reshape(-1, 4) for b in frames]
    offline = OfflineParams(
        backfill=backfill, stitch_max_gap=stitch_max_gap, stitch_max_distance=stitch_max_distance
    )
    return track_offline(boxes, s, PedestrianTracker(TrackerParams(**tracker_kw)), offline, **kw)


def test_backfill_gives_first_frames_and_frame_zero_their_id():
    # A from frame 0; B appears at frame 5. Online, frame 0 and B's first two frames are tentative.
    frames = [
        [_box(100 + 5 * f)] + ([_box(900 - 5 * f, cy=400)] if f >= 5 else []) for f in range(12)
    ]
    online = _run(PedestrianTracker(), frames)
    assert (
        online[0].tolist() == [-1]
        and online[5].tolist() == [1, -1]
        and online[6].tolist() == [1, -1]
    )
    ids = _offline(frames, backfill=True)
    assert ids[0].tolist() == [1]
    assert [row.tolist() for row in ids[5:]] == [[1, 2]] * 7
    # without back-fill the tentative rows stay untracked
    assert _offline(frames, backfill=False)[5].tolist() == [1, -1]


def test_backfill_leaves_unconfirmed_tracklets_alone():
    # a box seen twice (below min_hits = 3) is never confirmed: no id, even offline
    frames = [[_box(100 + 5 * f)] + ([_box(700, cy=500)] if f in (6, 7) else []) for f in range(12)]
    ids = _offline(frames, backfill=True)
    assert ids[6].tolist() == [1, -1] and ids[7].tolist() == [1, -1]


def test_tracklet_keys_follow_rows_and_skip_low_scores():
    tracker = PedestrianTracker()
    for f in range(4):
        tracker.update(
            np.asarray([_box(100 + 5 * f), _box(600, cy=400)], np.float32), np.array([0.9, 0.3])
        )
    assert [k.tolist() for k in tracker.tracklet_keys] == [[0, -1]] * 4
    assert tracker.confirmed_ids == {0: 1}


def test_stitching_joins_a_walker_hidden_longer_than_max_age():
    # hidden for frames 10..17 (8 frames) with max_age 3: OC-SORT drops the track and starts anew
    frames = [
        [_box(600, cy=300)] + ([] if 10 <= f < 18 else [_box(100 + 8 * f)]) for f in range(30)
    ]
    plain = _offline(frames, max_age=3, backfill=True, stitch_max_gap=0)
    assert len(set(np.concatenate(plain).tolist()) - {-1}) == 3
    ids = _offline(frames, max_age=3, backfill=True, stitch_max_gap=10, stitch_max_distance=0.5)
    assert set(np.concatenate(ids).tolist()) == {1, 2}
    walker = {row[1] for row in ids if len(row) == 2}
    assert walker == {2}
    # a gap longer than stitch_max_gap is not bridged
    short = _offline(frames, max_age=3, backfill=True, stitch_max_gap=7, stitch_max_distance=0.5)
    assert len(set(np.concatenate(short).tolist()) - {-1}) == 3


def test_stitching_does_not_join_different_people():
    # A walks right and leaves at frame 10 near x = 150; B appears at frame 14 at x = 800 walking
    # left: the gap is short but neither extrapolation lands near the other
    frames = [
        [_box(100 + 5 * f)] if f < 10 else ([_box(870 - 5 * f)] if f >= 14 else [])
        for f in range(25)
    ]
    ids = _offline(frames, backfill=True, stitch_max_gap=10, stitch_max_distance=0.5)
    assert ids[0].tolist() == [1] and ids[14].tolist() == [2] and ids[24].tolist() == [2]


def test_stitch_ids_chains_and_never_overlaps_in_time():
    # three fragments of one walker (ids 7, 3, 9) and a fourth id that overlaps fragment 3 in time
    walker = lambda f: _box(100 + 10 * f)  # noqa: E731
    ids, boxes = [], []
    for f in range(20):
        rows, bx = [], []
        if f < 5 or 7 <= f < 12 or f >= 14:
            rows.append(7 if f < 5 else 3 if f < 12 else 9)
            bx.append(walker(f))
        if 8 <= f < 10:  # another person at the walker's extrapolated place, during fragment 3
            rows.append(5)
            bx.append(walker(f + 2))
        ids.append(np.asarray(rows, np.int64))
        boxes.append(np.asarray(bx, np.float64).reshape(-1, 4))
    out = stitch_ids(ids, boxes, OfflineParams(stitch_max_gap=5))
    walker_ids = {int(row[0]) for row in out if len(row)}
    assert walker_ids == {1}  # renumbered from 1 by first appearance, one id over all fragments
    assert out[8].tolist() == [1, 2]
    # max_gap 0: no joins, ids only renumbered (7, 3, 5, 9 -> 1, 2, 3, 4)
    assert stitch_ids(ids, boxes, OfflineParams(stitch_max_gap=0))[14].tolist() == [4]


def test_offline_ids_are_deterministic():
    rng = np.random.default_rng(3)
    frames = [
        [
            _box(100 + 7 * f + rng.normal(0, 2), cy=200 + 40 * k)
            for k in range(4)
            if rng.random() > 0.2
        ]
        for f in range(40)
    ]
    first = _offline(frames, backfill=True, stitch_max_gap=10, stitch_max_distance=0.5)
    second = _offline(frames, backfill=True, stitch_max_gap=10, stitch_max_distance=0.5)
    assert [r.tolist() for r in first] == [r.tolist() for r in second]
    seen = [i for row in first for i in row.tolist() if i > 0]
    assert sorted(set(seen)) == list(range(1, len(set(seen)) + 1))
    assert seen[0] == 1


def test_backfill_ids_keeps_online_ids():
    keys = [np.array([0, 1]), np.array([0, 1])]
    online = [np.array([-1, -1]), np.array([4, -1])]
    assert [r.tolist() for r in backfill_ids(keys, online, {0: 4})] == [[4, -1], [4, -1]]


# ---- world-position check (split_tracks / stitch_ids with positions) ---------------------------

from tasks.track.offline import split_tracks  # noqa: E402

_DT = 0.2  # 5 Hz


def _walk(x0: float, y: float, vx: float, frames: range) -> dict[int, np.ndarray]:
    return {f: np.array([x0 + vx * _DT * f, y]) for f in frames}


def _refine(ids, boxes, positions, tentative=frozenset()):
    times = np.arange(len(ids)) * _DT
    split, clean, parent = split_tracks(ids, positions, times)
    provisional = {frag for frag, p in parent.items() if p in tentative}
    return stitch_ids(
        split,
        boxes,
        OfflineParams(stitch_max_gap=10),
        positions=clean,
        times_s=times,
        parent=parent,
        provisional=provisional,
    )


def test_world_positions_undo_a_swap_between_people_overlapping_in_the_image():
    # B walks 1 m behind A in the same direction: their boxes nearly coincide, and the 2D tracker
    # swapped their ids at frame 10 (row 0 is always A, row 1 always B)
    a, b = _walk(8.0, 0.0, -1.4, range(20)), _walk(9.0, 0.1, -1.4, range(20))
    ids = [np.array([1, 2]) if f < 10 else np.array([2, 1]) for f in range(20)]
    boxes = [np.array([_box(300), _box(302)]) for _ in range(20)]
    positions = [np.stack([a[f], b[f]]) for f in range(20)]
    out = _refine(ids, boxes, positions)
    assert {int(r[0]) for r in out} == {1} and {int(r[1]) for r in out} == {2}
    # without positions the swap stays (nothing to see it by)
    nan = [np.full((2, 2), np.nan) for _ in range(20)]
    blind = _refine(ids, boxes, nan)
    assert blind[0].tolist() == [1, 2] and blind[19].tolist() == [2, 1]


def test_one_stray_position_is_an_outlier_not_a_cut():
    a = _walk(8.0, 0.0, -1.4, range(15))
    positions = [a[f][None] for f in range(15)]
    positions[7] = positions[7] + np.array([[2.0, 0.0]])  # points of the person in front
    ids = [np.array([1]) for _ in range(15)]
    split, clean, parent = split_tracks(ids, positions, np.arange(15) * _DT)
    assert {int(r[0]) for r in split} == {1} and parent == {1: 1}
    assert np.isnan(clean[7]).all() and np.isfinite(clean[6]).all()
    # two frames off in a row are another person: cut in and out again; stitching then joins
    # the two ends of A around them
    positions[8] = positions[8] + np.array([[2.0, 0.0]])
    split, _, parent = split_tracks(ids, positions, np.arange(15) * _DT)
    assert len({int(r[0]) for r in split}) == 3 and set(parent.values()) == {1}
    out = _refine(ids, [np.array([_box(300)])] * 15, positions)
    assert out[0].tolist() == out[14].tolist() == [1] and out[7].tolist() == out[8].tolist() == [2]


def test_a_lost_person_rejoins_on_position_and_a_stranger_does_not():
    # A hidden for frames 8..11; the robot turned meanwhile, so A's box reappears far away in the
    # image. C appears at frame 12 right where A's box was extrapolated, but 3 m away in the world.
    a, c = _walk(8.0, 0.0, -1.4, range(20)), _walk(11.0, 0.0, -1.4, range(20))
    ids, boxes, positions = [], [], []
    for f in range(20):
        rows_id, rows_box, rows_xy = [], [], []
        if f < 8 or f >= 12:
            rows_id.append(1 if f < 8 else 2)
            rows_box.append(_box(300 + 5 * f if f < 8 else 700))
            rows_xy.append(a[f])
        if f >= 12:
            rows_id.append(3)
            rows_box.append(_box(300 + 5 * f))
            rows_xy.append(c[f])
        ids.append(np.array(rows_id, np.int64))
        boxes.append(np.array(rows_box, np.float64).reshape(-1, 4))
        positions.append(np.array(rows_xy, np.float64).reshape(-1, 2))
    out = _refine(ids, boxes, positions)
    assert out[0].tolist() == [1] and out[12].tolist() == [1, 2] and out[19].tolist() == [1, 2]
    # on pixels alone the stranger takes A's id
    assert stitch_ids(ids, boxes, OfflineParams(stitch_max_gap=10))[12].tolist() == [2, 1]


def test_the_trackers_own_continuation_stands_where_no_position_judges_it():
    ids = [np.array([1]) for f in range(12) if f != 5]
    boxes = [np.array([_box(100 + 40 * f)]) for f in range(12) if f != 5]  # fast: pixel gate fails
    ids.insert(5, np.zeros(0, np.int64))
    boxes.insert(5, np.zeros((0, 4)))
    positions = [np.full((len(i), 2), np.nan) for i in ids]
    out = _refine(ids, boxes, positions)
    assert {int(r[0]) for r in out if len(r)} == {1}


def test_tentative_fragments_join_a_confirmed_track_or_are_dropped():
    a = _walk(8.0, 0.0, -1.4, range(14))
    # A confirmed on frames 0..9, missed 10..11, seen again on 12..13 by a tracklet that never got
    # min_hits (id 50, provisional); a lone provisional tracklet (id 51) elsewhere.
    ids = [
        np.array([1]) if f < 10 else np.array([50, 51]) if f >= 12 else np.zeros(0, np.int64)
        for f in range(14)
    ]
    boxes = [
        np.array([_box(300)])
        if f < 10
        else np.array([_box(600), _box(900)])
        if f >= 12
        else np.zeros((0, 4))
        for f in range(14)
    ]
    positions = [
        np.array([a[f]])
        if f < 10
        else np.array([a[f], [20.0, 5.0]])
        if f >= 12
        else np.zeros((0, 2))
        for f in range(14)
    ]
    out = _refine(ids, boxes, positions, tentative={50, 51})
    assert out[12].tolist() == [1, -1] and out[13].tolist() == [1, -1]


def test_person_world_xy_is_the_median_point_in_the_world_and_needs_min_points():
    from tasks.track.product import person_world_xy

    points = np.array(
        [[5.0, 1.0, 0.5], [5.2, 1.1, 1.0], [5.1, 0.9, 1.5], [30.0, 9.0, 1.0]], np.float32
    )
    T = np.eye(4)
    T[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]  # yaw 90 degrees
    T[:3, 3] = [100.0, 50.0, 0.0]
    xy = person_world_xy(points, [np.array([0, 1, 2]), np.array([3])], T, min_points=3)
    assert np.allclose(xy[0], [100.0 - 1.0, 50.0 + 5.1])
    assert np.isnan(xy[1]).all()


def test_an_outlier_just_before_a_missed_stretch_does_not_split_the_track():
    # frame 7's points belong to someone in front, frames 8..10 are missed, A is seen again at 11
    frames = [f for f in range(18) if not 8 <= f <= 10]
    a = _walk(8.0, 0.0, -1.4, range(18))
    ids = [np.array([1]) if f in frames else np.zeros(0, np.int64) for f in range(18)]
    boxes = [np.array([_box(300 + 60 * f)]) if f in frames else np.zeros((0, 4)) for f in range(18)]
    positions = [np.array([a[f]]) if f in frames else np.zeros((0, 2)) for f in range(18)]
    positions[7] = np.array([[4.0, 0.5]])
    out = _refine(ids, boxes, positions)
    assert {int(r[0]) for r in out if len(r)} == {1}


# ---- the gates at the tracking rate (tasks/track/rate.py) -------------------------------------------

from tasks.track.offline import WorldCheck  # noqa: E402
from tasks.track.rate import GateRate, frames_at, gates_at_rate  # noqa: E402


def test_gates_keep_their_duration_at_another_rate():
    base = (TrackerParams(), OfflineParams(), WorldCheck())
    assert gates_at_rate(*base, 5.0) == base  # the rate they are given at: unchanged
    tracker, offline, check = gates_at_rate(*base, 10.0)
    assert (tracker.max_age, tracker.delta_t, tracker.min_hits) == (60, 6, 3)
    assert (offline.stitch_max_gap, check.window) == (20, 10)
    assert gates_at_rate(*base, 10.0, GateRate(scale_min_hits=True))[0].min_hits == 6
    tracker, offline, check = gates_at_rate(*base, 2.5)
    assert (tracker.max_age, tracker.delta_t, offline.stitch_max_gap, check.window) == (
        15,
        2,
        5,
        3,
    )  # halves up
    assert gates_at_rate(*base, 10.0, GateRate(gates_rate_hz=10.0)) == base
    assert (
        frames_at(0, 2.0, 1) == 0 and frames_at(1, 0.1, 1) == 1
    )  # off stays off; never below the minimum
    with pytest.raises(ValueError, match="rates must be > 0"):
        gates_at_rate(*base, 0.0)


def test_a_walker_hidden_for_1_6_s_is_joined_at_5_and_at_10_hz():
    """The same scene sampled at 5 and 10 Hz (a walker at 40 px/s hidden from 2.0 to 3.6 s, beside
    a standing person): with the gates scaled to the rate the walker keeps one id at both; at
    10 Hz with the 5 Hz frame counts the gap (17 frames) is longer than stitch_max_gap (10)."""

    def ids_at(rate, scaled):
        frames = [
            [_box(600, cy=300)] + ([] if 2.0 <= f / rate < 3.6 else [_box(100 + 40 * f / rate)])
            for f in range(int(6 * rate))
        ]
        base = (TrackerParams(max_age=3), OfflineParams(stitch_max_gap=10), WorldCheck())
        tracker, offline, _ = gates_at_rate(*base, rate) if scaled else base
        boxes = [np.asarray(b, np.float32).reshape(-1, 4) for b in frames]
        ids = track_offline(
            boxes, [np.full(len(b), 0.9) for b in boxes], PedestrianTracker(tracker), offline
        )
        return set(np.concatenate(ids).tolist()) - {-1}

    assert ids_at(5.0, True) == {1, 2} and ids_at(10.0, True) == {1, 2}
    assert len(ids_at(10.0, False)) == 3
