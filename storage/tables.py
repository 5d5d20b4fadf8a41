"""Parquet tables of the dataset (frames, instances, sequences), partitioned by sequence.

Layout: ``<root>/tables/<name>/sequence=<seq>/data.parquet``, one file per partition. A partition
is written to a hidden file (``.tmp-*``, skipped by pyarrow / pandas discovery) and renamed onto
``data.parquet`` (:mod:`storage.atomic`): a reader sees the old partition or the new one, never a
mix or an empty directory. Schemas: :mod:`storage.schemas`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.dataset as pads
import pyarrow.parquet as pq

from storage.atomic import move_into_place, write_atomically
from storage.layout import TABLES_DIR, StoreError, check_name
from storage.schemas import PARTITION_FIELD, TABLE_NAMES, dataset_schema, file_schema

PARTITION_FILE = "data.parquet"


def to_table(
    name: str, data: pa.Table | Mapping[str, Any] | Sequence[Mapping[str, Any]]
) -> pa.Table:
    """Conform rows (list of dicts), columns (dict of lists / arrays) or a Table to the schema.

    Missing nullable columns become nulls; unknown columns, missing required ones or values of the
    wrong length raise StoreError. 2D numpy arrays are accepted for list columns (e.g. poses as
    (N, 16) or (N, 4, 4)).
    """
    schema = file_schema(name)
    if isinstance(data, pa.Table):
        columns = {c: data.column(c) for c in data.column_names}
    elif isinstance(data, Mapping):
        columns = dict(data)
    else:
        rows = list(data)
        keys = (
            {k for row in rows for k in row} if rows else set(schema.names)
        )  # no rows: empty table
        columns = {k: [row.get(k) for row in rows] for k in sorted(keys)}
    columns.pop("sequence", None)  # lives in the partition path
    unknown = set(columns) - set(schema.names)
    if unknown:
        raise StoreError(
            f"table {name!r}: unknown columns {sorted(unknown)}, expected {schema.names}"
        )
    lengths = {k: len(v) for k, v in columns.items()}
    if len(set(lengths.values())) > 1:
        raise StoreError(f"table {name!r}: columns differ in length: {lengths}")
    n = next(iter(lengths.values()), 0)
    arrays = []
    for field in schema:
        if field.name not in columns:
            if not field.nullable:
                raise StoreError(f"table {name!r}: required column {field.name!r} missing")
            arrays.append(pa.nulls(n, field.type))
            continue
        value = columns[field.name]
        if isinstance(value, np.ndarray) and value.ndim > 1:
            value = list(value.reshape(len(value), -1))
        try:
            arrays.append(
                pa.array(value, type=field.type)
                if not isinstance(value, (pa.Array, pa.ChunkedArray))
                else value.cast(field.type)
            )
        except (pa.ArrowInvalid, pa.ArrowTypeError, TypeError, ValueError) as exc:
            raise StoreError(
                f"table {name!r}: column {field.name!r} does not fit {field.type}: {exc}"
            ) from exc
    return pa.Table.from_arrays(arrays, schema=schema)


def write_table_file(table: pa.Table, path: Path) -> None:
    # fixed writer settings: same rows -> same bytes (no created_by timestamps in Parquet)
    pq.write_table(table, path, compression="zstd", compression_level=1, write_statistics=True)


def partition_dir(root: str | os.PathLike, name: str, sequence: str) -> Path:
    if name not in TABLE_NAMES:
        raise StoreError(f"unknown table {name!r}, expected one of {TABLE_NAMES}")
    check_name("sequence", sequence)
    return Path(root) / TABLES_DIR / name / f"sequence={sequence}"


def publish_partition(
    root: str | os.PathLike, name: str, sequence: str, source: str | os.PathLike
) -> Path:
    """Move a written Parquet file onto the partition ``name/sequence=<seq>`` atomically."""
    part = partition_dir(root, name, sequence)
    part.mkdir(parents=True, exist_ok=True)
    # one rename on one file system: the staging dir is under root
    return move_into_place(source, part / PARTITION_FILE)


def write_partition(root: str | os.PathLike, name: str, sequence: str, data: Any) -> Path:
    """Write one sequence's partition of table ``name`` now, atomically replacing any old one."""
    target = partition_dir(root, name, sequence) / PARTITION_FILE
    with write_atomically(target) as tmp:
        write_table_file(to_table(name, data), tmp)
    return target


def read_table(
    root: str | os.PathLike, name: str, sequence: str | Sequence[str] | None = None
) -> pa.Table:
    """The table ``name`` (all sequences or the given ones) with the latest schema.

    Sorted by sequence then by the table's natural key (frame / track_id, frame).
    """
    schema = dataset_schema(name)
    base = Path(root) / TABLES_DIR / name
    if not base.is_dir():
        return schema.empty_table()
    dataset = pads.dataset(
        base,
        schema=schema,
        format="parquet",
        partitioning=pads.partitioning(pa.schema([PARTITION_FIELD]), flavor="hive"),
    )
    flt = None
    if sequence is not None:
        wanted = [sequence] if isinstance(sequence, str) else list(sequence)
        flt = pads.field("sequence").isin(wanted)
    table = dataset.to_table(filter=flt)
    keys = {"frames": ["frame"], "instances": ["track_id", "frame"], "sequences": []}[name]
    return table.sort_by([("sequence", "ascending")] + [(k, "ascending") for k in keys])
