"""Where wrong voxels lie (tasks/metrics/confusion.py): analytic grids with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from tasks import conventions as C
from tasks.metrics._common import MetricInputError
from tasks.metrics.confusion import LOCATIONS, ErrorLocations, class_counts, error_locations
from tasks.metrics.occupancy import OccupancyMetric

SHAPE = (20, 20, 10)
SENSOR = np.array([0.5, 10.0, 5.0])  # voxel units: at the -x end, mid y, mid z


def _box(lo, hi, cls=C.CAR, grid=None):
    g = np.full(SHAPE, C.FREE, np.uint8) if grid is None else grid.copy()
    g[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]] = cls
    return g


def _loc(result: ErrorLocations, kind: int, cls: int) -> dict:
    return dict(zip(LOCATIONS, result.counts[kind, cls].tolist()))


def test_a_surface_one_voxel_toward_the_sensor_is_adjacent_sensor_side():
    gt = _box((10, 8, 3), (12, 12, 6))
    pred = _box((9, 8, 3), (11, 12, 6))  # the box moved one voxel toward the sensor (-x)
    loc = error_locations(pred, gt, None, SENSOR)
    false, missed = _loc(loc, 0, C.CAR), _loc(loc, 1, C.CAR)
    assert false == {
        "adjacent_sensor_side": 12,
        "adjacent_far_side": 0,
        "along_ray": 0,
        "elsewhere": 0,
    }
    # the missed voxels lie behind the labelled ones: adjacent, not on the sensor side
    assert missed == {
        "adjacent_sensor_side": 0,
        "adjacent_far_side": 12,
        "along_ray": 0,
        "elsewhere": 0,
    }


def test_a_surface_moved_away_from_the_sensor_is_adjacent_far_side():
    gt = _box((10, 8, 3), (12, 12, 6))
    pred = _box((11, 8, 3), (13, 12, 6))
    false = _loc(error_locations(pred, gt, None, SENSOR), 0, C.CAR)
    assert false["adjacent_far_side"] == 12 and sum(false.values()) == 12


def test_range_error_along_the_ray_and_an_invented_voxel_elsewhere():
    gt = _box((12, 10, 5), (13, 11, 6))  # one voxel on the sensor's line (y = 10, z = 5)
    pred = _box((9, 10, 5), (10, 11, 6))  # three voxels nearer, on the same ray
    pred = _box((3, 1, 1), (4, 2, 2), grid=pred)  # and one far off the ray
    loc = error_locations(pred, gt, None, SENSOR)
    assert _loc(loc, 0, C.CAR) == {
        "adjacent_sensor_side": 0,
        "adjacent_far_side": 0,
        "along_ray": 1,
        "elsewhere": 1,
    }
    assert _loc(loc, 1, C.CAR)["along_ray"] == 1


def test_mask_limits_the_wrong_voxels_not_the_reference():
    gt = _box((10, 8, 3), (12, 12, 6))
    pred = _box((9, 8, 3), (11, 12, 6))
    mask = np.zeros(SHAPE, bool)
    mask[9] = True  # only the front layer is evaluated; the GT voxels behind it are not
    loc = error_locations(pred, gt, mask, SENSOR)
    assert _loc(loc, 0, C.CAR)["adjacent_sensor_side"] == 12
    assert loc.counts[1].sum() == 0  # the missed layer x = 11 is outside the mask


def test_wrong_class_counts_for_both_classes_and_sums():
    gt = _box((10, 8, 3), (12, 12, 6), cls=C.TRUCK)
    pred = _box((10, 8, 3), (12, 12, 6), cls=C.CAR)
    loc = error_locations(pred, gt, None, SENSOR)
    assert loc.counts[0, C.CAR, 3] == 24  # no GT car anywhere: elsewhere
    assert loc.counts[1, C.TRUCK, 3] == 24
    twice = loc + loc
    assert twice.counts[0, C.CAR, 3] == 48
    assert set(twice.as_dict()) == {"car", "truck"}


def test_class_counts_from_the_confusion_matrix():
    gt = _box((10, 8, 3), (12, 12, 6))
    pred = _box((9, 8, 3), (11, 12, 6))
    m = OccupancyMetric()
    m.update(pred, gt)
    car = class_counts(m.confusion)["car"]
    assert car["gt_voxels"] == 24 and car["labelled_voxels"] == 24 and car["true_voxels"] == 12
    assert car["iou"] == pytest.approx(12 / 36)
    assert np.isnan(class_counts(m.confusion)["pole"]["iou"])


def test_bad_sensor_is_refused():
    g = np.full(SHAPE, C.FREE, np.uint8)
    with pytest.raises(MetricInputError, match="sensor_voxel"):
        error_locations(g, g, None, np.array([np.nan, 0, 0]))
