"""Robot logs end to end: the same simulated scene as a CODa tree, as a ROS 2 MCAP log (poses on
/tf) and as a ROS 1 bag (poses as nav_msgs/Odometry) gives the same published labels, byte for
byte; the planner's stat memo works for logs (an untouched log plans nothing, a changed one
reruns its sequence only)."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from configs.schema import ORACLE_CONFIG, load_config
from flows.pipeline.units import run_units, summary_table

pytestmark = [pytest.mark.slow]

#: cheap settings: the comparison is between formats, not about the products' quality
CHEAP = {
    "fit.iterations": 2,
    "dataset.max_range_m": 15.0,
    "map.voxel_size_m": 0.4,
    "map.freespace.voxel_size_m": 0.4,
    "map.freespace.max_range_m": 15.0,
    "fuse.grid.voxel_size_m": 0.4,
    "export.formats": ["occ3d"],
}


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """One simulated scene (1 sequence, 4 raw frames = 2 frames at 5 Hz, 3 people) written as a
    CODa tree, an MCAP log and a ROS 1 bag, each run through the pipeline."""
    from flows.commands.simulate import simulate

    root = tmp_path_factory.mktemp("scenes")
    outs = {}
    for fmt in ("coda", "mcap", "ros1"):
        data = root / fmt
        simulate(data, 1, 4, seed=5, pedestrians=3, progress=False, fast=True, fmt=fmt)
        out = root / f"out-{fmt}"
        report = run_units(
            load_config(
                ORACLE_CONFIG,
                overrides={"dataset.root": str(data), "output.root": str(out), **CHEAP},
            ),
            progress=False,
        )
        assert report.exit_code == 0, summary_table(report)
        outs[fmt] = out
    return outs


def _labels(out: Path) -> dict[str, bytes]:
    """Every array file of the sequence's occupancy store (chunks and array metadata) and every
    Occ3D labels.npz, by path (the store's folder is named by its stage key: left out)."""
    [store] = [p for p in (out / "occupancy" / "0").iterdir() if p.suffix == ".zarr"]
    files = {
        f"occupancy/{p.relative_to(store).as_posix()}": p.read_bytes()
        for p in sorted(store.rglob("*"))
        if p.is_file() and p.relative_to(store).as_posix() != "zarr.json"
    }
    # by sample token: the scene folder is the log's own name for a log, coda-<SEQ> for a tree
    for p in sorted((out / "exports" / "occ3d" / "gts").rglob("labels.npz")):
        files[f"occ3d/gts/{p.parent.name}/labels.npz"] = p.read_bytes()
    return files


def _rows(out: Path, table: str) -> list[dict]:
    return pq.read_table(out / "tables" / table / "sequence=0" / "data.parquet").to_pylist()


@pytest.mark.parametrize("fmt", ["mcap", "ros1"])
def test_a_log_gives_the_labels_of_the_same_scene_as_a_coda_tree(scenes, fmt):
    coda, log = scenes["coda"], scenes[fmt]
    labels = _labels(coda)
    assert len(labels) >= 7 and any(k.endswith("labels.npz") for k in labels)
    assert _labels(log) == labels  # byte for byte
    [store_a] = (coda / "occupancy" / "0").glob("*.zarr")
    [store_b] = (log / "occupancy" / "0").glob("*.zarr")
    attrs = [json.loads((s / "zarr.json").read_text())["attributes"] for s in (store_a, store_b)]
    assert {k for k in attrs[0] if attrs[0][k] != attrs[1].get(k)} == {"stage_key"}
    assert _rows(log, "instances") == _rows(coda, "instances")
    # frames: the same but where the raw data are (a file of the tree, a message of the log)
    where = ("lidar_path", "cam0_path", "cam1_path")
    frames_a, frames_b = _rows(coda, "frames"), _rows(log, "frames")
    assert [{k: v for k, v in r.items() if k not in where} for r in frames_b] == [
        {k: v for k, v in r.items() if k not in where} for r in frames_a
    ]
    assert frames_b[0]["lidar_path"] == f"0.{'bag' if fmt == 'ros1' else 'mcap'}#/ouster/points@0"
    seq_a, seq_b = _rows(coda, "sequences")[0], _rows(log, "sequences")[0]
    for k in ("K", "T_base_from_lidar", "image_width", "image_height", "num_frames", "status"):
        assert seq_a[k] == seq_b[k], k
    # the camera extrinsic went through a quaternion on /tf_static: equal to ~1e-16
    assert (
        max(abs(a - b) for a, b in zip(seq_a["T_cam0_from_lidar"], seq_b["T_cam0_from_lidar"]))
        < 1e-12
    )


def test_the_planner_memo_works_for_logs(scenes, tmp_path):
    """An untouched log plans from its stat memo (nothing read, nothing run); a rewritten one
    reruns; the folder of logs lists each log as a sequence."""
    from flows.pipeline.plan import plan_run, selected_sequences
    from storage.manifest import FingerprintCache, Manifest

    data = tmp_path / "logs"
    data.mkdir()
    os.link(scenes["mcap"].parent / "mcap" / "0.mcap", data / "0.mcap")
    shutil.copytree(scenes["mcap"].parent / "mcap" / "gt", data / "gt", copy_function=os.link)
    out = tmp_path / "out"
    shutil.copytree(scenes["mcap"], out, symlinks=True)
    cfg = load_config(
        ORACLE_CONFIG, overrides={"dataset.root": str(data), "output.root": str(out), **CHEAP}
    )
    assert selected_sequences(cfg) == ["0"]
    cache = FingerprintCache(out / ".cache" / "sequences")
    [first] = plan_run(cfg, Manifest.load(out), cache)
    assert not first.error and all(u.fresh for u in first.units.values()), first
    [again] = plan_run(cfg, Manifest.load(out), FingerprintCache(out / ".cache" / "sequences"))
    assert again.memo_hit and all(u.fresh for u in again.units.values())
    # the same log written again (a new inode and mtime, the same bytes): read, same fingerprint
    shutil.copyfile(data / "0.mcap", data / "0.tmp")
    os.replace(data / "0.tmp", data / "0.mcap")
    [copy] = plan_run(cfg, Manifest.load(out), FingerprintCache(out / ".cache" / "sequences"))
    assert not copy.memo_hit and copy.fingerprint == first.fingerprint
    # a changed log (its first sweep dropped; still a whole MCAP file): its sequence reruns from
    # detect. Bytes appended to the file would make it a cut MCAP, an error of its own.
    from tests.log_fixture import rewrite_log

    dropped: list[int] = []

    def drop_first_sweep(topic, msgtype, msg, log_ns):
        if msgtype.endswith("PointCloud2") and not dropped:
            dropped.append(log_ns)
            return []
        return None

    rewrite_log(data / "0.mcap", data / "0.mcap", drop_first_sweep)
    assert dropped
    [changed] = plan_run(cfg, Manifest.load(out), FingerprintCache(out / ".cache" / "sequences"))
    assert changed.fingerprint != first.fingerprint
    assert changed.units["detect"].reason == "input files changed"


def test_exports_name_a_logs_scene_and_images_as_the_log_has_them(scenes, tmp_path):
    """Issue 38: a log's Occ3D scene had a ``coda-`` prefix and its img_path no extension; the
    scene is the log's own name and img_path the file the nuScenes export writes."""
    from flows import cli

    occ = json.loads((scenes["coda"] / "exports/occ3d/annotations.json").read_text())
    assert list(occ["scene_infos"]) == occ["train_split"] == ["coda-0"]
    for fmt in ("mcap", "ros1"):
        out = scenes[fmt]
        occ = json.loads((out / "exports/occ3d/annotations.json").read_text())
        assert list(occ["scene_infos"]) == occ["train_split"] == ["0"], fmt
        assert (out / "exports/occ3d/gts/0").is_dir()
        paths = [
            s["camera_sensor"]["CAM_FRONT"]["img_path"] for s in occ["scene_infos"]["0"].values()
        ]
        assert len(paths) == 2 and all(p.startswith("samples/CAM_FRONT/0__") for p in paths)
        nus = tmp_path / f"nus-{fmt}"
        assert (
            cli.main(["export", "--out", str(out), "--format", "nuscenes", "--to", str(nus)]) == 0
        )
        written = sorted(
            p.relative_to(nus).as_posix() for p in (nus / "samples/CAM_FRONT").iterdir()
        )
        assert written == sorted(paths), (written, paths)  # the same names, extensions included
        scenes_table = json.loads(next(nus.rglob("scene.json")).read_text())
        assert [s["name"] for s in scenes_table] == ["0"]


def test_show_draws_a_log_and_a_dataset_built_from_one(scenes, tmp_path, capsys):
    """Issue 38: `show` on a log-built dataset ended in a traceback (it took only ROOT/gt/SEQ)."""
    from PIL import Image

    from flows import cli

    log = scenes["mcap"].parent / "mcap" / "0.mcap"
    for i, (path, more) in enumerate(
        [(scenes["mcap"], ["--frame", "1"]), (log, ["--frame", "1"]), (log.parent, [])]
    ):
        png = tmp_path / f"{i}.png"
        assert cli.main(["show", str(path), "--png", str(png), *more]) == 0
        with Image.open(png) as im:
            picture = np.asarray(im.convert("RGB"))
        # the bird's-eye view (left) is not blank: labels or returns drawn over white
        assert (
            picture.shape[1] > picture.shape[0]
            and (picture[:, : picture.shape[0] // 2] != 255).any()
        )
    capsys.readouterr()
    assert cli.main(["show", str(log), "--frame", "7", "--png", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err
    assert "no frame 7" in err and "0..1" in err and "Traceback" not in err
    assert cli.main(["show", str(tmp_path), "--png", str(tmp_path / "x.png")]) == 2
