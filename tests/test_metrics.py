"""Metric kernels on hand-made cases whose values are computed by hand in the comments."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tasks import conventions as C
from tasks.metrics._common import MetricInputError, PRCounts
from tasks.metrics.bev import (
    DIFF_CORRECT,
    DIFF_EXTRA,
    DIFF_FREE,
    DIFF_MISSED,
    DIFF_UNKNOWN,
    DIFF_WRONG_CLASS,
    bev_difference,
    bev_top_labels,
)
from tasks.metrics.detection import DetectionCounts, detection_counts
from tasks.metrics.occupancy import OccupancyMetric
from tasks.metrics.pedestrian import (
    box_voxel_masks,
    pedestrian_box_counts,
    pedestrian_lidar_counts,
    voxelize_points,
)
from tasks.metrics.static import static_counts
from tasks.metrics.tracking import HOTA_ALPHAS, tracking_scores
from tasks.metrics.velocity import velocity_errors, voxel_velocity_errors

P, ROAD, FREE = C.PEDESTRIAN, C.ROAD, C.FREE


def col(values) -> np.ndarray:
    """A (N, 1, 1) uint8 grid from a list of class ids."""
    return np.asarray(values, dtype=np.uint8).reshape(-1, 1, 1)


# ---- occupancy (Occ3D) -------------------------------------------------------------------------


def occupancy_scores(pred, gt, mask=None):
    """One frame's scores."""
    metric = OccupancyMetric()
    metric.update(pred, gt, mask)
    return metric.compute()


def test_occupancy_iou_by_hand():
    gt, pred = col([P, P, ROAD, FREE]), col([P, ROAD, ROAD, ROAD])
    s = occupancy_scores(pred, gt)
    # pedestrian: TP 1, union 2 + 1 - 1 = 2; road: TP 1, union 1 + 3 - 1 = 3
    assert s.per_class_iou[P] == pytest.approx(0.5)
    assert s.per_class_iou[ROAD] == pytest.approx(1 / 3)
    assert np.isnan(s.per_class_iou[C.CAR])  # in neither grid: NaN, left out of the mean
    assert s.miou == pytest.approx(5 / 12)
    assert s.geometric_iou == pytest.approx(3 / 4)  # 3 occupied in both, 1 free predicted occupied
    assert len(s.per_class_iou) == 9 and s.num_voxels == 4


def test_occupancy_mask_and_accumulation():
    gt, pred = col([P, P, ROAD, FREE]), col([P, ROAD, ROAD, ROAD])
    mask = col([1, 1, 1, 0])
    s = occupancy_scores(pred, gt, mask)
    assert s.per_class_iou[ROAD] == pytest.approx(0.5) and s.miou == pytest.approx(0.5)
    assert s.geometric_iou == pytest.approx(1.0)
    m = OccupancyMetric()
    m.update(pred, gt, mask)
    m.update(col([C.CAR, FREE, FREE, FREE]), col([FREE, FREE, FREE, FREE]))  # a false car
    t = m.compute()
    assert t.per_class_iou[C.CAR] == 0.0  # predicted only: 0, and counted in the mean
    assert t.miou == pytest.approx((0.5 + 0.5 + 0.0) / 3)
    assert t.geometric_iou == pytest.approx(3 / 4)
    assert t.confusion.sum() == 7


def test_occupancy_rejects_bad_input():
    with pytest.raises(MetricInputError, match="class id 12"):
        occupancy_scores(col([12]), col([0]))
    with pytest.raises(MetricInputError, match="shape"):
        occupancy_scores(col([0, 1]), col([0]))


# ---- static voxels vs labelled points -----------------------------------------------------------


def test_static_by_hand():
    labels = col([ROAD, C.VEGETATION, FREE])  # 1 m voxels from x = 0
    T, V = C.TERRAIN, C.VEGETATION
    pts = (
        [(0.5, 0.5, 0.5)] * 4
        + [(1.5, 0.5, 0.5)] * 3
        + [(2.5, 0.5, 0.5)] * 2
        + [(0.2, 0.2, 0.2), (9, 0, 0)]
    )
    cls = [ROAD, ROAD, ROAD, T] + [T, T, V] + [ROAD, ROAD] + [C.UNLABELED, ROAD]
    s = static_counts(labels, (0, 0, 0), 1.0, np.array(pts, np.float32), np.array(cls, np.uint8))
    d = s.as_dict(classes=[ROAD, V, T])
    assert d["per_class_iou"]["road"] == pytest.approx(
        3 / 6
    )  # TP 3, FN 2 (free voxel), FP 1 terrain
    assert d["per_class_iou"]["vegetation"] == pytest.approx(1 / 3)  # TP 1, FP 2 terrain
    assert d["per_class_iou"]["terrain"] == 0.0
    assert d["miou"] == pytest.approx(5 / 18)
    assert d["coverage"] == pytest.approx(7 / 9)
    assert d["point_accuracy"] == pytest.approx(4 / 7)
    assert d["voxel_accuracy"] == pytest.approx(
        1 / 2
    )  # voxel 0 majority road = road; voxel 1 terrain != veg
    assert d["num_points_ignored"] == 2 and d["num_points"] == 9
    both = (s + s).as_dict(classes=[ROAD, V, T])
    assert both["miou"] == pytest.approx(5 / 18) and both["num_voxels"] == 4


def test_static_rejects_free_gt_class():
    for bad in (C.UNCLASSIFIED, C.FREE):  # the truth has a semantic class or none
        with pytest.raises(MetricInputError, match=f"class id {bad}"):
            static_counts(col([0]), (0, 0, 0), 1.0, np.zeros((1, 3)), np.array([bad], np.uint8))


# ---- pedestrian voxels --------------------------------------------------------------------------


def box_case():
    pred = np.full((6, 6, 4), FREE, np.uint8)
    pred[1:3, 1:3, 1] = P  # 4 body voxels inside the box
    pred[1, 1, 0] = P  # in the bottom slab: left out of both sides
    pred[4, 4, 1] = P  # outside every box
    pred[1, 1, 2] = C.OTHER_STRUCTURE  # occupied box voxel not labelled pedestrian
    # box x, y in [1, 3], z in [0, 3]; voxel centres at k + 0.5; bottom 0.6 m -> layer z = 0
    return pred, dict(
        range_min=(0, 0, 0), voxel_size_m=1.0, centers=[(2, 2, 1.5)], sizes=[(2, 2, 3)], yaws=[0.0]
    )


def test_pedestrian_boxes_by_hand():
    pred, box = box_case()
    body, bottom = box_voxel_masks(
        pred.shape, box["range_min"], 1.0, box["centers"], box["sizes"], box["yaws"], 0.6
    )
    assert body.sum() == 8 and bottom.sum() == 4 and bottom[1:3, 1:3, 0].all()
    c = pedestrian_box_counts(pred, **box, bottom_exclude_m=0.6)
    assert (c.pred_matched, c.pred_total, c.ref_matched, c.ref_total) == (4, 5, 4, 5)
    assert (
        c.precision == pytest.approx(0.8)
        and c.recall == pytest.approx(0.8)
        and c.f1 == pytest.approx(0.8)
    )
    visible = np.ones(pred.shape, bool)
    visible[4, 4, 1] = False  # the stray pedestrian voxel is not camera-visible
    assert (
        pedestrian_box_counts(pred, **box, visible=visible, bottom_exclude_m=0.6).precision == 1.0
    )


def test_box_slab_top_on_voxel_centres_is_decided_by_geometry_not_rounding():
    # a box standing on the ground (z = 0, a voxel face of a 0.2 m grid from z = -1 m): the top
    # of its 0.1 m bottom slab lies exactly on the centres of the z = 0.1 m layer, and its side
    # faces on voxel centres too. Float32 ground truth and 6-decimal 3d_bbox JSON put the box a
    # few 1e-7 m either way; the voxels must not follow (the whole footprint layer did).
    kw = dict(shape=(10, 10, 15), range_min=(0.0, 0.0, -1.0), voxel_size_m=0.2, yaws=[0.0])
    ref = None
    for eps in (0.0, 1.5e-9, -3.7e-10, 4e-7, -4e-7):
        body, bottom = box_voxel_masks(
            centers=[(1.0, 1.0, 0.85 + eps)], sizes=[(0.6, 0.6, 1.7)], bottom_exclude_m=0.1, **kw
        )
        if ref is None:
            ref = (body, bottom)
            # the feet layer (z 0..0.2 m, centre on the slab top) is body; x, y 0.7..1.3 m: the
            # centres 0.7 and 1.3 on the faces are inside (4 x 4 footprint)
            assert body[:, :, 5].sum() == 16 and not bottom.any()
            assert body.sum() == 16 * 9  # centres z 0.1..1.7 m (1.7 m on the top face)
        np.testing.assert_array_equal(body, ref[0], err_msg=str(eps))
        np.testing.assert_array_equal(bottom, ref[1], err_msg=str(eps))


def test_rotated_box_voxels():
    kw = dict(
        shape=(7, 7, 1),
        range_min=(0, 0, 0),
        voxel_size_m=1.0,
        centers=[(3.5, 3.5, 0.5)],
        sizes=[(3.8, 0.8, 0.8)],
        bottom_exclude_m=0.0,
    )
    along_x, _ = box_voxel_masks(yaws=[0.0], **kw)
    along_y, _ = box_voxel_masks(yaws=[math.pi / 2], **kw)
    assert np.argwhere(along_x).tolist() == [[2, 3, 0], [3, 3, 0], [4, 3, 0]]
    assert np.argwhere(along_y).tolist() == [[3, 2, 0], [3, 3, 0], [3, 4, 0]]


def test_pedestrian_lidar_tolerance():
    pred = np.full((5, 5, 5), FREE, np.uint8)
    pred[2, 2, 3] = P  # one voxel from the GT voxel (2, 2, 2)
    pred[4, 4, 4] = P  # two voxels away from it
    gt = voxelize_points(
        np.array([[2.5, 2.5, 2.5], [0.1, 0.1, 0.1], [7.0, 0, 0]]), (0, 0, 0), 1.0, (5, 5, 5)
    )
    assert np.argwhere(gt).tolist() == [[0, 0, 0], [2, 2, 2]]
    c = pedestrian_lidar_counts(pred, gt)
    assert (c.pred_matched, c.pred_total, c.ref_matched, c.ref_total) == (1, 2, 1, 2)
    assert c.f1 == pytest.approx(0.5)
    assert pedestrian_lidar_counts(pred, gt, tolerance_voxels=0).pred_matched == 0
    region = np.ones(pred.shape, bool)
    region[4, 4, 4] = region[0, 0, 0] = False
    r = pedestrian_lidar_counts(pred, gt, region)
    assert (r.precision, r.recall) == (1.0, 1.0)


def test_pr_counts_micro_average():
    s = PRCounts(1, 2, 1, 2) + PRCounts(3, 4, 0, 2)
    assert s.precision == pytest.approx(4 / 6) and s.recall == pytest.approx(1 / 4)
    assert s.f1 == pytest.approx(2 * (4 / 6) * (1 / 4) / (4 / 6 + 1 / 4))
    assert math.isnan(PRCounts().precision)


# ---- detection robustness -----------------------------------------------------------------------


def test_detection_counts_two_boxes_and_threshold():
    gt = [[0, 0, 10, 10], [20, 0, 30, 10], [40, 0, 50, 10]]
    visible = [True, False, True]
    dets = [[1, 0, 11, 10], [20, 0, 25, 10], [100, 100, 110, 110]]  # IoU 0.818, 0.5, none
    assert detection_counts(gt, visible, dets) == DetectionCounts(T=2, M_vis=1, M_occ=0, W=1)
    dets[1] = [20, 0, 24, 10]  # IoU 0.4: the occluded person is missed
    assert detection_counts(gt, visible, dets) == DetectionCounts(T=1, M_vis=1, M_occ=1, W=2)
    assert detection_counts(np.zeros((0, 4)), [], np.zeros((0, 4))) == DetectionCounts()


def test_detection_rates_match_paper_table():
    crowded, night = DetectionCounts(480, 6, 6, 5), DetectionCounts(40, 12, 3, 1)
    assert [round(100 * v, 1) for v in (crowded.recall, crowded.precision, crowded.miss_vis)] == [
        98.8,
        99.0,
        1.2,
    ]
    assert [round(100 * v, 1) for v in (night.recall, night.precision, night.miss_vis)] == [
        76.9,
        97.6,
        23.1,
    ]


# ---- tracking -----------------------------------------------------------------------------------


def B(x):
    return [x, 0.0, x + 10.0, 10.0]


def test_mota_idf1_three_frames_by_hand():
    a, b, far = B(0), B(50), B(200)
    frames = [
        ([1, 2], [a, b], [11, 12], [a, b]),
        ([1, 2], [a, b], [11, 13], [a, far]),  # b missed, a false positive far away
        ([1, 2], [a, b], [11, 14], [a, b]),  # b matched again under a new id: one switch
    ]
    s = tracking_scores(frames)
    assert (s.num_objects, s.misses, s.false_positives, s.switches) == (6, 1, 1, 1)
    assert s.mota == pytest.approx(1 - 3 / 6)
    # identity: 1 <-> 11 (3 frames), 2 <-> 12 or 14 (1 frame): IDTP 4 of 6 GT and 6 predicted boxes
    assert (s.idtp, s.idfp, s.idfn) == (4, 2, 2)
    assert s.idf1 == pytest.approx(8 / 12)


def test_hota_id_switch_by_hand():
    # one person over 4 frames, perfect boxes, predicted id 7 then 8: DetA 1, A = 2 / (4 + 2 - 2) = 0.5
    frames = [([1], [B(0)], [7 if k < 2 else 8], [B(0)]) for k in range(4)]
    s = tracking_scores(frames)
    assert s.deta == pytest.approx(1.0) and s.assa == pytest.approx(0.5)
    assert s.hota == pytest.approx(math.sqrt(0.5))
    assert s.mota == pytest.approx(1 - 1 / 4)


def test_hota_partial_overlap_by_hand():
    # IoU of [0, 10] x [0, 10] and [0, 6.25] x [0, 10] = 0.625: detected for alpha <= 0.625
    # (12 of 19 thresholds) with perfect association (HOTA_alpha 1), else DetA 0 (HOTA_alpha 0)
    frames = [([1], [B(0)], [5], [[0.0, 0.0, 6.25, 10.0]]) for _ in range(3)]
    s = tracking_scores(frames)
    assert len(HOTA_ALPHAS) == 19
    assert s.hota == pytest.approx(12 / 19)
    assert (s + s).hota == pytest.approx(12 / 19)  # sequences combine by counts


def test_tracking_empty_frames_and_bad_ids():
    empty = np.zeros((0, 4))
    s = tracking_scores([([], empty, [], empty), ([1], [B(0)], [], empty)])
    assert s.num_objects == 1 and s.misses == 1 and s.hota == 0.0
    with pytest.raises(MetricInputError, match="frame 0: repeated GT ids"):
        tracking_scores([([1, 1], [B(0), B(20)], [], empty)])


# ---- velocity -----------------------------------------------------------------------------------


def test_ave_three_voxels():
    gt, pred = col([P, P, P]), col([P, P, FREE])
    v_gt = np.array([[1, 0], [0, 2], [3, 4]], float).reshape(3, 1, 1, 2)
    v_pred = np.array([[1, 0], [0, 1], [9, 9]], float).reshape(3, 1, 1, 2)
    e = velocity_errors(pred, v_pred, gt, v_gt)
    assert e.ave_o == pytest.approx(0.5)  # errors 0 and 1 on the two both-pedestrian voxels
    assert e.ave_t == pytest.approx(2.0)  # plus ||(3, 4)|| = 5 where the prediction missed: 6 / 3
    assert (e + e).ave_t == pytest.approx(2.0) and (e + e).n_t == 6
    o, t = voxel_velocity_errors(pred, v_pred, gt, v_gt, mask=col([0, 1, 1]))
    assert o.tolist() == [1.0] and t.tolist() == [1.0, 5.0]


# ---- BEV summaries ------------------------------------------------------------------------------


def test_bev_top_and_difference():
    g = np.full((2, 2, 3), FREE, np.uint8)
    g[0, 0, 0], g[0, 0, 2] = ROAD, P  # top is the pedestrian
    g[0, 1, 0] = ROAD
    g[1, 0, 1] = C.CAR
    mask = np.ones(g.shape, bool)
    mask[1, 1] = False  # column never seen
    top = bev_top_labels(g, mask)
    assert top.tolist() == [[P, ROAD], [C.CAR, C.UNLABELED]]
    pred = g.copy()
    pred[0, 1, 0] = FREE  # missed road
    pred[1, 0, 1] = C.TRUCK  # wrong class
    pred[1, 0, 2] = (
        C.TRUCK
    )  # and one extra voxel above it: 1 wrong, 1 extra -> wrong class (tie order)
    pred[1, 1, 0] = ROAD  # in an unseen column
    assert bev_difference(pred, g, mask).tolist() == [
        [DIFF_CORRECT, DIFF_MISSED],
        [DIFF_WRONG_CLASS, DIFF_UNKNOWN],
    ]
    pred[0, 0, 1] = C.CAR  # extra under the pedestrian
    pred[0, 0, 2] = FREE  # pedestrian missed: 1 missed, 1 extra -> missed
    assert bev_difference(pred, g, mask)[0, 0] == DIFF_MISSED
    extra = np.full((1, 1, 3), FREE, np.uint8)
    extra[0, 0, 1] = ROAD
    assert bev_difference(extra, np.full((1, 1, 3), FREE, np.uint8)).tolist() == [[DIFF_EXTRA]]
    empty = np.full((1, 1, 3), FREE, np.uint8)
    assert bev_difference(empty, empty).tolist() == [[DIFF_FREE]]


def test_person_point_counts_hand_made():
    from tasks.metrics.pedestrian import person_point_counts

    inst = np.array([0, 7, 7, 7, 7, 9, 9, 0])
    # person 7: 3 of its 4 points and one background point; person 9: both points; a false positive
    c = person_point_counts(
        inst, [np.array([1, 2, 3, 0]), np.array([5, 6]), np.array([7])], np.array([7, 9, -1])
    )
    assert (c.pred_matched, c.pred_total, c.ref_matched, c.ref_total) == (5, 7, 5, 6)
    assert c.precision == pytest.approx(5 / 7) and c.recall == pytest.approx(5 / 6)


def test_pck_and_mask_iou():
    from tasks.metrics.keypoints import mask_iou, pck_counts

    gt = np.zeros((1, 17, 3))
    gt[0, :, 2] = 2
    gt[0, 0, 2] = 1  # occluded: not counted
    pred = np.zeros((1, 17, 3))
    pred[0, 1:9, 0] = 9.9  # within 0.1 x 100 px
    pred[0, 9:, 0] = 10.1  # outside
    assert pck_counts(pred, gt, np.array([100.0])) == (8, 16)
    a = np.zeros((2, 4, 4), bool)
    b = np.zeros((2, 4, 4), bool)
    a[0, :2], b[0, 1:3] = True, True  # 4 shared of 12
    np.testing.assert_allclose(mask_iou(a, b), [4 / 12, 0.0])
