"""Round-trips and validation errors of the precomputed perception files."""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from PIL import Image

from storage.perception_files import (
    DETECTIONS_FILE,
    LIDAR_FILE,
    META_FILE,
    PerceptionFileError,
    PrecomputedPerception,
    rle_decode,
    rle_encode,
    rle_from_string,
    rle_to_string,
    write_perception,
)
from tasks.perception.types import ImagePerception, LidarDetections

W, H = 40, 30


def _frame(rng: np.random.Generator, count: int) -> ImagePerception:
    boxes = np.zeros((count, 4), np.float32)
    masks = np.zeros((count, H, W), bool)
    for d in range(count):
        u0, v0 = rng.integers(0, 20), rng.integers(0, 10)
        boxes[d] = [u0 + 0.25, v0 + 0.5, u0 + 12.75, v0 + 18.0]
        masks[d, v0 : v0 + 18, u0 : u0 + 12] = rng.random((18, 12)) < 0.7
    masks[:, 0, 0] = True  # a run starting with ones at the very first pixel
    if count:
        masks[-1] = False  # a detection without a mask
    keypoints = rng.uniform(0, 1, (count, 17, 3)).astype(np.float32)
    keypoints[:, :, :2] *= [W, H]
    semantic = rng.integers(0, 19, (H, W)).astype(np.uint8)
    semantic[0] = 255
    return ImagePerception(
        boxes_xyxy=boxes,
        scores=rng.uniform(0, 1, count).astype(np.float32),
        keypoints=keypoints,
        masks=masks,
        semantic=semantic,
    )


def _lidar(rng: np.random.Generator, count: int) -> LidarDetections:
    return LidarDetections(
        centers=rng.normal(0, 5, (count, 3)).astype(np.float32),
        sizes=rng.uniform(0.3, 2.0, (count, 3)).astype(np.float32),
        yaws=rng.uniform(-3, 3, count).astype(np.float32),
        scores=rng.uniform(0, 1, count).astype(np.float32),
    )


def test_rle_known_values():
    mask = np.array([[0, 1], [1, 1], [0, 0]], bool)  # column-major: 0 1 0 | 1 1 0
    np.testing.assert_array_equal(rle_encode(mask), [1, 1, 1, 2, 1])
    np.testing.assert_array_equal(rle_decode([1, 1, 1, 2, 1], 3, 2), mask)
    np.testing.assert_array_equal(rle_encode(np.ones((2, 2), bool)), [0, 4])
    # hand-computed COCO strings: 100 -> 'T3' (two 5-bit groups), negative delta 1 - 2 -> 'O'
    assert rle_to_string([0, 3, 100]) == "03T3"
    assert rle_to_string([1, 2, 3, 1]) == "123O"
    np.testing.assert_array_equal(rle_from_string("123O"), [1, 2, 3, 1])


def test_rle_random_roundtrip():
    rng = np.random.default_rng(0)
    for shape in [(1, 1), (7, 5), (64, 33)]:
        for density in (0.0, 0.3, 1.0):
            mask = rng.random(shape) < density
            counts = rle_encode(mask)
            assert counts.sum() == mask.size
            np.testing.assert_array_equal(rle_from_string(rle_to_string(counts)), counts)
            np.testing.assert_array_equal(rle_decode(counts, *shape), mask)


def test_roundtrip(tmp_path):
    rng = np.random.default_rng(1)
    images = {0: _frame(rng, 3), 1: _frame(rng, 0), 5: _frame(rng, 1)}
    lidar = {0: _lidar(rng, 2), 1: _lidar(rng, 0), 5: _lidar(rng, 1)}
    root = write_perception(tmp_path / "seq", W, H, images.items(), lidar.items())
    assert [p.name for p in tmp_path.iterdir()] == ["seq"]  # no temporary left beside it
    reader = PrecomputedPerception(root)
    assert reader.frames == (0, 1, 5)
    for frame, expected in images.items():
        got = ImagePerception(**reader.image(frame))
        np.testing.assert_allclose(got.boxes_xyxy, expected.boxes_xyxy, atol=1e-5)
        np.testing.assert_array_equal(got.scores, expected.scores)
        np.testing.assert_array_equal(got.keypoints, expected.keypoints)
        np.testing.assert_array_equal(got.masks, expected.masks)
        np.testing.assert_array_equal(got.semantic, expected.semantic)
        boxes = LidarDetections(**reader.lidar(frame))
        for name in ("centers", "sizes", "yaws", "scores"):
            np.testing.assert_array_equal(getattr(boxes, name), getattr(lidar[frame], name))
    assert len(ImagePerception(**reader.image(1))) == 0


def test_written_without_lidar_boxes_reads_as_no_boxes(tmp_path):
    rng = np.random.default_rng(2)
    reader = PrecomputedPerception(write_perception(tmp_path / "s", W, H, [(0, _frame(rng, 1))]))
    assert len(ImagePerception(**reader.image(0))) == 1
    assert len(LidarDetections(**reader.lidar(0))) == 0


@pytest.fixture
def written(tmp_path):
    rng = np.random.default_rng(3)
    images = [(0, _frame(rng, 2)), (1, _frame(rng, 1))]
    return write_perception(
        tmp_path / "seq", W, H, images, [(0, _lidar(rng, 1)), (1, _lidar(rng, 1))]
    )


def _rewrite(path, column, row, value):
    table = pq.read_table(path)
    values = table.column(column).to_pylist()
    values[row] = value
    index = table.column_names.index(column)
    pq.write_table(
        table.set_column(
            index, table.schema.field(column), pa.array(values, table.schema.field(column).type)
        ),
        path,
    )


@pytest.mark.parametrize(
    "column,row,value,pattern",
    [
        ("bbox", 1, [1.0, 2.0, float("nan"), 3.0], r"frame 0: row 1: bbox has NaN"),
        ("bbox", 0, [1.0, 2.0, -3.0, 3.0], r"frame 0: row 0: bbox .* w, h > 0"),
        ("bbox", 2, [35.0, 2.0, 10.0, 3.0], r"frame 1: row 2: bbox .*40 x 30 image"),
        ("score", 0, 1.5, r"frame 0: row 0: score 1.5 outside \[0, 1\]"),
        ("frame", 2, 7, r"frame 7: frame key not listed"),
        ("keypoints", 0, [0.5] * 50 + [2.0], r"frame 0: row 0: keypoint confidences"),
    ],
)
def test_bad_detection_rows(written, column, row, value, pattern):
    _rewrite(written / DETECTIONS_FILE, column, row, value)
    with pytest.raises(PerceptionFileError, match=pattern) as info:
        PrecomputedPerception(written)
    assert DETECTIONS_FILE in str(info.value)


def test_bad_mask_rle(written):
    _rewrite(written / DETECTIONS_FILE, "mask_counts", 0, rle_to_string([5, 5]))
    reader = PrecomputedPerception(written)
    with pytest.raises(
        PerceptionFileError,
        match=r"frame 0: row 0: mask_counts: RLE counts sum to 10, expected 30 x 40",
    ):
        reader.image(0)


@pytest.mark.parametrize(
    "column,value,pattern",
    [
        ("length", 0.0, r"frame 0: row 0: box size"),
        ("score", -0.5, r"score -0.5"),
        ("yaw", float("inf"), "NaN/inf"),
    ],
)
def test_bad_lidar_rows(written, column, value, pattern):
    _rewrite(written / LIDAR_FILE, column, 0, value)
    with pytest.raises(PerceptionFileError, match=pattern) as info:
        PrecomputedPerception(written)
    assert LIDAR_FILE in str(info.value)


def test_bad_semantic_png(written):
    reader = PrecomputedPerception(written)
    path = written / "semantic" / "000001.png"
    Image.fromarray(np.zeros((H, W + 1), np.uint8)).save(path)
    with pytest.raises(
        PerceptionFileError, match=r"000001.png: frame 1: image is 41 x 30, expected 40 x 30"
    ):
        reader.image(1)
    bad = np.zeros((H, W), np.uint8)
    bad[3, 4] = 40
    Image.fromarray(bad).save(path)
    with pytest.raises(PerceptionFileError, match=r"pixel \(u=4, v=3\) = 40"):
        reader.image(1)
    Image.fromarray(np.zeros((H, W, 3), np.uint8)).save(path)
    with pytest.raises(PerceptionFileError, match=r"mode 'RGB'"):
        reader.image(1)
    path.unlink()
    with pytest.raises(PerceptionFileError, match=r"frame 1: semantic PNG is missing"):
        reader.image(1)


def test_bad_meta_and_missing_files(written):
    with pytest.raises(PerceptionFileError, match=r"frame 9: frame not in"):
        PrecomputedPerception(written).image(9)
    meta = json.loads((written / META_FILE).read_text())
    (written / META_FILE).write_text(json.dumps({**meta, "image_width": 0}))
    with pytest.raises(PerceptionFileError, match=r"image_width must be a positive integer, got 0"):
        PrecomputedPerception(written)
    (written / META_FILE).write_text(json.dumps({**meta, "frames": [0, 0, 1]}))
    with pytest.raises(PerceptionFileError, match=r"duplicates"):
        PrecomputedPerception(written)
    (written / META_FILE).write_text(json.dumps(meta))
    (written / LIDAR_FILE).write_bytes(b"not parquet")
    with pytest.raises(PerceptionFileError, match=r"lidar_boxes.parquet: not a readable Parquet"):
        PrecomputedPerception(written)
    (written / DETECTIONS_FILE).unlink()
    with pytest.raises(PerceptionFileError, match=r"detections.parquet: file is missing"):
        PrecomputedPerception(written)
    (written / META_FILE).write_text("{")
    with pytest.raises(PerceptionFileError, match=r"perception.json: invalid JSON"):
        PrecomputedPerception(written)


def test_missing_column(written):
    table = pq.read_table(written / DETECTIONS_FILE).drop_columns(["score"])
    pq.write_table(table, written / DETECTIONS_FILE)
    with pytest.raises(PerceptionFileError, match=r"missing columns \['score'\]"):
        PrecomputedPerception(written)


def test_sequence_without_any_detection(tmp_path):
    empty = ImagePerception.empty(W, H)
    root = write_perception(
        tmp_path / "s", W, H, [(0, empty), (1, empty)], [(0, LidarDetections.empty())]
    )
    reader = PrecomputedPerception(root)
    got = ImagePerception(**reader.image(1))
    assert len(got) == 0 and got.masks.shape == (0, H, W) and (got.semantic == 255).all()
    assert len(LidarDetections(**reader.lidar(0))) == 0
