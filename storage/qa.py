"""The manual detection QA table: ``OUT/qa/detection_qa.parquet`` (SCHEMA.md, "Manual QA").

One row per mark (tasks.view.qa: T / W on a labelled person, M_vis / M_occ on a missed one), and
one row with ``kind`` null for a frame checked with nobody in it, so the table says which frames
a pass has done and a pass resumes where it stopped. A frame's marks are saved together: the
whole table is rewritten (read, the frame's old rows replaced, written atomically by
storage.atomic) under a file lock, so a reader sees the table before or after a save, never a
part of one, and two viewers on one dataset do not lose each other's frames.

The file carries its schema version (``mobileocc.schema`` = ``detection_qa``,
``mobileocc.schema_version``); a table of another version is refused with one error naming the
file and both versions, and nothing is written over it.
"""

from __future__ import annotations

import fcntl
import os
from collections.abc import Sequence
from contextlib import contextmanager
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from storage.atomic import atomic_write_bytes
from storage.layout import StoreError
from tasks.view.qa import MARK_KINDS, Mark

QA_DIR = "qa"
QA_FILE = "detection_qa.parquet"
QA_SCHEMA_NAME = "detection_qa"
QA_SCHEMA_VERSION = 1


def _f(name: str, t: pa.DataType, doc: str, nullable: bool = True) -> pa.Field:
    return pa.field(name, t, nullable=nullable, metadata={"doc": doc})


QA_SCHEMA = pa.schema(
    [
        _f("sequence", pa.string(), "sequence name", False),
        _f("frame", pa.int32(), "frame index (frames table `frame`)", False),
        _f("raw_frame", pa.int32(), "CODa frame number", False),
        _f("condition", pa.string(), "crowded / uncrowded / night", False),
        _f("kind", pa.string(), "T, W (labelled person), M_vis, M_occ (missed); null: nobody"),
        _f("track_id", pa.int32(), "the labelled person's track id (T / W), null for a miss"),
        _f("u", pa.float32(), "click on cam0, px (misses), null otherwise"),
        _f("v", pa.float32(), "click on cam0, px (misses), null otherwise"),
        _f("box2d_xyxy", pa.list_(pa.float32(), 4), "the labelled person's 2D box when marked, px"),
        _f("occupancy_version", pa.string(), "the published version of the sequence checked"),
        _f("marked_at_ns", pa.int64(), "Unix time of the save, ns", False),
    ]
).with_metadata(
    {"mobileocc.schema": QA_SCHEMA_NAME, "mobileocc.schema_version": str(QA_SCHEMA_VERSION)}
)


class QATableError(StoreError):
    """A QA table that cannot be read or extended (another version, a broken file)."""


def qa_path(out: str | os.PathLike) -> Path:
    return Path(out) / QA_DIR / QA_FILE


def read_qa(out: str | os.PathLike) -> pa.Table:
    """The QA table of the dataset at ``out`` (empty when no pass was saved), sorted by
    (sequence, frame). QATableError names the file when it is of another schema version or not a
    readable QA table."""
    path = qa_path(out)
    if not path.exists():
        return QA_SCHEMA.empty_table()
    try:
        schema = pq.read_schema(path)
    except (OSError, pa.ArrowException) as exc:
        raise QATableError(f"{path}: not a readable Parquet file ({exc})") from exc
    meta = {k.decode(): v.decode() for k, v in (schema.metadata or {}).items()}
    name, version = meta.get("mobileocc.schema"), meta.get("mobileocc.schema_version")
    if name != QA_SCHEMA_NAME:
        raise QATableError(
            f"{path}: not a mobileocc QA table (schema {name!r}, expected {QA_SCHEMA_NAME!r})"
        )
    if version != str(QA_SCHEMA_VERSION):
        older = version is not None and version.isdigit() and int(version) < QA_SCHEMA_VERSION
        raise QATableError(
            f"{path}: QA table of schema version {version}, written by "
            f"{'an older' if older else 'another'} mobileocc; this one reads version "
            f"{QA_SCHEMA_VERSION}. Nothing was changed: move the file aside to start a new pass "
            "(or open it with the mobileocc that wrote it)"
        )
    missing = [f.name for f in QA_SCHEMA if f.name not in schema.names]
    if missing:
        raise QATableError(f"{path}: QA table lacks column(s) {missing}")
    try:
        table = pq.read_table(path).select(QA_SCHEMA.names).cast(QA_SCHEMA)
    except (OSError, pa.ArrowException) as exc:
        raise QATableError(f"{path}: cannot read the QA table ({exc})") from exc
    return table.sort_by([("sequence", "ascending"), ("frame", "ascending")])


def checked_frames(table: pa.Table) -> set[tuple[str, int]]:
    """(sequence, frame) pairs that a QA table holds a verdict for."""
    return set(zip(table.column("sequence").to_pylist(), table.column("frame").to_pylist()))


@contextmanager
def _locked(out: Path):
    folder = Path(out) / QA_DIR
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / ".lock", "a+b") as fh:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


def save_frame(
    out: str | os.PathLike,
    sequence: str,
    frame: int,
    raw_frame: int,
    condition: str,
    marks: Sequence[Mark],
    boxes: dict[int, Sequence[float]],
    occupancy_version: str | None,
    marked_at_ns: int,
) -> Path:
    """Save one frame's verdict (replacing any earlier one of that frame); returns the file.

    marks: the frame's marks, checked beforehand (tasks.view.qa.check_marks); boxes: track id ->
    its 2D box (x0, y0, x1, y1) px, kept beside T / W marks. An empty ``marks`` records the frame
    as checked with nobody in it."""
    out = Path(out)
    rows = [
        {
            "kind": m.kind,
            "track_id": None if m.track_id is None else int(m.track_id),
            "u": m.u,
            "v": m.v,
            "box2d_xyxy": (
                [float(x) for x in boxes[int(m.track_id)]]
                if m.track_id is not None and int(m.track_id) in boxes
                else None
            ),
        }
        for m in marks
    ] or [{"kind": None, "track_id": None, "u": None, "v": None, "box2d_xyxy": None}]
    for r in rows:
        if r["kind"] is not None and r["kind"] not in MARK_KINDS:
            raise QATableError(f"sequence {sequence} frame {frame}: mark kind {r['kind']!r}")
        r.update(
            sequence=str(sequence),
            frame=int(frame),
            raw_frame=int(raw_frame),
            condition=str(condition),
            occupancy_version=occupancy_version,
            marked_at_ns=int(marked_at_ns),
        )
    new = pa.Table.from_pylist(rows, schema=QA_SCHEMA)
    with _locked(out):
        old = read_qa(out)  # refuses another version before anything is written
        keep = [
            i
            for i, (s, f) in enumerate(
                zip(old.column("sequence").to_pylist(), old.column("frame").to_pylist())
            )
            if not (s == str(sequence) and f == int(frame))
        ]
        table = pa.concat_tables([old.take(pa.array(keep, pa.int64())), new]).sort_by(
            [("sequence", "ascending"), ("frame", "ascending")]
        )
        sink = pa.BufferOutputStream()
        pq.write_table(table, sink, compression="zstd", compression_level=1)
        path = qa_path(out)
        atomic_write_bytes(path, sink.getvalue().to_pybytes())
    return path
