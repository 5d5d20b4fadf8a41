"""Offline refinement of OC-SORT output over a whole sequence: back-fill and fragment stitching.

The pipeline tracks recorded logs, so a track's future is known when its ids are written. Two
steps use that (both standard in offline MOT post-processing):

- back-fill: OC-SORT reports a new track only after ``min_hits`` consecutive hits (and never on
  the first frame of a sequence); those first, tentative detections belong to the track once it is
  confirmed, so every row of a confirmed tracklet gets the tracklet's id.
- stitching: a person lost for longer than the tracker's ``max_age`` (or re-found too far from the
  Kalman prediction) comes back as a new track. A track B that starts at most ``max_gap`` frames
  after track A ends is joined to A when constant-velocity extrapolation of each towards the other
  lands near the other's box: ``d = mean(|c_A(t_B) - c_B(t_B)|, |c_B(t_A) - c_A(t_A)|) / h``, box
  centres c in pixels, velocities from a least-squares line over each track's last (first)
  ``window`` observations, h the mean box height of the two end boxes; pairs with
  ``d <= max_distance`` and a height ratio within ``max_scale`` are candidates, and a one-to-one
  assignment (Hungarian, cost d) between track ends and track starts picks the joins. Joins chain
  (A -> B -> C); they never make a track hold two boxes in one frame.

Measured on four synthetic crowded day sequences (calibrated oracle detections, 5 Hz, 30 frames each;
IDF1 of all four together): online OC-SORT 82.4, stitching alone 83.9, back-fill 85.2, back-fill +
stitching (gap 10, gate 0.5) 87.2; the gate is not sensitive (0.5 and 1.0 give the same).
Shorter OC-SORT ``max_age`` (5 frames) helped the two tuning sequences and hurt the two held-out
ones (86.4 together), so the reference 30 stays.

Ids of the result are 1, 2, ... in order of first appearance (frame, then input row): deterministic
for given input.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment


def backfill_ids(tracklet_keys: list[np.ndarray], online_ids: list[np.ndarray],
                 confirmed_ids: dict[int, int]) -> list[np.ndarray]:
    """Online ids with every row of a confirmed tracklet carrying that tracklet's id.

    tracklet_keys, online_ids: per frame (D_f,) int64, aligned with the frame's detections (key -1:
    the row started or updated no tracklet; id -1: not reported online). confirmed_ids: tracklet
    key -> id. Returns per frame (D_f,) int64 ids, -1 = untracked.
    """
    out = []
    for keys, ids in zip(tracklet_keys, online_ids):
        ids = np.asarray(ids, np.int64).copy()
        for row, key in enumerate(np.asarray(keys, np.int64)):
            if ids[row] < 0 and int(key) in confirmed_ids:
                ids[row] = confirmed_ids[int(key)]
        out.append(ids)
    return out


def _end_motion(frames: np.ndarray, centres: np.ndarray, at: float) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares line through (frame, centre (2,) px): (centre at frame ``at``, velocity px/frame)."""
    if len(frames) < 2:
        return centres[0], np.zeros(2)
    t = frames - at
    A = np.stack([np.ones_like(t), t], axis=1).astype(np.float64)
    coef, *_ = np.linalg.lstsq(A, centres, rcond=None)
    return coef[0], coef[1]


def stitch_ids(ids: list[np.ndarray], boxes_xyxy: list[np.ndarray], max_gap: int,
               max_distance: float, max_scale: float = 1.5, window: int = 5) -> list[np.ndarray]:
    """Join track fragments across gaps (see the module docstring); ids renumbered 1, 2, ...

    ids: per frame (D_f,) int64 (-1 = untracked, left alone); boxes_xyxy: per frame (D_f, 4) float
    pixels. max_gap: largest frame gap (frames between A's last and B's first box, >= 1) to join;
    0 disables joining. max_distance: gate on d, in box heights. max_scale: gate on the ratio of
    the end boxes' heights (>= 1). window: observations per end for the velocity fit.
    Returns per frame (D_f,) int64.
    """
    tracks: dict[int, tuple[list[int], list[np.ndarray]]] = {}
    for f, (row_ids, boxes) in enumerate(zip(ids, boxes_xyxy)):
        boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
        for row, tid in enumerate(np.asarray(row_ids, np.int64)):
            if tid >= 0:
                fr, bx = tracks.setdefault(int(tid), ([], []))
                fr.append(f)
                bx.append(boxes[row])
    merged = {tid: tid for tid in tracks}
    if max_gap >= 1 and len(tracks) > 1:
        ends, starts = {}, {}
        for tid, (fr, bx) in tracks.items():
            fr_arr, bx_arr = np.asarray(fr, np.float64), np.asarray(bx)
            centres, heights = (bx_arr[:, :2] + bx_arr[:, 2:]) / 2, bx_arr[:, 3] - bx_arr[:, 1]
            ends[tid] = (fr[-1], *_end_motion(fr_arr[-window:], centres[-window:], fr[-1]), heights[-1])
            starts[tid] = (fr[0], *_end_motion(fr_arr[:window], centres[:window], fr[0]), heights[0])
        order = sorted(tracks)
        cost = np.full((len(order), len(order)), np.inf)
        for i, a in enumerate(order):
            fa, ca, va, ha = ends[a]
            for j, b in enumerate(order):
                fb, cb, vb, hb = starts[b]
                gap = fb - fa
                if a == b or not 1 <= gap <= max_gap or max(ha, hb) > max_scale * min(ha, hb):
                    continue
                # A carried forward to B's first frame, B carried back to A's last frame
                err = (np.linalg.norm(ca + va * gap - cb) + np.linalg.norm(cb - vb * gap - ca)) / 2
                d = err / ((ha + hb) / 2)
                if d <= max_distance:
                    cost[i, j] = d
        rows, cols = linear_sum_assignment(np.where(np.isfinite(cost), cost, 1e9))
        successor = {order[i]: order[j] for i, j in zip(rows, cols) if np.isfinite(cost[i, j])}
        for a in order:  # follow chains from their heads; time increases along a chain
            if a in successor.values():
                continue
            b = a
            while b in successor:
                b = successor[b]
                merged[b] = a
    # renumber by first appearance (frame, row)
    new: dict[int, int] = {}
    out = []
    for row_ids in ids:
        row_ids = np.asarray(row_ids, np.int64)
        res = np.full(row_ids.shape, -1, np.int64)
        for row, tid in enumerate(row_ids):
            if tid >= 0:
                root = merged[int(tid)]
                res[row] = new.setdefault(root, len(new) + 1)
        out.append(res)
    return out


def track_offline(boxes_xyxy: list[np.ndarray], scores: list[np.ndarray], tracker,
                  backfill: bool = True, stitch_max_gap: int = 0, stitch_max_distance: float = 0.5,
                  stitch_max_scale: float = 1.5) -> list[np.ndarray]:
    """Track a whole sequence: ``tracker.update`` per frame, then back-fill and stitching.

    boxes_xyxy: per frame (D_f, 4) float pixels; scores: per frame (D_f,) float. tracker: a fresh
    ``PedestrianTracker`` (one per sequence). Returns per frame (D_f,) int64 ids aligned with the
    input rows, 1, 2, ... by first appearance; -1 = untracked.
    """
    online = [tracker.update(b, s) for b, s in zip(boxes_xyxy, scores)]
    ids = backfill_ids(tracker.tracklet_keys, online, tracker.confirmed_ids) if backfill else online
    return stitch_ids(ids, boxes_xyxy, stitch_max_gap, stitch_max_distance, stitch_max_scale)
