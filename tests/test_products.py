"""Typed stage products (storage/products.py) and storage/SCHEMA.md agreeing with the code."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from storage.products import PRODUCTS, Bodies, Detections, ProductError, StaticMapProduct, Tracks
from storage.schemas import TABLE_NAMES, file_schema

SCHEMA_MD = Path(__file__).resolve().parents[1] / "storage" / "SCHEMA.md"


def _tracks(rows: int = 2, points: int = 5) -> Tracks:
    return Tracks(
        frame=np.arange(rows, dtype=np.int64),
        det_index=np.zeros(rows, np.int64),
        track_id=np.ones(rows, np.int64),
        boxes_xyxy=np.zeros((rows, 4), np.float32),
        scores=np.ones(rows, np.float32),
        keypoints=np.zeros((rows, 17, 3), np.float32),
        lidar_box=np.full(rows, -1, np.int64),
        gt_index=np.zeros(rows, np.int64),
        points_in_image=np.array([2, 1][:rows], np.int64),
        points_offsets=np.array([0, 3, points][: rows + 1], np.int64),
        points_index=np.arange(points, dtype=np.int64),
    )


def test_round_trip_and_points_of(tmp_path):
    t = _tracks()
    t.write(tmp_path)
    back = Tracks.read(tmp_path)
    assert all(np.array_equal(a, b) for a, b in zip(t.arrays().values(), back.arrays().values()))
    assert back.points_of(1).tolist() == [3, 4] and back.points_of(
        0, in_image_only=True
    ).tolist() == [0, 1]
    assert (tmp_path / "tracks.npz").read_bytes() == (
        t.write(tmp_path / "again") and (tmp_path / "again" / "tracks.npz").read_bytes()
    )


@pytest.mark.parametrize(
    "change, message",
    [
        ({"scores": np.ones(2, np.float64)}, "scores must be a float32 array"),
        ({"keypoints": np.zeros((2, 17), np.float32)}, r"keypoints must have shape \('R', 17, 3\)"),
        ({"track_id": np.ones(3, np.int64)}, "expected R = 2"),
        ({"points_offsets": np.array([0, 3], np.int64)}, r"expected R\+1 = 3"),
    ],
)
def test_a_wrong_dtype_or_shape_fails_loudly(change, message):
    fields = {**_tracks().arrays(), **change}
    with pytest.raises(ProductError, match=message):
        Tracks(**fields)


def test_reading_checks_the_file(tmp_path):
    np.savez(tmp_path / "tracks.npz", frame=np.zeros(2, np.int32))
    with pytest.raises(ProductError, match="missing field"):
        Tracks.read(tmp_path)
    (tmp_path / "bodies.npz").write_bytes(b"not a zip")
    with pytest.raises(ProductError, match="bodies.npz: cannot read"):
        Bodies.read(tmp_path)
    with pytest.raises(ProductError, match="is missing"):
        StaticMapProduct.read(tmp_path)


def test_empty_products_have_their_row_shapes():
    empty = Detections.empty(H=4, W=5)
    assert empty.keypoints.shape == (0, 17, 3) and empty.semantic.shape == (4, 5)
    assert Tracks.empty().points_offsets.tolist() == [0]
    assert len(Bodies.empty().frame) == 0


def _md_tables(text: str, heading: str) -> dict[str, list[list[str]]]:
    """Markdown tables under level-3 headings inside the level-2 section ``heading``."""
    section = text.split(f"## {heading}", 1)[1].split("\n## ", 1)[0]
    out: dict[str, list[list[str]]] = {}
    for block in re.split(r"\n### ", section)[1:]:
        title = block.splitlines()[0]
        rows = [
            [c.strip() for c in line.strip().strip("|").split("|")]
            for line in block.splitlines()
            if line.startswith("|") and not line.startswith("|---")
        ]
        out[title] = rows[1:]
    return out


def test_schema_md_documents_every_product_field():
    tables = _md_tables(SCHEMA_MD.read_text(), "Stage products")
    for product in PRODUCTS:
        title = next((t for t in tables if f" {product.__name__} " in f" {t} "), None)
        assert title is not None, f"SCHEMA.md has no section for {product.__name__}"
        doc = {row[0]: (row[1], row[2]) for row in tables[title]}
        want = {
            name: (
                str(spec.dtype),
                "(" + ", ".join(map(str, spec.shape)) + ("," if len(spec.shape) == 1 else "") + ")",
            )
            for name, spec in product.specs().items()
        }
        assert doc == want, product.__name__


def test_schema_md_documents_every_table_column():
    tables = _md_tables(SCHEMA_MD.read_text(), "Tables")
    for name in TABLE_NAMES:
        title = next(t for t in tables if t.startswith(name))
        documented = set()
        for row in tables[title]:
            documented |= {c.strip() for c in row[0].split(",")}
        documented = {c.split(" ")[0] for c in documented}
        assert documented == set(file_schema(name).names), name
