"""RayIoU / OccScore (tasks/metrics/rayiou.py) on toy scenes whose values are derived by hand from
the reference definition (SparseOcc ``loaders/ray_metrics.py`` + ``lib/dvr/dvr.cu`` +
``loaders/ego_pose_dataset.py``, MCG-NJU/SparseOcc; OpenOcc ``projects/mmdet3d_plugin/datasets/
ray_metrics.py`` + ``tools/ray_iou/ego_pose_extractor.py``, OpenDriveLab/OccNet branch
``challenge``). The rules used in the derivations below, as read there:

- R1 (dvr.cu, "test" phase): a ray walks voxel by voxel from its origin; the first voxel whose
  class is not free is the hit; the rendered depth is the ray parameter at which the ray *leaves*
  that voxel (``d[i]``), times the voxel size. A ray that meets no occupied voxel ends with the
  class of its last voxel (free).
- R2 (``main_rayiou``): rays whose ground-truth class is free are dropped (``valid_mask``).
- R3 (``calc_rayiou``): per class, gt_cnt = rays with GT class c, pred_cnt = rays with predicted
  class c, tp = both c and ``|depth_pred - depth_gt| < threshold`` (strict), thresholds 1, 2, 4 m;
  IoU = tp / (gt + pred - tp); free dropped (``[:-1]``); RayIoU = nanmean over all (threshold,
  class) entries, RayIoU@t = nanmean over classes.
- R4 (OpenOcc ``calc_metrics``): AVE_c = mean L2 flow error over class c's true-positive rays at
  2 m (flow classes only); mAVE = nanmean; OccScore = 0.9 RayIoU + 0.1 max(1 - mAVE, 0).
- R5 (``EgoPoseDataset``): origins = the LiDAR positions of every frame of the scene in the
  reference ego frame, kept when |x| < 39 and |y| < 39 on the +-40 m grid, then at most 8 at
  ``round(linspace(0, n - 1, 8))``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from tasks import conventions as C
from tasks.metrics.rayiou import (
    RayCounts,
    RayIoUSettings,
    cast_rays,
    frame_ray_counts,
    lidar_ray_directions,
    ray_counts,
    ray_origins,
)

# Toy scene A: 1 m voxels, grid (10, 7, 5) from (0, 0, 0); two origins at voxel centres; six
# axis-aligned rays from each (+x, -x, +y, -y, +z, -z), so every depth is exact in binary.
SHAPE = (10, 7, 5)
O1, O2 = (0.5, 3.5, 1.5), (2.5, 3.5, 2.5)
DIRS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)


def scene_a():
    F = C.FREE
    gt = np.full(SHAPE, F, np.uint8)
    gt[:, :, 0] = C.ROAD
    gt[8, :, :] = C.OTHER_STRUCTURE
    gt[5, 3, 1:3] = C.PEDESTRIAN
    gt[2, 5, 2] = C.POLE
    gt[0, 1, 1] = C.CAR
    pred = np.full(SHAPE, F, np.uint8)
    pred[:, :, 0] = C.ROAD
    pred[0, 3, 0] = C.TERRAIN
    pred[9, :, :] = C.OTHER_STRUCTURE
    pred[8, 3, 1] = C.PEDESTRIAN
    pred[6, 3, 2] = C.PEDESTRIAN
    pred[2, 5, 2] = C.POLE
    pred[0, 3, 4] = C.VEGETATION
    gt_flow = np.zeros(SHAPE + (2,))
    pred_flow = np.zeros(SHAPE + (2,))
    gt_flow[5, 3, 2] = (1.0, 0.0)
    pred_flow[6, 3, 2] = (0.7, 0.4)
    gt_flow[5, 3, 1] = (5.0, 5.0)  # O1 +x: a true positive at 4 m only: not in the AVE
    return pred, gt, pred_flow, gt_flow


# Per ray (origin-major, DIRS order), by R1: GT (class, depth) and predicted (class, depth).
# O1 = (0.5, 3.5, 1.5):
#   +x GT ped (5,3,1), leaves at x=6: 5.5     | pred ped (8,3,1), leaves x=9: 8.5 (error 3.0)
#   -x GT leaves the grid: free (dropped, R2) | pred free
#   +y GT free (dropped)                      | pred free
#   -y GT car (0,1,1), leaves at y=1: 2.5     | pred free (a miss)
#   +z GT free (dropped)                      | pred vegetation (0,3,4), 3.5: dropped (R2)
#   -z GT road (0,3,0), leaves at z=0: 1.5    | pred terrain (0,3,0): 1.5 (wrong class)
# O2 = (2.5, 3.5, 2.5):
#   +x GT ped (5,3,2), leaves at x=6: 3.5     | pred ped (6,3,2), leaves x=7: 4.5 (error 1.0)
#   -x GT free (dropped)                      | pred free
#   +y GT pole (2,5,2), leaves at y=6: 2.5    | pred pole, 2.5
#   -y GT free (dropped)                      | pred free
#   +z GT free (dropped)                      | pred free
#   -z GT road (2,3,0), leaves at z=0: 2.5    | pred road, 2.5
EXPECTED_GT = [(0, 5.5), (C.FREE, None), (C.FREE, None), (1, 2.5), (C.FREE, None), (4, 1.5)] + [
    (0, 3.5),
    (C.FREE, None),
    (3, 2.5),
    (C.FREE, None),
    (C.FREE, None),
    (4, 2.5),
]
EXPECTED_PRED = [(0, 8.5), (C.FREE, None), (C.FREE, None), (C.FREE, None), (8, 3.5), (5, 1.5)] + [
    (0, 4.5),
    (C.FREE, None),
    (3, 2.5),
    (C.FREE, None),
    (C.FREE, None),
    (4, 2.5),
]
# R3 over the 6 kept rays: GT ped 2, car 1, pole 1, road 2; predicted ped 2, terrain 1, pole 1,
# road 1 (the car ray predicts free). True positives: ped: errors 3.0 and 1.0 -> 0 @1 (1.0 is not
# < 1), 1 @2, 2 @4; pole 1 and road 1 at every threshold. IoU = tp / (gt + pred - tp):
#   ped 0/4, 1/3, 2/2; car 0/1 (x3); pole 1/1 (x3); road 1/2 (x3); terrain 0/1 (x3);
#   other-structure, truck, two-wheeler, vegetation: 0/0 -> NaN (vegetation's only hit is dropped).
# RayIoU@1 = (0 + 0 + 1 + .5 + 0) / 5 = 0.3; @2 = (1/3 + 1.5) / 5 = 11/30; @4 = 2.5 / 5 = 0.5;
# RayIoU = (1.5 + 11/6 + 2.5) / 15 = 7/18.
# R4: true positives at 2 m of flow classes: O2 +x only: ||(0.7, 0.4) - (1.0, 0.0)|| = 0.5 -> mAVE
# 0.5 (the 4 m-only O1 +x ray, error 7.07, stays out); OccScore = 0.9 * 7/18 + 0.1 * 0.5 = 0.4.
EXPECTED_IOU = {
    "1m": {"pedestrian": 0.0, "car": 0.0, "pole": 1.0, "road": 0.5, "terrain": 0.0},
    "2m": {"pedestrian": 1 / 3, "car": 0.0, "pole": 1.0, "road": 0.5, "terrain": 0.0},
    "4m": {"pedestrian": 1.0, "car": 0.0, "pole": 1.0, "road": 0.5, "terrain": 0.0},
}


def _check_hits(hits, expected):
    for k, (cls, depth) in enumerate(expected):
        assert hits.classes[k] == cls, f"ray {k}"
        if depth is None:
            assert hits.index[k] == -1 and math.isnan(hits.depth_m[k]), f"ray {k}"
        else:
            assert hits.depth_m[k] == depth, f"ray {k}: {hits.depth_m[k]} != {depth}"


def test_first_hits_and_exit_depths_of_toy_scene():
    pred, gt, _, _ = scene_a()
    origins = np.array([O1, O2])
    _check_hits(cast_rays(gt, origins, DIRS, (0, 0, 0), 1.0), EXPECTED_GT)
    _check_hits(cast_rays(pred, origins, DIRS, (0, 0, 0), 1.0), EXPECTED_PRED)
    # the same scene at 0.2 m voxels from another corner: every depth scales, nothing else
    h = cast_rays(gt, origins * 0.2 + (0.4, -4.8, -1.0), DIRS, (0.4, -4.8, -1.0), 0.2)
    np.testing.assert_array_equal(h.classes, [c for c, _ in EXPECTED_GT])
    np.testing.assert_allclose(
        h.depth_m, [np.nan if d is None else 0.2 * d for _, d in EXPECTED_GT], atol=1e-12
    )


def test_rayiou_and_occscore_of_toy_scene():
    pred, gt, pred_flow, gt_flow = scene_a()
    counts = frame_ray_counts(
        pred, gt, np.array([O1, O2]), (0, 0, 0), 1.0, pred_flow, gt_flow, directions=DIRS
    )
    s = counts.scores()
    assert s["rays"] == 6
    for t, row in EXPECTED_IOU.items():
        got = s["per_class_iou"][t]
        for name, v in row.items():
            assert got[name] == pytest.approx(v, abs=1e-12), (t, name)
        for name in ("other-structure", "truck", "two-wheeler", "vegetation"):
            assert math.isnan(got[name]), (t, name)
    assert s["ray_iou_1m"] == pytest.approx(0.3, abs=1e-12)
    assert s["ray_iou_2m"] == pytest.approx(11 / 30, abs=1e-12)
    assert s["ray_iou_4m"] == pytest.approx(0.5, abs=1e-12)
    assert s["ray_iou"] == pytest.approx(7 / 18, abs=1e-12)
    assert s["per_class_ave"]["pedestrian"] == pytest.approx(0.5, abs=1e-12)
    assert math.isnan(s["per_class_ave"]["car"])
    assert s["mave"] == pytest.approx(0.5, abs=1e-12)
    assert s["occ_score"] == pytest.approx(0.4, abs=1e-12)
    # counts add before dividing (two copies of the frame: same ratios, twice the rays)
    both = (counts + counts).scores()
    assert both["ray_iou"] == pytest.approx(7 / 18) and both["rays"] == 12
    # no flow: mAVE and OccScore undefined, RayIoU unchanged
    s0 = frame_ray_counts(pred, gt, np.array([O1, O2]), (0, 0, 0), 1.0, directions=DIRS).scores()
    assert s0["ray_iou"] == pytest.approx(7 / 18) and math.isnan(s0["occ_score"])
    # mAVE above 1 m/s: the velocity term is 0 (max(1 - mAVE, 0)), OccScore = 0.9 RayIoU
    gt_flow[5, 3, 2] = (3.0, 0.0)
    s3 = frame_ray_counts(
        pred, gt, np.array([O1, O2]), (0, 0, 0), 1.0, pred_flow, gt_flow, directions=DIRS
    ).scores()
    assert s3["mave"] > 1 and s3["occ_score"] == pytest.approx(0.9 * 7 / 18, abs=1e-12)


def test_perfect_prediction_and_empty_counts():
    _, gt, _, gt_flow = scene_a()
    s = frame_ray_counts(
        gt, gt, np.array([O1, O2]), (0, 0, 0), 1.0, gt_flow, gt_flow, directions=DIRS
    ).scores()
    assert s["ray_iou"] == 1.0 and s["mave"] == 0.0 and s["occ_score"] == pytest.approx(1.0)
    empty = RayCounts().scores()
    assert math.isnan(empty["ray_iou"]) and empty["rays"] == 0


def test_oblique_ray_depth_is_where_it_leaves_the_voxel():
    """Direction (2, -1, 0) / sqrt(5), position o + u (2, -1, 0) (distance u sqrt(5)), in scene A's
    GT at z = 3.5 (above the pedestrian, the pole and the ground). From (0.5, 3.5, 3.5): y = 0
    (out of the grid) at u = 3.5 comes before the wall x = 8 at u = 3.75: no hit. From
    (0.5, 6.5, 3.5): x = 8 at u = 3.75 (y = 2.75: voxel (8, 2, 3), the wall); it leaves that voxel
    through x = 9 at u = 4.25 (y = 2.25), before y = 2 (u = 4.5): depth 4.25 sqrt(5) (R1)."""
    _, gt, _, _ = scene_a()
    d = np.array([[2.0, -1.0, 0.0]])
    miss = cast_rays(gt, [(0.5, 3.5, 3.5)], d, (0, 0, 0), 1.0)
    assert miss.classes[0] == C.FREE and miss.index[0] == -1
    hit = cast_rays(gt, [(0.5, 6.5, 3.5)], d, (0, 0, 0), 1.0)
    assert hit.classes[0] == C.OTHER_STRUCTURE
    assert hit.index[0] == np.ravel_multi_index((8, 2, 3), SHAPE)
    assert hit.depth_m[0] == pytest.approx(4.25 * math.sqrt(5), abs=1e-12)


def test_origin_outside_the_grid_and_inside_an_occupied_voxel():
    """Our grid starts at x = 0.4 m: the frame's own LiDAR (x ~ 0) sits outside it. A ray from
    there enters the grid and hits as if cast inside; a ray pointing away never enters it (free).
    An origin inside an occupied voxel hits that voxel, at the distance where it leaves it."""
    g = np.full((4, 4, 4), C.FREE, np.uint8)
    g[2, 1, 1] = C.CAR
    h = cast_rays(g, [(-3.0, 1.5, 1.5)], [(1, 0, 0), (-1, 0, 0)], (0, 0, 0), 1.0)
    assert list(h.classes) == [C.CAR, C.FREE] and h.depth_m[0] == 6.0
    h = cast_rays(g, [(2.25, 1.5, 1.5)], [(1, 0, 0), (-1, 0, 0)], (0, 0, 0), 1.0)
    assert list(h.classes) == [C.CAR, C.CAR] and list(h.depth_m) == [0.75, 0.25]


def test_query_rays_are_the_reference_rings():
    d = lidar_ray_directions()
    assert d.shape == (39 * 360, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    pitch = np.arcsin(d[::360, 2])
    # ring k (1..10) meets the ground plane z = -h at k sensor heights: tan(-pitch) = 1 / k
    np.testing.assert_allclose(np.tan(-pitch[:10]), 1.0 / np.arange(1, 11), atol=1e-12)
    gaps = np.diff(pitch[9:])
    np.testing.assert_allclose(gaps, gaps[0], atol=1e-12)
    assert pitch[-2] < 0.21 <= pitch[-1]
    az = np.degrees(np.arctan2(d[:360, 1], d[:360, 0])) % 360
    np.testing.assert_allclose(az, np.arange(360), atol=1e-9)


def test_origins_follow_the_reference_rule():
    """R5 on the reference grid (+-40 m, margin 1 m): frames 10 m apart along x, reference frame 2:
    local x = -20, -10, 0, 10, 20, 30, 40, 50 -> the first six (40 is not < 39)."""
    ref_grid = ((-40.0, -40.0, -1.0), (40.0, 40.0, 5.4))
    T = np.eye(4)
    T[0, 3] = 20.0
    sensors = np.array([[10.0 * i, 0.0, 1.8] for i in range(8)])
    got = ray_origins(T, sensors, 2, *ref_grid)
    np.testing.assert_allclose(got[:, 0], [-20, -10, 0, 10, 20, 30])
    # twelve frames 1 m apart, all inside: thinned to round(linspace(0, 11, 8)) = 0 2 3 5 6 8 9 11
    sensors = np.array([[float(i), 0.0, 1.8] for i in range(12)])
    got = ray_origins(np.eye(4), sensors, 0, *ref_grid)
    np.testing.assert_allclose(got[:, 0], [0, 2, 3, 5, 6, 8, 9, 11])
    # our grid (x from 0.4 m): the frame's own sensor at x = 0.2 is kept, the one 0.5 m behind
    # is not; the rotation of the reference pose applies (yaw 90 deg: world +y is base +x)
    T = np.eye(4)
    T[:2, :2] = [[0, -1], [1, 0]]
    sensors = np.array([[0.0, -0.3, 0.8], [0.0, 0.2, 0.8], [0.0, 3.0, 0.8]])
    got = ray_origins(T, sensors, 1, (0.4, -4.8, -1.0), (10.0, 4.8, 3.8))
    np.testing.assert_allclose(got, [[0.2, 0.0, 0.8], [3.0, 0.0, 0.8]], atol=1e-12)
    with pytest.raises(ValueError, match="frame index 5"):
        ray_origins(T, sensors, 5, (0.4, -4.8, -1.0), (10.0, 4.8, 3.8))


def test_settings_are_checked():
    with pytest.raises(ValueError, match="flow_threshold_m"):
        RayIoUSettings(flow_threshold_m=3.0)
    pred, gt, _, _ = scene_a()
    a = cast_rays(gt, [O1], DIRS, (0, 0, 0), 1.0)
    b = cast_rays(gt, [O1, O2], DIRS, (0, 0, 0), 1.0)
    with pytest.raises(ValueError, match="rays differ"):
        ray_counts(a, b)
