"""OC-SORT pedestrian tracking over 2D boxes, one tracker instance per sequence.

Wraps ``trackers.OCSORTTracker`` (roboflow ``trackers``, Apache-2.0, a clean-room OC-SORT: Kalman
state [u, v, s, r, du, dv, ds], observation-centric momentum, recovery and re-update). The wrapper
adds what the pipeline needs: ids aligned with the *input* detections (so keypoints and masks stay
attached), ids numbered 1, 2, ... per instance in the order they are first confirmed, and plain
numpy in / out.

The library keeps its id counter on the tracker instance (``_next_track_id``), not on the class,
so two ``PedestrianTracker`` instances never share ids; we still re-number to start at 1.

As in the OC-SORT reference, during the first ``min_hits`` frames of a sequence every matched
detection gets an id at once (so people present from the first frame are not delayed); later
tracks need ``min_hits`` consecutive hits before they get an id.

After a miss, OC-SORT's hit streak restarts, and the reference hides a re-found track for
``min_hits - 1`` frames although it already has an id. With ``keep_confirmed_ids`` (default) the
wrapper reports the id of an already confirmed track as soon as it is matched again (found as the
tracklet whose last observation is exactly the input box), so a one-frame miss does not cost the
later stages three frames of that person; ``keep_confirmed_ids=False`` gives the reference output.

For offline use (whole logs, tasks/track/offline.py) the wrapper also records, per frame and input
row, the key of the library tracklet that the row updated or started (``tracklet_keys``; keys
0, 1, ... in order of creation, -1 for a row below ``det_thresh``), and which keys got an id
(``confirmed_ids``): enough to give a confirmed track its tentative first frames back.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tasks.bounds import AtLeastOne, Probability


@dataclass(frozen=True)
class TrackerParams:
    """OC-SORT's settings (Cao et al.; defaults are OC-SORT's), frames at the tracker's rate.

    det_thresh: detections scoring below it never start or update a track (id -1).
    max_age: frames a lost track survives without a detection. min_hits: consecutive hits before a
    track gets an id. iou_threshold: minimum IoU to associate. delta_t: frames back used for the
    motion direction. inertia: weight of the direction-consistency term in the association cost.
    keep_confirmed_ids: report a confirmed track's id again on its first re-match after a miss
    (False = reference OC-SORT output).
    """

    det_thresh: Probability = 0.6
    max_age: AtLeastOne = 30
    min_hits: AtLeastOne = 3
    iou_threshold: Probability = 0.3
    delta_t: AtLeastOne = 3
    inertia: Probability = 0.2
    keep_confirmed_ids: bool = True


class PedestrianTracker:
    """OC-SORT over one sequence's 2D pedestrian boxes; call ``update`` once per frame, in order
    (settings: :class:`TrackerParams`)."""

    def __init__(self, params: TrackerParams = TrackerParams()) -> None:
        det_thresh, max_age, min_hits = params.det_thresh, params.max_age, params.min_hits
        iou_threshold, delta_t, inertia = params.iou_threshold, params.delta_t, params.inertia
        keep_confirmed_ids = params.keep_confirmed_ids
        if max_age < 0 or min_hits < 1 or delta_t < 1:
            raise ValueError(
                f"PedestrianTracker: need max_age >= 0, min_hits >= 1, delta_t >= 1; got "
                f"max_age={max_age}, min_hits={min_hits}, delta_t={delta_t}"
            )
        from trackers import OCSORTTracker  # here: the settings above import without the library

        # frame_rate == 30 makes the library's lost-track buffer exactly ``max_age`` frames.
        self._tracker = OCSORTTracker(
            lost_track_buffer=int(max_age),
            frame_rate=30.0,
            minimum_consecutive_frames=int(min_hits),
            minimum_iou_threshold=float(iou_threshold),
            direction_consistency_weight=float(inertia),
            high_conf_det_threshold=float(det_thresh),
            delta_t=int(delta_t),
        )
        self._keep_confirmed_ids = bool(keep_confirmed_ids)
        self._our_id: dict[int, int] = {}
        # id(tracklet) -> (tracklet, key) for the library's live tracklets; holding the object keeps
        # its id() from being reused by a new tracklet while the entry exists
        self._live: dict[int, tuple[object, int]] = {}
        self._next_key = 0
        self._key_ids: dict[int, int] = {}
        self.tracklet_keys: list[np.ndarray] = []
        self.frame_count = 0

    @property
    def confirmed_ids(self) -> dict[int, int]:
        """Tracklet key -> the id it was reported under (keys that reached ``min_hits``)."""
        return dict(self._key_ids)

    def update(self, boxes_xyxy: np.ndarray, scores: np.ndarray) -> np.ndarray:
        """Advance one frame.

        boxes_xyxy: (D, 4) float pixels (u_min, v_min, u_max, v_max); scores: (D,) float in [0, 1].
        Returns track_ids (D,) int64 aligned with the input rows; -1 = no confirmed track.
        """
        boxes = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
        conf = np.asarray(scores, dtype=np.float64).reshape(-1)
        if conf.shape[0] != boxes.shape[0]:
            raise ValueError(
                f"PedestrianTracker.update (frame {self.frame_count}): {boxes.shape[0]} boxes but "
                f"{conf.shape[0]} scores"
            )
        if not (np.isfinite(boxes).all() and np.isfinite(conf).all()):
            raise ValueError(f"PedestrianTracker.update (frame {self.frame_count}): NaN/inf input")
        import supervision as sv

        count = boxes.shape[0]
        detections = sv.Detections(
            xyxy=boxes,
            confidence=conf,
            class_id=np.zeros(count, dtype=int),
            data={"row": np.arange(count)},
        )
        result = self._tracker.update(detections)
        track_ids = np.full(count, -1, dtype=np.int64)
        if len(result) > 0:
            rows = np.asarray(result.data["row"], dtype=np.int64)
            library_ids = np.asarray(result.tracker_id, dtype=np.int64).copy()
            if self._keep_confirmed_ids and (library_ids < 0).any():
                library_ids = self._recover_confirmed(boxes, rows, library_ids)
            for row, library_id in zip(rows, library_ids):
                if library_id < 0:
                    continue
                if library_id not in self._our_id:
                    self._our_id[int(library_id)] = len(self._our_id) + 1
                track_ids[row] = self._our_id[int(library_id)]
        self.tracklet_keys.append(self._record_keys(boxes))
        self.frame_count += 1
        return track_ids

    def _record_keys(self, boxes: np.ndarray) -> np.ndarray:
        """(D,) int64 key of the tracklet each input row updated or started this frame, -1 if none.

        A row's tracklet is the live one updated this frame whose last observation is exactly the
        row's box (the library stores the box it was given); identical boxes go in row order."""
        live: dict[int, tuple[object, int]] = {}
        by_box: dict[tuple[float, ...], list[int]] = {}
        for tracklet in self._tracker.tracks:
            entry = self._live.get(id(tracklet))
            if entry is not None and entry[0] is tracklet:
                key = entry[1]
            else:
                key, self._next_key = self._next_key, self._next_key + 1
            live[id(tracklet)] = (tracklet, key)
            if (
                tracklet.tracker_id >= 0
                and key not in self._key_ids
                and tracklet.tracker_id in self._our_id
            ):
                self._key_ids[key] = self._our_id[int(tracklet.tracker_id)]
            if tracklet.time_since_update == 0:
                obs = tuple(np.asarray(tracklet.last_observation, np.float64).tolist())
                by_box.setdefault(obs, []).append(key)
        self._live = live
        keys = np.full(boxes.shape[0], -1, np.int64)
        for row in range(boxes.shape[0]):
            found = by_box.get(tuple(boxes[row].tolist()))
            if found:
                keys[row] = found.pop(0)
        return keys

    def _recover_confirmed(
        self, boxes: np.ndarray, rows: np.ndarray, library_ids: np.ndarray
    ) -> np.ndarray:
        """Library ids for rows matched this frame to a track that already has an id."""
        by_box: dict[tuple[float, ...], list[int]] = {}
        for tracklet in self._tracker.tracks:
            if tracklet.time_since_update == 0 and tracklet.tracker_id >= 0:
                key = tuple(np.asarray(tracklet.last_observation, np.float64).tolist())
                by_box.setdefault(key, []).append(int(tracklet.tracker_id))
        for k in np.flatnonzero(library_ids < 0):
            candidates = by_box.get(tuple(boxes[rows[k]].tolist()), [])
            if len(candidates) == 1:
                library_ids[k] = candidates[0]
        return library_ids
