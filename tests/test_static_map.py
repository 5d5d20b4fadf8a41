"""Static semantic map: max voting, ground consistency, lifting semantics, pedestrian removal and
the ghost trail a walking person leaves when its points are not removed."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tasks.conventions import (
    CAR,
    CITYSCAPES_TO_CLASS,
    CITYSCAPES_TRAIN_IDS,
    FREE,
    OTHER_STRUCTURE,
    PEDESTRIAN,
    ROAD,
    TERRAIN,
    TWO_WHEELER,
    UNCLASSIFIED,
    UNLABELED,
    VEGETATION,
)
from tasks.occupancy.freespace import OccupancyMap
from tasks.occupancy.settings import FreeSpaceParams, MapParams
from tasks.occupancy.static_map import (
    NUM_OCCUPIED_CLASSES,
    StaticMapError,
    StaticSemanticMap,
    lift_image_semantics,
    pedestrian_boxes_for_masking,
    pedestrian_point_mask,
    project_points,
)

VS = 0.2
#: the map's settings (their defaults: voxels of VS) and its ground classes
MAP = MapParams(voxel_size_m=VS)
GROUND = (ROAD, TERRAIN)
#: lift_image_semantics with plain nearest-neighbour matching for out-of-view ground
PLAIN = dataclasses.replace(MAP, fallback_ground_lateral_scale=1.0)


def _at(keys, n):
    return np.repeat((np.asarray(keys, float) + 0.5) * VS, n, axis=0)


def _labels(result):
    return {tuple(int(v) for v in k): int(lab) for k, lab in zip(result.keys, result.labels)}


def test_max_voting_ties_and_pedestrian_votes():
    m = StaticSemanticMap(VS)
    m.add_sweep(_at([[1, 1, 1]], 3), np.full(3, OTHER_STRUCTURE, np.uint8))
    m.add_sweep(_at([[1, 1, 1]], 2), np.full(2, VEGETATION, np.uint8))
    m.add_sweep(_at([[2, 1, 1]], 2), np.array([VEGETATION, OTHER_STRUCTURE], np.uint8))  # tie
    m.add_sweep(_at([[3, 1, 1]], 4), np.array([PEDESTRIAN] * 3 + [VEGETATION], np.uint8))
    m.add_sweep(_at([[4, 1, 1]], 2), np.full(2, PEDESTRIAN, np.uint8))  # only pedestrian votes
    # no class at all: the returns still hold a surface (issue 38)
    m.add_sweep(_at([[5, 1, 1]], 2), np.full(2, UNLABELED, np.uint8))
    # keep-mask: these 5 votes for the road are dropped by the caller's pedestrian mask
    m.add_sweep(_at([[1, 1, 1]], 5), np.full(5, ROAD, np.uint8), keep=np.zeros(5, bool))
    res = m.finalize(MAP, ())
    assert _labels(res) == {
        (1, 1, 1): OTHER_STRUCTURE,
        (2, 1, 1): OTHER_STRUCTURE,
        (3, 1, 1): VEGETATION,
        (5, 1, 1): UNCLASSIFIED,
    }
    keys, counts = m.counts()
    assert counts.dtype == np.uint16 and counts.shape == (5, NUM_OCCUPIED_CLASSES)
    assert counts[[tuple(k) for k in keys].index((1, 1, 1))].tolist() == [
        0,
        0,
        3,
        0,
        0,
        0,
        0,
        0,
        3 - 1,
        0,
    ]


def test_ground_consistency_rejects_far_ground_votes():
    m = StaticSemanticMap(VS)
    ground = [[i, j, 0] for i in range(-10, 10) for j in range(-10, 10)]  # z centre 0.1
    m.add_sweep(_at(ground, 5), np.full(len(ground) * 5, ROAD, np.uint8))
    near = [[2, 2, 1]]  # centre 0.3: 0.2 m above ground -> kept
    far = [[3, 3, 2]]  # centre 0.5: 0.4 m above -> road votes rejected, the wall votes decide
    far_only = [[4, 4, 7]]  # centre 1.5: only road votes -> rejected, UNCLASSIFIED (a surface)
    below = [[5, 5, -2]]  # centre -0.3: 0.4 m below
    m.add_sweep(_at(near + far + far_only + below, 4), np.full(16, TERRAIN, np.uint8))
    m.add_sweep(_at(far, 1), np.full(1, OTHER_STRUCTURE, np.uint8))
    res = m.finalize(MAP, GROUND)  # tolerance 0.3 m, cells of 1 m
    lab = _labels(res)
    assert lab[(2, 2, 1)] == TERRAIN
    assert lab[(3, 3, 2)] == OTHER_STRUCTURE
    assert lab[(4, 4, 7)] == lab[(5, 5, -2)] == UNCLASSIFIED  # the returns are there, not ground
    assert res.ground_rejected == 12
    assert sum(v == ROAD for v in lab.values()) == len(ground)
    # without the check the far votes win
    lab_nocheck = _labels(m.finalize(MAP, ()))
    assert lab_nocheck[(3, 3, 2)] == TERRAIN and lab_nocheck[(4, 4, 7)] == TERRAIN


def test_merges_across_flushes_equal_one_merge():
    rng = np.random.default_rng(0)
    sweeps = [
        (rng.uniform(-2, 2, (500, 3)).astype(np.float32), rng.integers(0, 9, 500).astype(np.uint8))
        for _ in range(6)
    ]
    a, b = StaticSemanticMap(VS, flush_points=300), StaticSemanticMap(VS, flush_points=10**9)
    for p, lab in sweeps:
        a.add_sweep(p, lab)
        b.add_sweep(p, lab)
    (ka, ca), (kb, cb) = a.counts(), b.counts()
    np.testing.assert_array_equal(ka, kb)
    np.testing.assert_array_equal(ca, cb)
    assert ca.sum() == 3000


def test_crop_to_grid_and_sample_points():
    from tasks.occupancy.grid import GridSpec

    m = StaticSemanticMap(VS)
    m.add_sweep(
        _at([[0, 0, 0], [20, 0, 0], [-20, 0, 0], [0, 30, 0]], 1),
        np.array([ROAD, VEGETATION, TERRAIN, OTHER_STRUCTURE], np.uint8),
    )
    res = m.finalize(MAP, ())
    spec = GridSpec((0.0, -1.0, -1.0), (5.0, 1.0, 1.0), 0.1)
    T = np.eye(4)
    T[:3, :3] = [[-1.0, 0, 0], [0, -1.0, 0], [0, 0, 1]]  # facing -x: the voxel at x = -4 is inside
    T[:3, 3] = (0.05, 0.05, 0.0)
    assert _labels(res.crop_to_grid(spec, T)) == {(0, 0, 0): ROAD, (-20, 0, 0): TERRAIN}
    pts, lab = res.crop_to_grid(spec, T).sample_points(0.1)
    assert len(pts) == 2 * 8 and set(lab.tolist()) == {ROAD, TERRAIN}
    np.testing.assert_allclose(np.sort(np.unique(pts[:, 0])), [-3.95, -3.85, 0.05, 0.15], atol=1e-6)


def test_bad_votes_raise():
    m = StaticSemanticMap(VS)
    with pytest.raises(StaticMapError, match=f"class {FREE}"):
        m.add_sweep(np.zeros((1, 3)), np.array([FREE], np.uint8))
    with pytest.raises(StaticMapError, match="labels"):
        m.add_sweep(np.zeros((2, 3)), np.array([1], np.uint8))


R_CAM_FROM_LIDAR = np.array([[0, -1.0, 0], [0, 0, -1.0], [1.0, 0, 0]])  # lidar x forward = cam z


def _cam():
    T = np.eye(4)
    T[:3, :3] = R_CAM_FROM_LIDAR
    K = np.array([[20.0, 0, 19.5], [0, 20.0, 9.5], [0, 0, 1]])
    return K, T


def test_lift_image_semantics_and_fallback():
    K, T = _cam()
    img = np.full((20, 40), CITYSCAPES_TRAIN_IDS["road"], np.uint8)
    img[:, :20] = CITYSCAPES_TRAIN_IDS["building"]
    img[:2, :] = CITYSCAPES_TRAIN_IDS["sky"]
    pts = np.array([[5, 1, 0], [5, -1, 0], [5, 0, 2.25], [-5, 1.2, 0], [5, 40, 0]], float)
    # u = 19.5 - 20 y / x, v = 9.5 - 20 z / x
    lab = lift_image_semantics(pts, img, K, T, CITYSCAPES_TO_CLASS, PLAIN)
    assert lab.tolist() == [OTHER_STRUCTURE, ROAD, UNLABELED, OTHER_STRUCTURE, OTHER_STRUCTURE]
    lab = lift_image_semantics(
        pts,
        img,
        K,
        T,
        CITYSCAPES_TO_CLASS,
        dataclasses.replace(MAP, outside_image_fallback="unknown"),
    )
    assert lab.tolist() == [OTHER_STRUCTURE, ROAD, UNLABELED, UNLABELED, UNLABELED]


def test_nearest_fallback_keeps_ground_and_objects_apart():
    """Out of view, ground points take the nearest in-view ground label and raised points the
    nearest in-view raised label, even where the nearest point overall is of the other level."""
    K, T = _cam()
    ground = np.stack(
        np.meshgrid(
            np.arange(-4.0, 10.0, 0.25), np.arange(-2.0, 3.01, 0.25), [-0.9], indexing="ij"
        ),
        -1,
    ).reshape(-1, 3)
    car = np.stack(
        np.meshgrid(np.arange(-4.0, 6.0, 0.2), [-2.3], [-0.5, -0.3], indexing="ij"), -1
    ).reshape(-1, 3)  # a car side 0.4-0.6 m above the ground, mostly beside the robot
    pts = np.concatenate([ground, car])
    pix, valid = project_points(pts, K, T, 40, 20)
    img = np.full(
        (20, 40), CITYSCAPES_TRAIN_IDS["road"], np.uint8
    )  # the view: road and the car's front
    is_car = np.arange(len(pts)) >= len(ground)
    img[pix[valid & is_car, 1], pix[valid & is_car, 0]] = CITYSCAPES_TRAIN_IDS["car"]
    out = ~valid
    assert out[is_car].sum() > 20 and valid[is_car].sum() > 5 and out[~is_car].sum() > 100
    lab = lift_image_semantics(pts, img, K, T, CITYSCAPES_TO_CLASS, PLAIN)
    assert np.all(lab[valid & is_car] == CAR)
    assert np.all(lab[out & is_car] == CAR)
    assert np.all(lab[out & ~is_car] == ROAD)
    # one level for all (the plain nearest neighbour) labels much of the car's side road
    plain = lift_image_semantics(
        pts, img, K, T, CITYSCAPES_TO_CLASS, dataclasses.replace(PLAIN, ground_max_deviation_m=1e3)
    )
    assert np.mean(plain[out & is_car] == ROAD) > 0.3


def test_lateral_scale_carries_ground_strips_along_the_path():
    """A lawn strip (|y| >= 2 m) beside a road, seen by the camera only ahead: with the lateral
    axis stretched, the out-of-view strip beside the robot is labelled terrain, not road."""
    K, T = _cam()
    ground = np.stack(
        np.meshgrid(
            np.arange(-4.0, 10.0, 0.25), np.arange(-3.0, 3.01, 0.25), [-0.9], indexing="ij"
        ),
        -1,
    ).reshape(-1, 3)
    lawn = np.abs(ground[:, 1]) >= 2.0
    pix, valid = project_points(ground, K, T, 40, 20)
    img = np.full((20, 40), CITYSCAPES_TRAIN_IDS["road"], np.uint8)
    img[pix[valid & lawn, 1], pix[valid & lawn, 0]] = CITYSCAPES_TRAIN_IDS["terrain"]
    out = ~valid
    assert (valid & lawn).sum() > 10 and (out & lawn).sum() > 50
    truth = np.where(lawn, TERRAIN, ROAD)
    plain = lift_image_semantics(ground, img, K, T, CITYSCAPES_TO_CLASS, PLAIN)
    along = lift_image_semantics(ground, img, K, T, CITYSCAPES_TO_CLASS, MAP)  # lateral scale 4
    assert np.mean(plain[out & lawn] == TERRAIN) < 0.6
    assert np.mean(along[out & lawn] == TERRAIN) > 0.9
    assert np.mean(along[out] == truth[out]) > np.mean(plain[out] == truth[out])


def test_pedestrian_point_mask_instances_and_rotated_boxes():
    K, T = _cam()
    inst = np.zeros((20, 40), np.int32)
    inst[:, 25:30] = 3
    pts = np.array([[5, -1.5, 0], [5, 1, 0], [0.55, 0, 0], [0.0, 0.45, 0], [0.5, 0.5, 0]], float)
    mask = pedestrian_point_mask(pts, K=K, T_cam_from_lidar=T, instance_image=inst)
    assert mask.tolist() == [True, False, False, False, False]
    box = np.array([[0, 0, 0, 1.0, 0.2, 2.0, 0.0]])
    mask = pedestrian_point_mask(pts, boxes_lidar=box, box_margin_m=0.1)
    assert mask.tolist() == [False, False, True, False, False]
    box[0, 6] = np.pi / 2  # now 1 m along y
    mask = pedestrian_point_mask(pts, boxes_lidar=box, box_margin_m=0.0)
    assert mask.tolist() == [False, False, False, True, False]


def test_one_projection_serves_every_per_sweep_kernel():
    """The map stage projects a sweep once: labels and the pedestrian mask from that projection
    equal those computed from K and T; a projection made for another image size is refused."""
    K, T = _cam()
    rng = np.random.default_rng(1)
    pts = rng.uniform([-8, -6, -1], [12, 6, 2], (400, 3))
    img = rng.integers(0, 19, (20, 40)).astype(np.uint8)
    inst = np.zeros((20, 40), np.int32)
    inst[5:15, 10:20] = 1
    proj = project_points(pts, K, T, 40, 20)
    assert 50 < proj[1].sum() < 350
    np.testing.assert_array_equal(
        lift_image_semantics(pts, img, K, T, CITYSCAPES_TO_CLASS, PLAIN, projection=proj),
        lift_image_semantics(pts, img, K, T, CITYSCAPES_TO_CLASS, PLAIN),
    )
    np.testing.assert_array_equal(
        pedestrian_point_mask(pts, instance_image=inst, projection=proj),
        pedestrian_point_mask(pts, K=K, T_cam_from_lidar=T, instance_image=inst),
    )
    wide = project_points(pts, K * [[2], [2], [1]], T, 80, 40)
    with pytest.raises(StaticMapError, match="80 x 40|40 x 20"):
        lift_image_semantics(pts, img, K, T, CITYSCAPES_TO_CLASS, PLAIN, projection=wide)
    with pytest.raises(StaticMapError, match="shapes"):
        pedestrian_point_mask(pts[:10], instance_image=inst, projection=proj)


def test_project_points_pixel_centres_and_depth():
    K, T = _cam()
    # u = 19.5 - 20 y / x, v = 9.5 - 20 z / x; pixel c spans [c - 0.5, c + 0.5)
    pts = np.array(
        [
            [10, 0.0, 0],
            [10, 0.026, 0],
            [10, 9.76, 0],
            [10, 10.26, 0],
            [0.05, 0, 0],
            [-5, 0, 0],
            [10, 0, -0.26],
        ]
    )
    pix, valid = project_points(pts, K, T, 40, 20)
    assert valid.tolist() == [True, True, True, False, False, False, True]
    assert pix.tolist() == [[20, 10], [19, 10], [0, 10], [0, 0], [0, 0], [0, 0], [20, 10]]
    assert project_points(pts[:1], K, T, 40, 20, min_depth_m=20.0)[1].tolist() == [False]


def test_pedestrian_boxes_for_masking_image_confirms_in_view():
    """In view a LiDAR box counts only when an image detection overlaps its projection; out of
    view every LiDAR box counts."""
    K, T = _cam()
    centers = np.array([[5.0, 0.0, 0.0], [5.0, -1.5, 0.0], [-5.0, 0.0, 0.0]], np.float32)
    sizes = np.tile(np.array([[0.5, 0.5, 1.7]], np.float32), (3, 1))
    yaws = np.zeros(3, np.float32)
    # the projected corners of box 0: u in [18.45, 20.55], v in [5.9, 13.1]
    det = np.array([[18.4, 5.9, 20.6, 13.1]], np.float32)
    out = pedestrian_boxes_for_masking(det, centers, sizes, yaws, K, T, 40, 20, 0.5)
    assert out.shape == (2, 7)
    np.testing.assert_array_equal(out[:, :3], centers[[0, 2]])
    none = pedestrian_boxes_for_masking(np.zeros((0, 4)), centers, sizes, yaws, K, T, 40, 20, 0.5)
    np.testing.assert_array_equal(none[:, :3], centers[[2]])
    assert pedestrian_boxes_for_masking(
        det, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), K, T, 40, 20, 0.5
    ).shape == (0, 7)


def test_ghost_trail_removed_by_pedestrian_boxes():
    """A person walks across the robot's view; with its points removed (3D boxes) the static map
    and the occupancy map hold nothing along its path; without removal a trail appears."""
    from tasks.occupancy.synthetic import box_mesh, os1_directions, raycast

    scene = [box_mesh((0, 0, -0.1), (30, 30, 0.2)), box_mesh((8.1, 0, 1.5), (0.2, 12, 3.0))]
    dirs = os1_directions(48, 360)
    origin = np.array([0.0, 0.0, 1.0])

    def run(remove: bool):
        smap, omap = StaticSemanticMap(VS), OccupancyMap(FreeSpaceParams(voxel_size_m=VS))
        for y in np.linspace(-3, 3, 13):
            person = (4.0, y, 0.85, 0.5, 0.5, 1.7, 0.3)
            pts, _ = raycast(scene + [box_mesh(person[:3], person[3:6], person[6])], origin, dirs)
            # image semantics missing (person outside the camera): the nearest static class
            lab = np.where(pts[:, 2] < 0.05, ROAD, OTHER_STRUCTURE).astype(np.uint8)
            keep = (
                ~pedestrian_point_mask(pts, boxes_lidar=np.array([person]), box_margin_m=0.1)
                if remove
                else np.ones(len(pts), bool)
            )
            smap.add_sweep(pts, lab, keep)
            omap.insert_scan(pts[keep], origin, max_range_m=20.0, discretize=False)
        res = smap.finalize(MAP, GROUND)
        c = res.centers()
        corridor = (np.abs(c[:, 0] - 4.0) < 0.6) & (np.abs(c[:, 1]) < 3.5) & (c[:, 2] > 0.25)
        xs, ys, zs = np.meshgrid(
            np.arange(3.5, 4.5, VS),
            np.arange(-3.4, 3.4, VS),
            np.arange(0.3, 1.7, VS),
            indexing="ij",
        )
        occ = omap.query(np.stack([xs, ys, zs], -1).reshape(-1, 3) + VS / 2)
        return int(corridor.sum()), int((occ == 1).sum()), int((occ == 0).sum())

    static_trail, occupied, free = run(remove=True)
    assert static_trail == 0 and occupied == 0 and free > 100
    static_trail, occupied, _ = run(remove=False)
    assert static_trail > 50 and occupied > 10


def test_merge_static_maps_primary_wins_and_fallback_fills():
    from tasks.occupancy.static_map import StaticMap, merge_static_maps

    counts = np.zeros((1, NUM_OCCUPIED_CLASSES), np.uint16)
    cam = StaticMap(0.2, np.array([[0, 0, 0]]), np.array([2], np.uint8), counts, 1)
    fallback = StaticMap(
        0.2,
        np.array([[0, 0, 0], [5, 0, 0]]),
        np.array([8, 4], np.uint8),
        np.zeros((2, NUM_OCCUPIED_CLASSES), np.uint16),
        2,
    )
    merged = merge_static_maps(cam, fallback)
    assert merged.keys.tolist() == [[0, 0, 0], [5, 0, 0]]
    assert merged.labels.tolist() == [2, 4]  # the camera's label stays; the fallback fills the rest
    assert merged.ground_rejected == 3


def test_lookup_labels_resamples_an_offset_grid_without_holes():
    """Regression: pushing map voxel centres into a grid offset by half a voxel left striped holes
    (two centres in one cell, none in the next). Pulling by the cell centres fills every cell."""
    from tasks.occupancy.static_map import StaticMap, lookup_labels

    keys = np.array([[i, 0, -1] for i in range(10)])  # a 2 m strip of road, 0.2 m voxels
    road = StaticMap(
        0.2, keys, np.full(10, 4, np.uint8), np.zeros((10, NUM_OCCUPIED_CLASSES), np.uint16), 0
    )
    centres = np.stack(
        [0.2 + 0.2 * np.arange(9), np.full(9, 0.1), np.full(9, -0.1)], 1
    )  # offset 0.1
    assert lookup_labels(road, centres).tolist() == [4] * 9
    assert lookup_labels(road, np.array([[5.0, 0.1, -0.1]])).tolist() == [255]


def _block(x0, x1, y0, y1, z0, z1):
    return [[x, y, z] for x in range(x0, x1) for y in range(y0, y1) for z in range(z0, z1)]


def test_small_fragments_are_per_class_and_26_connected():
    from tasks.occupancy.static_map import small_fragments

    wall = _block(0, 4, 0, 1, 0, 5)  # 20 voxels
    stray = [[10, 10, 6], [10, 10, 7]]  # a 2-voxel column alone
    touching = [[4, 1, 5], [5, 1, 5]]  # 2 voxels of another class touching the wall's corner
    diagonal = [[20, 0, 0], [21, 1, 1], [22, 2, 2], [23, 3, 3], [24, 4, 4]]  # corners only
    keys = np.array(wall + stray + touching + diagonal, np.int64)
    labels = np.array(
        [OTHER_STRUCTURE] * 20 + [TWO_WHEELER] * 2 + [VEGETATION] * 2 + [CAR] * 5, np.uint8
    )
    small = small_fragments(keys, labels, 5)
    assert not small[:20].any()  # the wall
    assert small[20:24].all()  # the column, and the fragment that only touches another class
    assert not small[24:].any()  # 5 voxels joined by corners are one fragment of 5
    assert not small_fragments(keys, labels, 1).any()  # 1: off


def test_the_final_map_drops_fragments_smaller_than_any_object():
    """Issue 30, crowded night: the returns of a passer-by that no detector removed, labelled
    two-wheeler by the image, stayed in the map as a 2-voxel column with 8 votes; single noisy
    other-structure labels in vegetation made 1-vote voxels. Both are fragments no static object
    is as small as, and go; the wall and the bush stay."""
    from tasks.occupancy.mapping import final_maps

    params = dataclasses.replace(MAP, surface_noise_m=0.0)  # every voxel with votes is a surface
    m = StaticSemanticMap(VS, moments=True)
    origin = np.zeros(3)
    parts = [
        (_block(10, 14, 5, 6, 0, 5), OTHER_STRUCTURE, 8),  # a wall
        (_block(10, 13, -8, -5, 0, 3), VEGETATION, 8),  # a bush
        ([[12, -5, 3]], OTHER_STRUCTURE, 1),  # a stray label on the bush
        ([[20, 0, 6], [20, 0, 7]], TWO_WHEELER, 8),  # a missed passer-by's torso
    ]
    for keys, cls, n in parts:
        m.add_sweep(_at(keys, n), np.full(len(keys) * n, cls, np.uint8), origin_world=origin)
    empty = StaticSemanticMap(VS, moments=True)
    sides = [(*s.packed_counts(), s.packed_moments()) for s in (m, empty)]
    final, _ = final_maps(sides, params, GROUND)
    got = _labels(final)
    assert sorted(set(got.values())) == [OTHER_STRUCTURE, VEGETATION]
    assert len(got) == 20 + 27
    assert (12, -5, 3) not in got and (20, 0, 6) not in got
    kept, _ = final_maps(sides, dataclasses.replace(params, min_fragment_voxels=1), GROUND)
    assert _labels(kept)[(20, 0, 6)] == TWO_WHEELER and len(kept.keys) == 20 + 27 + 3
