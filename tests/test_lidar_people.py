"""The LiDAR people detector on analytic scenes: the robust ground under multipath returns, the
person score against posts, poles and bushes (issue 39 item 2)."""

from __future__ import annotations

import numpy as np
import pytest

from tasks.perception.lidar_clusters import (
    LidarClusterParams,
    detect_pedestrians_lidar,
    ground_height,
    person_score,
    robust_ground_height,
)
from tests import lidar_shapes as S

GROUND_Z = -1.7
#: the old detector: the per-cell minimum as the ground, no score gate
OLD = LidarClusterParams(ground_percentile=0.0, ground_max_drop_m=1e6, min_score=0.0)


def _road(rng, n=20000):
    return S.ground(rng, n, (-2.0, 20.0), (-8.0, 8.0), GROUND_Z)


def test_person_over_multipath_returns_is_detected_at_its_height():
    rng = np.random.default_rng(3)
    person = S.person(rng, 8.4, 0.3, GROUND_Z, height_m=1.75, density=400.0)
    # 100 multipath returns 4 m below the road around the person (the KITTI sweep of issue 39)
    below = S.multipath(rng, 100, (6.5, 10.5), (-1.5, 2.0), GROUND_Z, depth_m=(3.9, 4.1))
    points = np.concatenate([_road(rng), person, below]).astype(np.float32)
    det = detect_pedestrians_lidar(points)
    assert len(det) == 1
    np.testing.assert_allclose(det.centers[0, :2], [8.4, 0.3], atol=0.15)
    assert abs(det.sizes[0, 2] - 1.75) < 0.08
    assert det.scores[0] > 0.8
    # the old per-cell minimum puts the ground 4 m down: the person is 5.75 m tall and dropped
    assert len(detect_pedestrians_lidar(points, OLD)) == 0


def test_robust_ground_ignores_multipath_and_follows_a_slope():
    rng = np.random.default_rng(4)
    xy = rng.uniform([-10, -10], [30, 10], (30000, 2))
    plane = GROUND_Z + 0.05 * xy[:, 0]  # a 5 % slope
    road = np.column_stack([xy, plane + rng.normal(0, 0.02, len(xy))])
    below = S.multipath(rng, 400, (-10, 30), (-10, 10), 0.0, depth_m=(1.0, 6.0))
    below[:, 2] += GROUND_Z + 0.05 * below[:, 0]
    points = np.concatenate([road, below])
    ground = robust_ground_height(points, 2.0, 0.1, 0.5)[: len(road)]
    err = ground - plane
    # the 3 x 3 neighbourhood's lowest cell lies up to 2 cells downhill: 0.2 m on a 5 % slope
    assert np.abs(err).max() < 0.3 and np.median(np.abs(err)) < 0.15
    old = ground_height(points, 2.0)[: len(road)] - plane
    assert np.median(old) < -1.0  # the minimum sinks to the multipath


def test_robust_ground_lets_an_object_cell_borrow_its_neighbours_ground():
    rng = np.random.default_rng(5)
    road = _road(rng, 8000)
    wall = np.column_stack(
        [rng.uniform(4.0, 6.0, 6000), rng.uniform(0.0, 2.0, 6000), rng.uniform(-1.5, 1.0, 6000)]
    )
    inside = (road[:, 0] >= 4) & (road[:, 0] < 6) & (road[:, 1] >= 0) & (road[:, 1] < 2)
    points = np.concatenate([road[~inside], wall])
    ground = robust_ground_height(points, 2.0, 0.1, 0.5)[-len(wall) :]
    np.testing.assert_allclose(ground, GROUND_Z, atol=0.1)


@pytest.mark.parametrize(
    "name,make",
    [
        ("3 m pole", lambda rng: S.column(rng, 5.0, -1.0, 0.08, GROUND_Z, 3.0)),
        ("0.2 m post, 1.8 m", lambda rng: S.column(rng, 5.0, -1.0, 0.1, GROUND_Z, 1.8)),
        ("wide bush", lambda rng: S.bush(rng, 5.0, -1.0, GROUND_Z, radius=0.55, height_m=1.2)),
        ("low bush", lambda rng: S.bush(rng, 5.0, -1.0, GROUND_Z, radius=0.5, height_m=1.05)),
    ],
)
def test_posts_poles_and_bushes_are_not_people(name, make):
    rng = np.random.default_rng(6)
    thing = make(rng)
    points = np.concatenate([_road(rng, 8000), thing]).astype(np.float32)
    assert len(detect_pedestrians_lidar(points)) == 0, name
    above = thing[thing[:, 2] > GROUND_Z + 0.2]
    score, _ = person_score(above, GROUND_Z)
    assert score < 0.3, (name, score)
    # the old gates alone took the ones that fit the height / footprint boxes
    if name != "3 m pole":
        assert len(detect_pedestrians_lidar(points, OLD)) == 1, name


def test_person_score_of_people_at_range_and_a_child():
    rng = np.random.default_rng(7)
    for x, height, density in [(5.0, 1.8, 400.0), (15.0, 1.7, 60.0), (6.0, 1.3, 300.0)]:
        person = S.person(rng, x, 1.0, GROUND_Z, height_m=height, density=density)
        score, parts = person_score(person[person[:, 2] > GROUND_Z + 0.2], GROUND_Z)
        assert score >= 0.5, (x, height, parts)


# --- removal from the static map needs a confirmed person (issue 39) ------------------------------

W, H = 640, 480
K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
# LiDAR x forward, y left, z up -> camera x right, y down, z forward, same origin
T_CAM_FROM_LIDAR = np.array([[0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0], [0, 0, 0, 1]], np.float64)


def test_only_confirmed_lidar_boxes_remove_static_returns():
    from tasks.occupancy.static_map import pedestrian_boxes_for_masking
    from tasks.perception.models.proposals import project_lidar_boxes

    # in view: a person and a post candidate; behind the camera: a person and a bush candidate
    centers = np.array([[6, 0.5, -0.8], [5, -1, -0.8], [-6, 0, -0.8], [-5, 2, -0.8]], np.float32)
    sizes = np.tile(np.array([[0.5, 0.4, 1.75]], np.float32), (4, 1))
    yaws = np.zeros(4, np.float32)
    scores = np.array([0.95, 0.2, 0.9, 0.25], np.float32)
    image_box, _ = project_lidar_boxes(centers[:1], sizes[:1], yaws[:1], T_CAM_FROM_LIDAR, K, W, H)
    kept = pedestrian_boxes_for_masking(
        image_box, centers, sizes, yaws, K, T_CAM_FROM_LIDAR, W, H, 0.3, scores, 0.5
    )
    # the image confirms the person in view; behind, only the person-like box counts
    np.testing.assert_allclose(kept[:, :3], centers[[0, 2]])
    everything = pedestrian_boxes_for_masking(
        image_box, centers, sizes, yaws, K, T_CAM_FROM_LIDAR, W, H, 0.3
    )
    np.testing.assert_allclose(everything[:, :3], centers[[0, 2, 3]])  # unscored: as before


# --- a person seen once gets a track (issue 38 item 4) --------------------------------------------


def _keypoints(conf: float) -> np.ndarray:
    kp = np.zeros((1, 17, 3), np.float32)
    kp[..., 2] = conf
    return kp


def _plain_view():
    """One detection: image score 0.9, 17 keypoints of confidence 0.9, LiDAR box 0 scoring 0.95."""
    return np.array([0.9]), _keypoints(0.9), np.array([0]), np.array([0.95])


@pytest.mark.parametrize("world_check", [True, False])
def test_one_frame_person_in_plain_view_gets_a_confirmed_track(world_check):
    from tasks.track.ocsort import PedestrianTracker
    from tasks.track.offline import Confirmation, WorldCheck, detection_evidence, track_offline

    boxes = [np.array([[100.0, 80.0, 160.0, 260.0]])]
    scores = [np.array([0.9])]
    positions = [np.array([[4.0, 1.0]])]
    check = WorldCheck(enabled=world_check)

    def run(evidence):
        return track_offline(
            boxes,
            scores,
            PedestrianTracker(),
            positions=positions,
            times_s=np.zeros(1),
            check=check,
            evidence=evidence,
        )[0]

    sure = detection_evidence(*_plain_view())
    assert sure.tolist() == [True]
    assert run([sure]).tolist() == [1]
    assert run(None).tolist() == [-1]  # OC-SORT's hit count alone: never a track
    # each source of evidence is needed: no LiDAR candidate, a post-like one, few keypoints, a
    # weak image box, or confirmation turned off
    for args in [
        (scores[0], _keypoints(0.9), np.array([-1]), np.zeros(0)),
        (scores[0], _keypoints(0.9), np.array([0]), np.array([0.2])),
        (scores[0], _keypoints(0.3), np.array([0]), np.array([0.95])),
        (np.array([0.4]), _keypoints(0.9), np.array([0]), np.array([0.95])),
    ]:
        weak = detection_evidence(*args)
        assert weak.tolist() == [False]
        assert run([weak]).tolist() == [-1]
    off = detection_evidence(*_plain_view(), Confirmation(enabled=False))
    assert off.tolist() == [False]


def test_person_points_keep_the_ground_out_over_multipath_returns():
    """The track stage's person points drop ground returns by the same robust ground: with the
    per-cell minimum, returns 4 m below the road left the road in the person's box."""
    from tasks.perception.person_points import (
        PersonPointParams,
        person_point_indices,
        project_points,
    )

    rng = np.random.default_rng(8)
    person = S.person(rng, 6.0, 0.3, GROUND_Z, density=900.0)
    road = S.ground(rng, 30000, (1.0, 12.0), (-4.0, 4.0), GROUND_Z, noise_m=0.01)
    # 100 returns 1.5-2.5 m below the road behind the person: most of them inside the image
    below = S.multipath(rng, 100, (7.0, 10.0), (-1.0, 2.0), GROUND_Z, depth_m=(1.5, 2.5))
    points = np.concatenate([person, road, below]).astype(np.float32)
    uv, _ = project_points(person, K, T_CAM_FROM_LIDAR, 0.1)
    box = np.array([[*uv.min(axis=0) - 4, *uv.max(axis=0) + 4]])
    truth = np.arange(len(person))

    def wrong(params):
        (found,) = person_point_indices(points, K, T_CAM_FROM_LIDAR, (W, H), box, params=params)
        assert np.isin(truth, found).mean() > 0.9
        return 1 - np.isin(found, truth).mean()

    assert wrong(PersonPointParams()) < 0.1  # the ground under the feet only
    old = PersonPointParams(ground_percentile=0.0, ground_max_drop_m=1e6)
    assert wrong(old) > 0.5  # the road in the box joined the person
