"""Zarr occupancy store: round-trips, chunk-aligned concurrent writes, atomic publication, npz."""

from __future__ import annotations

import hashlib
import json
import multiprocessing
import os
import zipfile
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest
import zarr

from storage import occupancy_store as occ
from storage import publish as pub
from storage.dataset import open_dataset
from storage.manifest import sweep_temporaries
from storage.npzio import save_npz_deterministic
from tasks import conventions as C
from tasks.conventions import FREE

GRID = (12, 10, 6)
ATTRS = {
    "range_min": [0.4, -4.8, -1.0],
    "range_max": [10.0, 4.8, 3.8],
    "voxel_size_m": 0.2,
    "config_hash": "c0",
}


def make_frames(n: int, grid=GRID, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    sem = np.full((n, *grid), FREE, np.uint8)
    sem[:, :, :, 0] = 4  # ground plane of road
    sem[:, 2:4, 3:5, 1:4] = rng.integers(0, 9, size=(n, 2, 2, 3), dtype=np.uint8)
    inst = np.zeros((n, *grid), np.uint16)
    inst[:, 2:4, 3:5, 1:4] = 300 + np.arange(n, dtype=np.uint16)[:, None, None, None]
    mask = np.zeros((n, *grid), np.uint8)
    mask[:, : grid[0] // 2] = 1
    vel = np.zeros((n, *grid, 2), np.float16)
    vel[:, 2:4, 3:5, 1:4] = (1.25, -0.5)
    return {
        "semantics": sem,
        "instances": inst,
        "mask_lidar": mask,
        "mask_camera": mask * 0 + mask,
        "velocity": vel,
    }


def test_round_trip_attrs_and_metadata(tmp_path):
    path = tmp_path / "s.zarr"
    layout = occ.create_store(path, 7, GRID, 3, ATTRS)
    assert layout.frames_per_chunk == 3 and not layout.sharded
    assert layout.chunk_shape == (3, *GRID)
    assert layout.write_units() == [(0, 3), (3, 6), (6, 7)]
    data = make_frames(7)
    occ.write_frames(path, 0, {k: v[:3] for k, v in data.items()})
    occ.write_frames(path, 3, {k: v[3:6] for k, v in data.items()})
    occ.write_frames(path, 6, {k: v[6:] for k, v in data.items()})  # last partial unit
    back = occ.read_frames(path)
    for name, value in data.items():
        assert back[name].dtype == value.dtype
        np.testing.assert_array_equal(back[name], value)
    np.testing.assert_array_equal(occ.read_frames(path, 4)["instances"], data["instances"][4:5])
    attrs = occ.read_attrs(path)
    assert (
        attrs["voxel_size_m"] == 0.2
        and attrs["frame"] == "base"
        and attrs["class_names"][C.FREE] == "free"
    )
    assert attrs["skip_empty_chunks"] is False  # coarse default: a 3-frame chunk is never all fill
    # another tool opens it directly, with dimension names and zstd in the metadata
    meta = json.loads((path / "velocity" / "zarr.json").read_text())
    assert meta["dimension_names"] == ["frame", "x", "y", "z", "component"]
    assert meta["data_type"] == "float16"
    assert any(c["name"] == "zstd" and c["configuration"]["level"] == 1 for c in meta["codecs"])
    assert zarr.open_array(str(path / "semantics"), mode="r").fill_value == FREE


def test_unwritten_frames_read_as_fill_values(tmp_path):
    path = tmp_path / "s.zarr"
    occ.create_store(path, 4, GRID, 2, ATTRS)
    back = occ.read_frames(path, slice(2, 4))
    assert (back["semantics"] == FREE).all() and (back["mask_camera"] == 0).all()
    assert not any((path / "semantics" / "c").glob("**/*")), "nothing stored for fill-value chunks"


@pytest.mark.parametrize("start,n", [(1, 2), (0, 1), (2, 1), (4, 2), (-2, 2)])
def test_misaligned_or_out_of_range_write_fails(tmp_path, start, n):
    path = tmp_path / "s.zarr"
    occ.create_store(path, 5, GRID, 2, ATTRS)
    data = make_frames(n)
    with pytest.raises(occ.StoreError, match=r"aligned|outside"):
        occ.write_frames(path, start, {"semantics": data["semantics"]})


def test_bad_shape_dtype_and_name_fail(tmp_path):
    path = tmp_path / "s.zarr"
    occ.create_store(path, 2, GRID, 2, ATTRS)
    with pytest.raises(occ.StoreError, match="shape"):
        occ.write_frames(path, 0, {"semantics": np.zeros((2, 12, 10, 5), np.uint8)})
    with pytest.raises(occ.StoreError, match="dtype"):
        occ.write_frames(path, 0, {"semantics": np.zeros((2, *GRID), np.int64)})
    with pytest.raises(occ.StoreError, match="unknown array"):
        occ.write_frames(path, 0, {"labels": np.zeros((2, *GRID), np.uint8)})
    with pytest.raises(occ.StoreError, match="zarr.json missing"):
        occ.read_frames(tmp_path / "nothing.zarr")


def test_fine_grid_uses_shards_and_optionally_skips_empty_chunks(tmp_path):
    grid = (160, 160, 80)  # 2 MB per uint8 frame: the fine-grid path
    sem = np.full((1, *grid), FREE, np.uint8)
    sem[0, :, :, 0] = 4
    sizes = {}
    for skip in (False, True):
        path = tmp_path / f"fine-{skip}.zarr"
        layout = occ.create_store(path, 3, grid, 1, ATTRS, skip_empty_chunks=skip)
        assert layout.sharded and layout.chunk_shape == (1, 160, 160, 40)
        occ.write_frames(path, 1, {"semantics": sem})
        occ.write_frames(path, 2, {"semantics": np.full((1, *grid), FREE, np.uint8)})  # all free
        back = occ.read_frames(path, slice(0, 3), ("semantics",))["semantics"]
        np.testing.assert_array_equal(back[1:2], sem)
        assert (back[[0, 2]] == FREE).all()
        files = sorted(p.name for p in (path / "semantics" / "c").iterdir())
        # frame 0 never written: no shard; frame 2 all free: a shard only without skipping
        assert files == (["1"] if skip else ["1", "2"])
        sizes[skip] = (path / "semantics" / "c" / "1" / "0" / "0" / "0").stat().st_size
    assert sizes[True] < sizes[False] < 20_000
    occ.create_store(tmp_path / "default.zarr", 1, grid, 1, ATTRS)
    assert (
        occ.read_attrs(tmp_path / "default.zarr")["skip_empty_chunks"] is False
    )  # measured default


def test_chunk_choice():
    assert occ.choose_chunks((48, 48, 24), 50) == ((50, 48, 48, 24), False)
    assert occ.choose_chunks((480, 480, 240), 1) == ((1, 240, 240, 15), True)
    # 0.1 m grid, 100 frames per unit: 44 MB would be one chunk; 10-frame chunks in the shard
    assert occ.choose_chunks((96, 96, 48), 100) == ((10, 96, 96, 48), True)


def _write_unit(args):
    path, start, stop, seed = args
    data = make_frames(stop - start, seed=seed + start)
    occ.write_frames(path, start, data)
    return start


def test_concurrent_process_writers_equal_one_writer(tmp_path):
    n, fpc = 10, 2
    one, many = tmp_path / "one.zarr", tmp_path / "many.zarr"
    layout = occ.create_store(one, n, GRID, fpc, ATTRS)
    occ.create_store(many, n, GRID, fpc, ATTRS)
    jobs = [(str(one), s, e, 0) for s, e in layout.write_units()]
    for job in jobs:
        _write_unit(job)
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=2, mp_context=ctx) as pool:
        done = list(
            pool.map(_write_unit, [(str(many), s, e, 0) for s, e in reversed(layout.write_units())])
        )
    assert sorted(done) == [0, 2, 4, 6, 8]
    a, b = occ.read_frames(one), occ.read_frames(many)
    for name in a:
        np.testing.assert_array_equal(a[name], b[name])
    assert (a["instances"][:, 2, 3, 1] == 300 + np.array([0, 1, 0, 1, 0, 1, 0, 1, 0, 1])).all()


def _publish(root, seq, version, value, n=4):
    with pub.sequence_writer(root, seq, version) as staged:
        occ.create_store(staged.store_path, n, GRID, 2, ATTRS)
        sem = np.full((n, *GRID), value, np.uint8)
        occ.write_frames(staged.store_path, 0, {"semantics": sem})


def test_interrupted_write_leaves_previous_version_readable(tmp_path):
    _publish(tmp_path, "seq0", "v1", 3)
    staged = pub.stage_sequence(tmp_path, "seq0", "v2")
    occ.create_store(staged.store_path, 4, GRID, 2, ATTRS)
    occ.write_frames(staged.store_path, 0, {"semantics": np.full((2, *GRID), 7, np.uint8)})
    # "crash" here: no publish. Readers still see v1 only, and the staging dir is invisible.
    ds = open_dataset(tmp_path)
    assert ds.sequences == ("seq0",)
    assert ds.store_path("seq0").name == "v1.zarr"
    assert (ds.arrays("seq0", lazy="zarr")["semantics"][:] == 3).all()
    assert (ds.arrays("seq0")["semantics"].compute() == 3).all()
    assert sweep_temporaries(tmp_path) == 1 and not staged.staging_dir.exists()  # the next run's
    # a write that raises inside the context manager is discarded, v1 stays
    with pytest.raises(RuntimeError):
        with pub.sequence_writer(tmp_path, "seq0", "v3") as staged3:
            occ.create_store(staged3.store_path, 4, GRID, 2, ATTRS)
            raise RuntimeError("worker died")
    assert not staged3.staging_dir.exists()
    assert open_dataset(tmp_path).store_path("seq0").name == "v1.zarr"
    # publishing v2 switches readers over and removes v1
    _publish(tmp_path, "seq0", "v2", 5)
    ds = open_dataset(tmp_path)
    assert ds.store_path("seq0").name == "v2.zarr"
    assert (occ.read_frames(ds.store_path("seq0"))["semantics"] == 5).all()
    assert not (tmp_path / "occupancy" / "seq0" / "v1.zarr").exists()
    # republishing the same version replaces it
    _publish(tmp_path, "seq0", "v2", 6)
    assert (occ.read_frames(open_dataset(tmp_path).store_path("seq0"))["semantics"] == 6).all()
    assert not [p for p in tmp_path.rglob(".tmp-*")]


def test_bad_names_refused(tmp_path):
    for bad in ("", ".x", "a/b", "a=b"):
        with pytest.raises(occ.StoreError):
            pub.stage_sequence(tmp_path, bad, "v1")
    with pytest.raises(occ.StoreError, match="not a staging"):
        pub.discard(tmp_path / "occupancy")


def test_npz_deterministic_and_loadable(tmp_path):
    sem = np.arange(24, dtype=np.uint8).reshape(2, 3, 4)
    a = save_npz_deterministic(tmp_path / "a" / "labels.npz", semantics=sem, mask=sem > 3)
    b = save_npz_deterministic(tmp_path / "b" / "labels.npz", semantics=sem, mask=sem > 3)
    assert hashlib.sha256(a.read_bytes()).digest() == hashlib.sha256(b.read_bytes()).digest()
    with np.load(a) as f:
        assert f.files == ["semantics", "mask"]
        np.testing.assert_array_equal(f["semantics"], sem)
        assert f["mask"].dtype == bool
    with zipfile.ZipFile(a) as zf:
        assert all(i.date_time == (1980, 1, 1, 0, 0, 0) for i in zf.infolist())
    raw = save_npz_deterministic(tmp_path / "raw.npz", compressed=False, x=sem)
    assert raw.stat().st_size > a.stat().st_size - 1000
    with pytest.raises(ValueError, match="object"):
        save_npz_deterministic(tmp_path / "o.npz", x=np.array([None]))


class _Killed(BaseException):
    """Stands for a SIGKILL at a rename: nothing after it runs (no handler catches it)."""


def _stage_with_tables(root, seq, version, value):
    staged = pub.stage_sequence(root, seq, version)
    occ.create_store(staged.store_path, 4, GRID, 2, ATTRS)
    occ.write_frames(staged.store_path, 0, {"semantics": np.full((4, *GRID), value, np.uint8)})
    pub.stage_table(staged, "frames", _frame_rows(value))
    pub.stage_table(staged, "sequences", [_sequence_row(version)])
    return staged


def _publish_with_tables(root, seq, version, value):
    pub.publish_sequence(_stage_with_tables(root, seq, version, value))


def _counting_renames(monkeypatch, kill_at: int = 0) -> list[int]:
    """Count os.replace calls from now on; raise _Killed at the ``kill_at``-th."""
    real, count = os.replace, [0]

    def replace(src, dst):
        count[0] += 1
        if count[0] == kill_at:
            raise _Killed
        return real(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    return count


def _frame_rows(value):
    return [
        {
            "frame": k,
            "raw_frame": 2 * k,
            "stamp_ns": value * 1000 + k,
            "T_world_from_lidar": [0.0] * 16,
        }
        for k in range(4)
    ]


def _sequence_row(version):
    return {"fingerprint": "f", "config_hash": "c", "code_version": "1", "status": "ok",
            "num_frames": 4, "occupancy_version": version}  # fmt: skip


def _seen(root):
    """(version, semantics value, frames stamp value, sequences row version) a reader sees."""
    from storage.tables import read_table

    ds = open_dataset(root)
    value = int(occ.read_frames(ds.store_path("seq0"))["semantics"].max())
    stamp = read_table(root, "frames", "seq0").column("stamp_ns").to_pylist()[0] // 1000
    row = read_table(root, "sequences", "seq0").column("occupancy_version").to_pylist()
    return ds.store_path("seq0").stem, value, stamp, row


#: the renames of publish_sequence replacing v1 by v2: intent, store, two partitions,
#: current.json, v1 moved aside (test_the_publication_steps_are_counted keeps this true)
PUBLICATION_RENAMES = 6


def test_the_publication_steps_are_counted(tmp_path, monkeypatch):
    _publish_with_tables(tmp_path, "seq0", "v1", 3)
    staged = _stage_with_tables(tmp_path, "seq0", "v2", 5)
    count = _counting_renames(monkeypatch)
    pub.publish_sequence(staged)
    assert count[0] == PUBLICATION_RENAMES


@pytest.mark.parametrize("step", range(1, PUBLICATION_RENAMES + 1))
def test_a_publication_killed_at_any_rename_is_completed_by_the_next_reader(
    step, tmp_path, monkeypatch
):
    """Every rename of a publication (intent, store, partitions, current.json, old version):
    after a "kill" there, readers are refused until the publication is completed, and
    storage.publish.reading completes it: v2 whole, never v1's arrays with v2's tables."""
    _publish_with_tables(tmp_path, "seq0", "v1", 3)
    assert _seen(tmp_path) == ("v1", 3, 3, ["v1"])
    staged = _stage_with_tables(tmp_path, "seq0", "v2", 5)
    real = os.replace
    _counting_renames(monkeypatch, kill_at=step)
    with pytest.raises(_Killed):
        pub.publish_sequence(staged)
    monkeypatch.setattr(os, "replace", real)
    if step == 1:  # before the intent: nothing changed
        assert not pub.pending_publications(tmp_path) and _seen(tmp_path)[0] == "v1"
    else:  # the intent is there: readers are refused until it is completed
        with pytest.raises(occ.StoreError, match="was interrupted by a killed run"):
            open_dataset(tmp_path)
    with pub.reading(tmp_path):
        seen = _seen(tmp_path)
    assert seen == (("v1", 3, 3, ["v1"]) if step == 1 else ("v2", 5, 5, ["v2"])), (step, seen)
    assert not pub.pending_publications(tmp_path)
    assert pub.check_publication(tmp_path, "seq0", seen[0], deep=True) == ""
    assert not (tmp_path / "occupancy" / "seq0" / ("v1.zarr" if step > 1 else "v2.zarr")).exists()


def test_check_publication_names_what_is_wrong(tmp_path):
    _publish_with_tables(tmp_path, "seq0", "v1", 3)
    assert pub.check_publication(tmp_path, "seq0", "v1", deep=True) == ""
    assert "names version 'v1'" in pub.check_publication(tmp_path, "seq0", "v2")
    part = tmp_path / "tables/frames/sequence=seq0/data.parquet"
    data = part.read_bytes()
    part.unlink()
    assert pub.check_publication(tmp_path, "seq0", "v1") == f"{part} is missing"
    part.write_bytes(data[:-1] + bytes([data[-1] ^ 1]))  # same size, other content
    assert pub.check_publication(tmp_path, "seq0", "v1") == ""
    assert "does not hold what was written" in pub.check_publication(
        tmp_path, "seq0", "v1", deep=True
    )
    (tmp_path / "occupancy/seq0/current.json").write_text("{")
    assert "cannot be read" in pub.check_publication(tmp_path, "seq0", "v1")


def test_completion_records(tmp_path):
    from storage.completion import check_record, write_record

    folder = tmp_path / "unit"
    (folder / "sub").mkdir(parents=True)
    (folder / "a.npz").write_bytes(b"abc")
    (folder / "sub" / "b.npz").write_bytes(b"defg")
    files = write_record(folder, stage="fit", sequence="0", key="k")
    assert sorted(files) == ["a.npz", "sub/b.npz"] and files["a.npz"][0] == 3
    assert check_record(folder, deep=True) == ""
    (folder / "a.npz").unlink()
    (folder / "a.npz").write_bytes(b"abd")
    assert check_record(folder) == ""  # the quick check sees sizes only
    assert "does not hold what was written" in check_record(folder, deep=True)
    (folder / "sub" / "b.npz").write_bytes(b"de")
    assert check_record(folder).endswith("b.npz is 2 bytes, 4 were written")
    (folder / "complete.json").unlink()
    assert "complete.json is missing" in check_record(folder)
    assert "is missing" in check_record(tmp_path / "nowhere")
