"""No observed surface is ever free (issue 38, item 3): class 9 unclassified, returns that get no
class still occupy their voxels, and the label-honesty metric that counts free returns."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from storage.network_files import BUNDLED_MODELS, DEFAULT_BUNDLED_CACHE
from tasks import conventions as C
from tasks.metrics.free_returns import free_return_counts, label_counts
from tasks.metrics.occupancy import OccupancyMetric
from tasks.occupancy.fuse import (
    PedestrianMesh,
    fuse_frame,
    occupy_returns,
    orphan_returns,
    returns_without_class,
)
from tasks.occupancy.grid import GridSpec
from tasks.occupancy.resample import grid_reach_m, static_in_grid
from tasks.occupancy.settings import MapParams
from tasks.occupancy.static_map import StaticMap, merge_static_maps
from tasks.occupancy.synthetic import box_mesh
from tests.test_labels_exact import VOXEL, _mapper

SPEC = GridSpec((0.4, -2.0, -1.0), (8.0, 2.0, 2.2), VOXEL)


def test_class_ids_are_fixed():
    """Other engineers code against these: unclassified 9, free last (10), 11 classes."""
    assert (C.UNCLASSIFIED, C.FREE, C.NUM_CLASSES, C.NUM_SEMANTIC_CLASSES) == (9, 10, 11, 9)
    assert C.CLASS_NAMES[C.UNCLASSIFIED] == "unclassified" and C.CLASS_NAMES[-1] == "free"
    assert len(C.CLASS_COLORS) == len(C.CLASS_TO_CITYSCAPES) == C.NUM_CLASSES
    assert len({tuple(c) for c in C.CLASS_COLORS}) == C.NUM_CLASSES  # a colour of its own


def _wall(x_face: float = 5.05) -> np.ndarray:
    """Returns of a wall facing the sensor at x = x_face, y in [-1, 1], z in [-0.6, 0.6]."""
    ys, zs = np.meshgrid(np.linspace(-1.0, 1.0, 81), np.linspace(-0.6, 0.6, 49), indexing="ij")
    return np.stack([np.full(ys.size, x_face), ys.ravel(), zs.ravel()], 1).astype(np.float32)


def _map(sweep: np.ndarray, semantic_id: int):
    """The static map of one sweep (LiDAR = world = base) whose semantic image is one id."""
    mapper = _mapper(MapParams(voxel_size_m=VOXEL))
    none = np.zeros((0, 3), np.float32)
    mapper.add_sweep(
        sweep,
        np.eye(4),
        np.full((480, 640), semantic_id, np.uint8),
        np.zeros((480, 640), np.uint16),
        np.zeros((0, 4), np.float32),
        none,
        none,
        np.zeros(0, np.float32),
    )
    final, _ = mapper.finish((C.ROAD, C.TERRAIN))
    return final, mapper.occupancy


def _fuse(static: StaticMap, occupancy, sweep: np.ndarray, **kw):
    pts, labels = static_in_grid(static, SPEC, np.eye(4), grid_reach_m(SPEC))
    return fuse_frame(
        SPEC,
        np.eye(4),
        static_points_world=pts,
        static_labels=labels,
        occupancy=occupancy,
        lidar_points_base=sweep,
        lidar_origin_base=np.zeros(3),
        threads=1,
        **kw,
    )


def test_wall_of_unlabelled_returns_is_occupied_unclassified():
    """No segmenter: every return is UNLABELED (sky's id is no class). Before issue 38 they cast
    no vote, the map was empty and the wall was exported free; now the wall occupies exactly the
    voxels it occupies when the camera calls it a car, as UNCLASSIFIED."""
    sweep = _wall()
    car, _ = _map(sweep, C.CITYSCAPES_TRAIN_IDS["car"])
    bare, occupancy = _map(sweep, C.CITYSCAPES_TRAIN_IDS["sky"])
    assert len(car.keys) > 50 and set(car.labels.tolist()) == {C.CAR}
    assert set(bare.labels.tolist()) == {C.UNCLASSIFIED}
    np.testing.assert_array_equal(bare.keys, car.keys)
    grids = _fuse(bare, occupancy, sweep)
    idx = SPEC.index_of(sweep)
    assert np.all(grids.semantics[tuple(idx.T)] == C.UNCLASSIFIED)
    assert grids.semantics[grids.semantics < C.FREE].tolist() == [C.UNCLASSIFIED] * int(
        np.count_nonzero(grids.semantics < C.FREE)
    )
    fr = free_return_counts(grids.semantics, grids.mask_lidar, sweep, SPEC.range_min, VOXEL)
    assert fr.return_voxels == len(np.unique(idx, axis=0)) and fr.free_return_voxels == 0


def _person(center=(4.0, 0.5, -0.1)) -> np.ndarray:
    """Returns of a person: the front of a 0.4 x 0.5 x 1.7 m box facing the sensor."""
    ys, zs = np.meshgrid(np.linspace(-0.25, 0.25, 11), np.linspace(-0.85, 0.85, 35), indexing="ij")
    c = np.asarray(center)
    return np.stack([np.full(ys.size, c[0] - 0.2), c[1] + ys.ravel(), c[2] + zs.ravel()], 1)


def test_removed_person_without_a_body_still_occupies_its_returns():
    """A person's returns are removed from the static map; with no fitted body they used to end
    free. PEDESTRIAN where the track confirmed the person, else UNCLASSIFIED; nothing is added
    where a body holds the returns."""
    empty = StaticMap(
        VOXEL, np.zeros((0, 3), np.int64), np.zeros(0, np.uint8), np.zeros((0, 10), np.uint16), 0
    )
    sweep = _person().astype(np.float32)
    idx = SPEC.index_of(sweep)
    confirmed = _fuse(empty, None, sweep, return_labels=np.full(len(sweep), C.PEDESTRIAN))
    assert np.all(confirmed.semantics[tuple(idx.T)] == C.PEDESTRIAN)
    assert np.count_nonzero(confirmed.semantics < C.FREE) == len(np.unique(idx, axis=0))
    assert not confirmed.instances.any()  # no body: no instance, no velocity
    unconfirmed = _fuse(empty, None, sweep)
    assert np.all(unconfirmed.semantics[tuple(idx.T)] == C.UNCLASSIFIED)
    n = len(np.unique(idx, axis=0))  # the instances table's per-person counts
    assert returns_without_class(confirmed.semantics, confirmed.instances, idx) == (0, n)
    assert returns_without_class(unconfirmed.semantics, unconfirmed.instances, idx) == (n, 0)
    # a fitted body over the returns: they are its; the rule adds nothing
    box = box_mesh((4.0, 0.5, -0.1), (0.4, 0.5, 1.7))
    body = [PedestrianMesh(3, np.asarray(box.vertices), np.asarray(box.triangles))]
    fitted = _fuse(empty, None, sweep, pedestrians=body, return_labels=np.zeros(len(sweep)))
    alone = fuse_frame(
        SPEC,
        np.eye(4),
        static_points_world=np.zeros((0, 3)),
        static_labels=np.zeros(0, np.uint8),
        pedestrians=body,
    )
    np.testing.assert_array_equal(fitted.semantics, alone.semantics)


def test_occupy_returns_reaches_no_further_than_one_voxel():
    sem = np.full((8, 8, 8), C.FREE, np.uint8)
    sem[2, 2, 2] = C.VEGETATION
    returns = np.array([[3, 3, 3], [4, 2, 2], [6, 6, 6], [6, 6, 6], [9, 0, 0]])
    orphan = orphan_returns(sem < C.FREE, returns)
    assert orphan.tolist() == [False, True, True, True, False]  # outside the grid: not counted
    out = occupy_returns(sem, returns, np.array([1, C.UNCLASSIFIED, 0, 5, 0], np.uint8))
    assert out[3, 3, 3] == C.FREE  # next to the vegetation: already honest
    assert out[4, 2, 2] == C.UNCLASSIFIED and out[6, 6, 6] == C.PEDESTRIAN  # lowest id wins
    assert np.count_nonzero(out < C.FREE) == 3 and sem[4, 2, 2] == C.FREE  # input untouched
    with pytest.raises(ValueError, match="not an occupied class"):
        occupy_returns(sem, returns[:1], np.array([C.FREE], np.uint8))


def test_free_returns_metric_on_a_hand_made_grid():
    sem = np.full((10, 10, 4), C.FREE, np.uint8)
    mask = np.ones(sem.shape, np.uint8)
    pts = []

    def at(i, j, k=1, n=2):  # n returns in voxel (i, j, k), 1 m voxels from the origin
        pts.extend([(i + 0.3 + 0.1 * r, j + 0.5, k + 0.5) for r in range(n)])

    for i in range(1, 6):  # A: 5 free return voxels in a row: counted
        at(i, 1)
    for i in range(1, 5):  # B: 4 in a row: noise, not counted
        at(i, 4)
    for i in range(1, 7):  # C: 6 in a row, x 2..4 beside an occupied voxel: 1 + 2 left
        at(i, 7)
    sem[3, 8, 1] = C.POLE
    at(8, 9)  # D: its own voxel occupied
    sem[8, 9, 1] = C.UNCLASSIFIED
    for i in range(5):  # E: 5 in a row outside mask_lidar (unknown, not free)
        at(i, 9, 3)
        mask[i, 9, 3] = 0
    pts.append((20.0, 0.5, 0.5))  # outside the grid
    res = free_return_counts(sem, mask, np.array(pts), (0.0, 0.0, 0.0), 1.0)
    assert (res.return_voxels, res.free_return_voxels, res.clusters) == (21, 5, 1)
    assert res.share == pytest.approx(5 / 21)
    both = res + res
    assert both.as_dict()["free_returns_share"] == pytest.approx(5 / 21) and both.frames == 2
    inst = np.zeros(sem.shape, np.uint16)
    sem[0, 0, 0] = sem[0, 1, 0] = C.PEDESTRIAN
    inst[0, 0, 0] = 4
    lc = label_counts(sem, mask, inst).as_dict()
    assert lc["occupied_voxels"] == 4 and lc["unclassified_voxels"] == 1
    assert lc["pedestrian_voxels"] == 2 and lc["pedestrian_voxels_without_body"] == 1
    assert lc["unclassified_share"] == pytest.approx(1 / 4)


def test_unclassified_counts_against_the_true_class():
    """mIoU over the 9 semantic classes: an unclassified voxel where the truth is road is a miss
    of road, not a class of its own; it is occupied for the geometric IoU."""
    gt = np.full((4, 1, 1), C.FREE, np.uint8)
    gt[:2] = C.ROAD
    pred = gt.copy()
    pred[1] = C.UNCLASSIFIED
    m = OccupancyMetric()
    m.update(pred, gt)
    s = m.compute()
    assert len(s.per_class_iou) == C.NUM_SEMANTIC_CLASSES
    assert s.per_class_iou[C.ROAD] == pytest.approx(0.5) and s.miou == pytest.approx(0.5)
    assert s.geometric_iou == pytest.approx(1.0) and s.unclassified_share == pytest.approx(0.5)


def test_a_class_beats_no_class_when_camera_and_fallback_maps_merge():
    keys = np.array([[0, 0, 0], [1, 0, 0]], np.int64)
    counts = np.zeros((2, 10), np.uint16)
    seen = StaticMap(VOXEL, keys, np.array([C.UNCLASSIFIED, C.CAR], np.uint8), counts, 0)
    unseen = StaticMap(VOXEL, keys, np.array([C.ROAD, C.ROAD], np.uint8), counts, 0)
    assert merge_static_maps(seen, unseen).labels.tolist() == [C.ROAD, C.CAR]


BUNDLED_DIR = Path(__file__).resolve().parents[1] / DEFAULT_BUNDLED_CACHE


@pytest.mark.slow
@pytest.mark.skipif(
    not all((BUNDLED_DIR / n).is_file() for n in BUNDLED_MODELS),
    reason=f"bundled models not extracted to {BUNDLED_DIR} (make setup does it)",
)
def test_no_segmenter_and_no_truth_leaves_no_return_free(copy_dataset, tmp_path, capsys):
    """End to end on a recording with no ground truth and no image segmenter (real models,
    semantic.kind none; no fit stage: no body for anyone): evaluate still reports, and under
    0.5 % of return-holding voxels are exported free."""
    from flows.bench.common import make_config, run_stages
    from flows.commands.evaluate import evaluate
    from flows.commands.status import print_plan
    from flows.pipeline.units import unclassified_line
    from storage.tables import read_table

    data = copy_dataset()
    shutil.rmtree(data / "gt")
    out = tmp_path / "out"
    cfg = make_config(
        data,
        out,
        {
            "dataset.sequences": ["1"],
            "detect.image_provider": "models",
            "detect.models.semantic.kind": "none",
            "map.point_classes": "camera",  # no geometric classes either: mostly unclassified
            "detect.models.device": "cpu",
            "detect.models.bundled_dir": str(BUNDLED_DIR),
        },
    )
    report = run_stages(cfg, ("detect", "track", "map", "fuse", "export"))
    line = unclassified_line(report, cfg)
    assert line is not None and "semantic.kind: none" in line
    print_plan(cfg, dry_run=False)
    assert " 1  labels  " in capsys.readouterr().out  # status: the sequence's unclassified share
    res = evaluate(out, None, tmp_path / "report", sample_frames=0)
    assert "occupancy" not in res and "static" not in res  # no truth: no truth-based sections
    honesty = res["label_honesty"]["all"]
    assert honesty["return_voxels"] > 1000 and honesty["frames"] == 2
    assert honesty["free_returns_share"] < 0.005
    assert honesty["unclassified_share"] > 0.5
    assert "Label honesty" in (tmp_path / "report" / "report.md").read_text()
    # no fit stage: every tracked person's returns are pedestrian voxels without a body
    rows = read_table(out, "instances", "1").to_pylist()
    without = [r["pedestrian_voxels_without_body"] for r in rows]
    assert rows and all(v is not None for v in without) and sum(without) > 0
    assert honesty["pedestrian_voxels_without_body"] > 0


def test_ground_truth_simulated_before_class_9_is_refused(copy_dataset):
    """Old ground truth wrote free as 9: read now, its free space would be 'unclassified'."""
    from storage.gt import GTFormatError, frame_path, read_frame_gt, write_frame_gt

    data = copy_dataset()
    frame = read_frame_gt(data, "0", 0)  # today's truth reads
    path = frame_path(data, "0", 0)
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["occupancy"] = np.where(arrays["occupancy"] == C.FREE, 9, arrays["occupancy"])
    write_frame_gt(data, "0", 0, arrays)
    with pytest.raises(GTFormatError, match="simulate again"):
        read_frame_gt(data, "0", 0)
    assert (frame.occupancy == C.FREE).any()
