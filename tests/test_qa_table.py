"""storage/qa.py: the manual QA table round-trips, replaces a frame's verdict whole, refuses a
table of another version without touching it, and leaves no temporary file."""

from __future__ import annotations

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from storage.qa import (
    QA_SCHEMA,
    QATableError,
    checked_frames,
    qa_path,
    read_qa,
    save_frame,
)
from tasks.view.qa import Mark


def _save(out, frame, marks, seq="0", t=1):
    return save_frame(out, seq, frame, frame * 2, "crowded", marks, {3: (1, 2, 3, 4)}, "v1", t)


def test_round_trip_replace_and_empty_frames(tmp_path):
    assert read_qa(tmp_path).num_rows == 0
    _save(tmp_path, 1, [Mark("T", 3), Mark("M_vis", None, 10.5, 20.0)])
    _save(tmp_path, 0, [])  # checked, nobody there
    table = read_qa(tmp_path)
    assert table.schema.equals(QA_SCHEMA, check_metadata=True)
    rows = table.to_pylist()
    assert [(r["frame"], r["kind"]) for r in rows] == [(0, None), (1, "T"), (1, "M_vis")]
    assert rows[1]["box2d_xyxy"] == [1, 2, 3, 4] and rows[2]["u"] == 10.5
    assert rows[1]["raw_frame"] == 2 and rows[1]["occupancy_version"] == "v1"
    assert checked_frames(table) == {("0", 0), ("0", 1)}
    # a new verdict of frame 1 replaces the old one whole, the other frames stay
    _save(tmp_path, 1, [Mark("W", 3)], t=2)
    rows = read_qa(tmp_path).to_pylist()
    assert [(r["frame"], r["kind"], r["marked_at_ns"]) for r in rows] == [(0, None, 1), (1, "W", 2)]
    assert sorted(p.name for p in qa_path(tmp_path).parent.iterdir()) == [
        ".lock",
        "detection_qa.parquet",
    ]


def test_a_table_of_an_older_version_is_refused_and_left_as_it_was(tmp_path):
    path = qa_path(tmp_path)
    path.parent.mkdir(parents=True)
    old = pa.table({"sequence": ["0"], "frame": [1], "verdict": ["T"]}).replace_schema_metadata(
        {"mobileocc.schema": "detection_qa", "mobileocc.schema_version": "0"}
    )
    pq.write_table(old, path)
    before = path.read_bytes()
    with pytest.raises(QATableError, match=r"schema version 0, written by an older mobileocc"):
        read_qa(tmp_path)
    with pytest.raises(QATableError, match="schema version 0"):
        _save(tmp_path, 2, [Mark("T", 3)])
    assert path.read_bytes() == before
    assert sorted(p.name for p in path.parent.iterdir()) == [".lock", "detection_qa.parquet"]
    # and a Parquet file that is no QA table, or no Parquet at all
    pq.write_table(pa.table({"a": [1]}), path)
    with pytest.raises(QATableError, match="not a mobileocc QA table"):
        read_qa(tmp_path)
    path.write_bytes(b"not parquet")
    with pytest.raises(QATableError, match="not a readable Parquet file"):
        read_qa(tmp_path)


def test_the_report_section_counts_marks_and_names_rebuilt_sequences(tmp_path):
    from flows.viewer.qa import manual_qa_section

    assert manual_qa_section(tmp_path) == (None, None)  # no pass saved: no section
    _save(tmp_path, 1, [Mark("T", 3), Mark("M_vis", None, 10.5, 20.0)])
    _save(tmp_path, 0, [])
    counts, note = manual_qa_section(tmp_path, {"0": "v1"})
    assert counts["crowded"]["T"] == 1 and counts["crowded"]["M_vis"] == 1
    assert counts["all"]["recall"] == 0.5 and "2 frame(s) checked" in note
    assert "rebuilt" not in note
    _, note = manual_qa_section(tmp_path, {"0": "v2"})
    assert "sequence(s) 0 were rebuilt after their frames were checked" in note
    qa_path(tmp_path).write_bytes(b"broken")  # evaluate goes on, saying why
    assert manual_qa_section(tmp_path)[0] is None
    assert "manual QA table not read" in manual_qa_section(tmp_path)[1]
