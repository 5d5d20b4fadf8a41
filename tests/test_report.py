"""The report writer: files exist, results.json equals the input, report.md holds the tables."""

from __future__ import annotations

import json

import numpy as np
import pytest

from flows.commands.report import ReportError, to_jsonable, write_report
from tasks import conventions as C
from tasks.metrics._common import PRCounts
from tasks.metrics.detection import DetectionCounts
from tasks.metrics.occupancy import OccupancyMetric
from tasks.metrics.velocity import VelocityErrors


def one_frame_scores(pred, gt, mask):
    metric = OccupancyMetric()
    metric.update(pred, gt, mask)
    return metric.compute()


def sample_grids(seed: int = 0, shape=(48, 48, 24)):
    """A small scene (ground, a wall, a tree, two pedestrians) and a perturbed prediction of it."""
    rng = np.random.default_rng(seed)
    gt = np.full(shape, C.FREE, np.uint8)
    gt[:, :, 4] = C.ROAD
    gt[:, :12, 4] = C.TERRAIN
    gt[30:34, 36:, 5:14] = C.OTHER_STRUCTURE
    gt[10:13, 5:8, 5:16] = C.VEGETATION
    gt[20:22, 20:22, 5:14] = C.PEDESTRIAN
    gt[26:28, 14:16, 5:13] = C.PEDESTRIAN
    pred = gt.copy()
    pred[20:22, 20:22, 5:14] = C.FREE
    pred[21:23, 21:23, 5:14] = C.PEDESTRIAN  # shifted by one voxel
    pred[:, 8:12, 4][rng.random((shape[0], 4)) < 0.5] = C.ROAD  # terrain / road confusion
    pred[40:42, 5:7, 5:8] = C.CAR  # an extra object
    mask = np.ones(shape, bool)
    mask[:, :, :4] = False
    for x in range(shape[0]):  # a camera frustum: columns outside +-45 deg unseen
        mask[x, : max(0, shape[1] // 2 - x - 2)] = False
        mask[x, min(shape[1], shape[1] // 2 + x + 2) :] = False
    return pred, gt, mask


def results_fixture(pred, gt, mask) -> dict:
    return {
        "title": "Synthetic benchmark",
        "meta": {"dataset": "out/", "frames": 3},
        "static": {
            "per_class_iou": {"road": 0.888, "vegetation": 0.68, "terrain": 0.57},
            "miou": 0.712,
            "coverage": 0.968,
            "voxel_accuracy": 0.881,
            "point_accuracy": 0.94,
            "num_points": 1000,
            "num_voxels": 120,
        },
        "pedestrian_boxes": {
            "7": PRCounts(8, 10, 4, 5).as_dict(),
            "all": PRCounts(8, 10, 4, 5).as_dict(),
        },
        "pedestrian_lidar": {
            "7": PRCounts(19, 20, 9, 10).as_dict(),
            "11": PRCounts(9, 10, 8, 10).as_dict(),
            "all": (PRCounts(19, 20, 9, 10) + PRCounts(9, 10, 8, 10)).as_dict(),
        },
        "detection": {
            "crowded": DetectionCounts(480, 6, 6, 5).as_dict(),
            "night": DetectionCounts(40, 12, 3, 1).as_dict(),
        },
        "occupancy": one_frame_scores(pred, gt, mask).as_dict(),
        "fit": {"PVE_mm": 41.5, "MPJPE_mm": 35.25, "PA_MPJPE_mm": 22.0, "MPERE": 0.031},
        "tracking": {
            "0": {
                "mota": 0.5,
                "idf1": 2 / 3,
                "hota": 0.7071,
                "deta": 1.0,
                "assa": 0.5,
                "switches": 1,
                "num_objects": 6,
            }
        },
        "velocity": VelocityErrors(1.0, 2, 6.0, 3).as_dict(),
        "extra_numbers": {"frames_per_s": np.float32(12.5), "workers": np.int64(4)},
    }


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    out = tmp_path_factory.mktemp("report")
    pred, gt, mask = sample_grids()
    results = results_fixture(pred, gt, mask)
    rng = np.random.default_rng(1)
    figures = {
        "bev": [
            {
                "title": "seq 0 frame 3",
                "pred": pred,
                "gt": gt,
                "mask": mask,
                "range_min": (0.4, -4.8, -1.0),
                "voxel_size_m": 0.2,
            }
        ],
        "histograms": {
            "PVE per person": {"values": rng.gamma(4, 10, 200), "xlabel": "PVE (mm)"},
            "AVE-T per voxel": rng.random(50),
        },
    }
    path = write_report(out, results, figures)
    return out, path, results


def test_files_exist_and_are_small(report):
    out, path, _ = report
    assert path == out / "report.md" and path.is_file() and (out / "results.json").is_file()
    pngs = sorted(p.name for p in (out / "figures").glob("*.png"))
    assert pngs == [
        "bev_00_seq_0_frame_3.png",
        "hist_ave_t_per_voxel.png",
        "hist_pve_per_person.png",
        "occupancy_class_iou.png",
        "static_class_iou.png",
    ]
    for p in (out / "figures").glob("*.png"):
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size < 300_000


def test_json_equals_input(report):
    out, _, results = report
    back = json.loads((out / "results.json").read_text())
    assert back == to_jsonable(results)
    assert back["detection"]["crowded"] == results["detection"]["crowded"]
    assert back["extra_numbers"] == {"frames_per_s": 12.5, "workers": 4}
    # NaN (car absent from both grids) becomes null
    assert (
        results["occupancy"]["per_class_iou"]["truck"]
        != results["occupancy"]["per_class_iou"]["truck"]
    )
    assert back["occupancy"]["per_class_iou"]["truck"] is None


def test_markdown_has_the_tables(report):
    out, path, _ = report
    md = path.read_text()
    for title in (
        "Static semantic voxels",
        "Pedestrian voxels (vs GT 3D boxes)",
        "Detection robustness",
        "Semantic occupancy",
        "Body fit accuracy",
        "Tracking",
        "Pedestrian velocity",
        "Extra numbers",
    ):
        assert f"## {title}" in md
    assert md.count("*How to read this:*") >= 9
    assert "| mIoU (road / vegetation / terrain) | 71.2 (88.8 / 68.0 / 57.0) |" in md
    assert "| crowded | 480 | 6 | 6 | 5 | 98.8 | 99.0 | 1.2 |" in md
    assert "| Precision | 95.0 | 90.0 | 93.3 |" in md  # per sequence and micro-averaged 'all'
    assert "| all | 0.500 | 2.000 | 2 | 3 |" in md  # AVE-O 1 / 2, AVE-T 6 / 3 m/s, voxel counts
    assert "| all | 41.5 | 35.2 | 22.0 | 0.031 |" in md
    for p in (out / "figures").glob("*.png"):
        assert f"figures/{p.name}" in md


def test_bad_results_fail_clearly(tmp_path):
    with pytest.raises(ReportError, match="cannot write a object"):
        write_report(tmp_path, {"x": {"y": object()}})
    with pytest.raises(ReportError, match="missing 'gt'"):
        write_report(tmp_path, {}, {"bev": [{"title": "t", "pred": np.zeros((2, 2, 2), np.uint8)}]})
