"""Parquet tables: schemas, round-trips, atomic partition replacement, discovery by other tools."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from storage import occupancy_store as occ
from storage import publish as pub
from storage import schemas, tables
from tasks import conventions as C


def frame_rows(n: int, offset: int = 0) -> list[dict]:
    eye = np.eye(4)
    return [
        {
            "frame": i,
            "raw_frame": 2 * i + offset,
            "stamp_ns": 1_675_000_000_000_000_000 + i * 200_000_000,
            "T_world_from_lidar": (eye + i).ravel(),
            "T_world_from_base": eye.ravel(),
            "lidar_path": f"3d_raw/os1/0/3d_raw_os1_0_{2 * i}.bin",
            "cam0_path": f"2d_raw/cam0/0/2d_raw_cam0_0_{2 * i}.png",
            "class_counts": list(range(C.NUM_CLASSES)),
            "is_night": False,
        }
        for i in range(n)
    ]


def test_schema_versions_and_metadata():
    for name in schemas.TABLE_NAMES:
        fs = schemas.file_schema(name)
        assert (
            fs.metadata[b"mobileocc.schema_version"] == str(schemas.SCHEMA_VERSIONS[name]).encode()
        )
        assert "sequence" not in fs.names
        assert schemas.dataset_schema(name).names[0] == "sequence"
    inst = schemas.file_schema("instances")
    assert inst.field("body_pose").type == pa.list_(pa.float32(), 69)
    assert inst.field("keypoints").type.list_size == 51
    assert schemas.file_schema("frames").field("stamp_ns").type == pa.int64()
    with pytest.raises(ValueError, match="unknown table"):
        schemas.file_schema("frame")


def test_round_trip_two_partitions_and_direct_readers(tmp_path):
    tables.write_partition(tmp_path, "frames", "a", frame_rows(3))
    tables.write_partition(tmp_path, "frames", "b", frame_rows(2, offset=100))
    t = tables.read_table(tmp_path, "frames")
    assert t.num_rows == 5 and t.schema.field("sequence").type == pa.string()
    assert t.column("sequence").to_pylist() == ["a"] * 3 + ["b"] * 2
    assert t.column("raw_frame").to_pylist() == [0, 2, 4, 100, 102]
    np.testing.assert_array_equal(
        np.asarray(t.column("T_world_from_lidar")[1].as_py()).reshape(4, 4), np.eye(4) + 1
    )
    assert t.column("cam1_path").null_count == 5
    b = tables.read_table(tmp_path, "frames", "b")
    assert b.num_rows == 2 and set(b.column("sequence").to_pylist()) == {"b"}
    # other tools open the files directly
    df = pd.read_parquet(tmp_path / "tables" / "frames", filters=[("sequence", "=", "a")])
    assert len(df) == 3 and list(df["stamp_ns"])[1] == 1_675_000_000_200_000_000
    one = pq.read_table(tmp_path / "tables" / "frames" / "sequence=a" / "data.parquet")
    assert one.schema.metadata[b"mobileocc.schema"] == b"frames"
    assert tables.read_table(tmp_path, "instances").num_rows == 0


def test_replacing_partition_is_whole_and_leaves_no_temp(tmp_path):
    tables.write_partition(tmp_path, "frames", "a", frame_rows(3))
    tables.write_partition(tmp_path, "frames", "a", frame_rows(1, offset=7))
    t = tables.read_table(tmp_path, "frames", "a")
    assert t.column("raw_frame").to_pylist() == [7]
    part = tmp_path / "tables" / "frames" / "sequence=a"
    assert sorted(p.name for p in part.iterdir()) == ["data.parquet"]


def test_hidden_temp_files_are_invisible(tmp_path):
    tables.write_partition(tmp_path, "frames", "a", frame_rows(2))
    # a crashed writer's leftovers: a hidden file in the partition and a hidden staging dir
    part = tmp_path / "tables" / "frames" / "sequence=a"
    pq.write_table(tables.to_table("frames", frame_rows(5)), part / ".tmp-crashed.parquet")
    staged = pub.stage_sequence(tmp_path, "a", "v9")
    pub.stage_table(staged, "frames", frame_rows(4))
    assert tables.read_table(tmp_path, "frames").num_rows == 2
    assert len(pd.read_parquet(tmp_path / "tables" / "frames")) == 2
    pub.publish_sequence(staged)
    assert tables.read_table(tmp_path, "frames", "a").num_rows == 4


def test_bad_rows_fail_loudly(tmp_path):
    rows = frame_rows(2)
    del rows[0]["stamp_ns"], rows[1]["stamp_ns"]
    with pytest.raises(occ.StoreError, match="required column 'stamp_ns'"):
        tables.write_partition(tmp_path, "frames", "a", rows)
    rows = frame_rows(1)
    rows[0]["T_world_from_base"] = [0.0] * 9
    with pytest.raises(occ.StoreError, match="T_world_from_base"):
        tables.to_table("frames", rows)
    with pytest.raises(occ.StoreError, match="unknown columns"):
        tables.to_table("frames", [{**frame_rows(1)[0], "colour": 3}])
    with pytest.raises(occ.StoreError, match="unknown table"):
        tables.write_partition(tmp_path, "frame", "a", frame_rows(1))
    with pytest.raises(occ.StoreError, match="invalid sequence"):
        tables.write_partition(tmp_path, "frames", "a/b", frame_rows(1))


def test_instances_and_sequences_columns(tmp_path):
    inst = {
        "track_id": [3, 1],
        "frame": [0, 0],
        "box3d_center": np.zeros((2, 3)),
        "keypoints": np.ones((2, 17, 3), np.float32),
        "body_pose": np.zeros((2, 69), np.float32),
        "vx": [0.5, None],
    }
    tables.write_partition(tmp_path, "instances", "s", inst)
    t = tables.read_table(tmp_path, "instances")
    assert t.column("track_id").to_pylist() == [1, 3]  # sorted by track, frame
    assert len(t.column("keypoints")[0].as_py()) == 51 and t.column("betas").null_count == 2
    seq = {
        "fingerprint": ["f"],
        "config_hash": ["c"],
        "code_version": ["0.1.0"],
        "status": ["ok"],
        "num_frames": [4],
        "K": [np.eye(3).ravel()],
        "image_width": [1224],
        "image_height": [1024],
    }
    tables.write_partition(tmp_path, "sequences", "s", seq)
    row = tables.read_table(tmp_path, "sequences").to_pylist()[0]
    assert row["sequence"] == "s" and row["error"] is None and row["K"][4] == 1.0


def test_older_partition_without_a_new_column_reads_as_null(tmp_path):
    # a partition written before `is_night` existed: the latest schema still reads it
    tables.write_partition(tmp_path, "frames", "new", frame_rows(1))
    old = tables.to_table("frames", frame_rows(2)).drop_columns(["is_night"])
    part = tmp_path / "tables" / "frames" / "sequence=old"
    part.mkdir(parents=True)
    pq.write_table(old, part / "data.parquet")
    t = tables.read_table(tmp_path, "frames")
    assert t.column("sequence").to_pylist() == ["new", "old", "old"]
    assert t.column("is_night").to_pylist() == [False, None, None]


def test_frames_of_schema_version_1_still_read(tmp_path):
    """Version 1 wrote 10 class counts (free at 9) as a fixed-size list and no
    unclassified_voxels; version 2 (issue 38: class 9 unclassified) 11. Both read as one table."""
    tables.write_partition(tmp_path, "frames", "new", frame_rows(1))
    old = tables.to_table("frames", frame_rows(1)).drop_columns(
        ["class_counts", "unclassified_voxels"]
    )
    old = old.append_column("class_counts", pa.array([list(range(10))], pa.list_(pa.int64(), 10)))
    part = tmp_path / "tables" / "frames" / "sequence=old"
    part.mkdir(parents=True)
    pq.write_table(old, part / "data.parquet")
    t = tables.read_table(tmp_path, "frames")
    assert [len(c) for c in t.column("class_counts").to_pylist()] == [C.NUM_CLASSES, 10]
    assert t.column("unclassified_voxels").to_pylist()[1] is None


def test_no_rows_gives_an_empty_partition(tmp_path):
    """Regression: a sequence with no tracked person wrote no instances table ('track_id' missing)."""
    from storage.tables import read_table, to_table, write_partition

    assert to_table("instances", []).num_rows == 0
    write_partition(tmp_path, "instances", "7", [])
    assert read_table(tmp_path, "instances", "7").num_rows == 0
