"""Small flows under Prefect's test harness: thread and Dask process runners, the stage cache,
failure isolation and the run lock."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from configs.schema import ORACLE_CONFIG, load_config
from flows.pipeline.dag import STAGES
from flows.pipeline.run import rebuild_dataset
from storage.manifest import Manifest, StoreLockedError, run_lock
from storage.schemas import TABLE_NAMES
from storage.tables import read_table

pytestmark = [pytest.mark.usefixtures("prefect_harness"), pytest.mark.xdist_group("prefect")]


def _config(data: Path, out: Path, **overrides):
    # few fit iterations: these tests are about orchestration, not fit quality
    return load_config(
        ORACLE_CONFIG,
        overrides={
            "dataset.root": str(data),
            "output.root": str(out),
            "fit.iterations": 5,
            **overrides,
        },
    )


def _run(cfg, **kw):
    return rebuild_dataset(cfg, progress=False, **kw)


def _ran(report) -> set[tuple[str, str]]:
    return {k for k, o in report.outcomes.items() if o.ran}


@pytest.fixture()
def dataset(copy_dataset):
    return copy_dataset()


def test_thread_runner_and_cache_consequences(dataset, tmp_path):
    out = tmp_path / "out"
    cfg = _config(dataset, out)
    first = _run(cfg)
    assert _ran(first) == {(s, st) for s in ("0", "1") for st in STAGES}
    assert all(o.status == "done" for o in first.outcomes.values())
    # every stage says plainly whether it computes its product yet
    assert all("implemented" in o.summary for o in first.outcomes.values())
    # the published instances carry the fitted bodies (regression: the export left the 3D boxes
    # empty, so the nuScenes export had no pedestrian annotations)
    inst = read_table(out, "instances").to_pandas().dropna(subset=["box3d_center"])
    assert len(inst) > 0 and all(1.0 < size[2] < 2.2 for size in inst["box3d_size"])
    # every declared column is written by the pipeline (the error column: only for a failure)
    for name in TABLE_NAMES:
        table = read_table(out, name)
        never = [c for c in table.column_names if table[c].null_count == len(table)]
        assert never == (["error"] if name == "sequences" else []), (name, never)

    # nothing changed -> nothing recomputed
    assert _ran(_run(cfg)) == set()

    # one sequence's files edited -> only that sequence runs
    bin_path = dataset / "3d_comp/os1/1/3d_comp_os1_1_2.bin"
    raw = bytearray(bin_path.read_bytes())
    raw[-8:-4] = bytes([0, 0, 192, 63])  # one intensity value becomes 1.5
    bin_path.write_bytes(bytes(raw))
    assert _ran(_run(cfg)) == {("1", st) for st in STAGES}

    # a fuse-only setting changed -> only fuse and export run
    finer = _config(dataset, out, **{"fuse.grid.voxel_size_m": 0.1})
    assert _ran(_run(finer)) == {(s, st) for s in ("0", "1") for st in ("fuse", "export")}

    # a stage's output deleted -> that stage and what depends on it run again
    manifest = Manifest.load(out)
    shutil.rmtree(out / manifest.get("0", "map").location)
    assert _ran(_run(finer)) == {("0", "map"), ("0", "fuse"), ("0", "export")}

    # a sequence added -> only it runs
    for sub in (
        "3d_comp/os1",
        "2d_rect/cam0",
        "2d_rect/cam1",
        "3d_bbox/os1",
        "3d_semantic/os1",
        "calibrations",
        "gt",
    ):
        src = dataset / sub / "1"
        dst = dataset / sub / "2"
        shutil.copytree(src, dst)
        for f in sorted(dst.rglob("*_1_*")):
            f.rename(f.with_name(f.name.replace("_1_", "_2_")))
    for sub, ext in (("timestamps", "txt"), ("poses/dense_global", "txt"), ("metadata", "json")):
        shutil.copy(dataset / sub / f"1.{ext}", dataset / sub / f"2.{ext}")
    assert _ran(_run(finer)) == {("2", st) for st in STAGES}


def test_bad_sequence_fails_alone(dataset, tmp_path):
    out = tmp_path / "out"
    path = dataset / "3d_comp/os1/0/3d_comp_os1_0_2.bin"
    path.write_bytes(path.read_bytes()[:1000])
    # any bad frame fails the sequence here (the default leaves up to half its frames out:
    # tests/test_faults.py, test_a_bad_frame_is_left_out_and_the_sequence_goes_on)
    report = _run(_config(dataset, out, **{"detect.max_failed_frame_share": 0}))
    failed = report.failed
    assert [(o.sequence, o.stage) for o in failed] == [("0", "detect")]
    assert "3d_comp_os1_0_2.bin (frame 2)" in failed[0].error and "truncated" in failed[0].error
    assert all(report.outcomes[("1", st)].status == "done" for st in STAGES)
    assert report.outcomes[("0", "fuse")].status == "skipped"
    manifest = Manifest.load(out)
    assert manifest.get("0", "detect").status == "failed"
    assert "truncated" in manifest.get("0", "detect").error
    assert manifest.get("1", "export").status == "done"


def test_unknown_sequence_is_recorded(dataset, tmp_path):
    cfg = _config(dataset, tmp_path / "out", **{"dataset.sequences": ["1", "9"]})
    report = _run(cfg)
    assert report.outcomes[("9", "detect")].status == "failed"
    assert "unknown sequence id '9'" in report.outcomes[("9", "detect")].error
    assert report.outcomes[("1", "export")].status == "done"


def test_second_run_on_same_store_is_refused(dataset, tmp_path):
    out = tmp_path / "out"
    with run_lock(out):
        with pytest.raises(StoreLockedError, match="is in use by another run"):
            _run(_config(dataset, out))


def test_dask_process_runner_matches_thread_runner(dataset, tmp_path):
    threads = _run(_config(dataset, tmp_path / "a"))
    dask = _run(_config(dataset, tmp_path / "b", **{"dask.runner": "dask", "dask.workers": 2}))
    assert {k: o.status for k, o in dask.outcomes.items()} == {
        k: o.status for k, o in threads.outcomes.items()
    }
    ma, mb = Manifest.load(tmp_path / "a"), Manifest.load(tmp_path / "b")
    assert {k: r.key for k, r in ma.rows.items()} == {k: r.key for k, r in mb.rows.items()}
    for (seq, stage), rec in ma.rows.items():
        a = (tmp_path / "a" / rec.location / "summary.json").read_text()
        b = (tmp_path / "b" / mb.get(seq, stage).location / "summary.json").read_text()
        assert json.loads(a) == json.loads(b)


def test_precomputed_cliff_estimates_written_from_the_oracle_fit_like_the_oracle(dataset, tmp_path):
    import numpy as np
    import torch

    from flows.pipeline.inputs import fit_inputs, sequence_ref, source
    from flows.stages.common import body_model
    from flows.stages.providers import init_provider
    from storage.cliff_files import cliff_path, write_cliff_estimates
    from storage.products import Bodies, Tracks
    from tasks.body.rotations import axis_angle_to_matrix
    from tasks.fit.init_oracle import params_to_cliff_camera

    oracle_cfg = _config(dataset, tmp_path / "oracle", **{"fit.batch_persons": 2})
    assert all(o.status == "done" for o in _run(oracle_cfg).outcomes.values())
    init_dir = tmp_path / "cliff"
    few = {}
    for seq in ("0", "1"):
        (folder,) = (tmp_path / "oracle" / "stages" / "track" / seq).iterdir()
        typed = Tracks.read(folder)
        tracks = typed.arrays()
        enough = tracks["points_in_image"] >= oracle_cfg.fit.min_points  # others are not fitted
        rows = np.flatnonzero((tracks["gt_index"] >= 0) & enough)
        few[seq] = int(((tracks["gt_index"] >= 0) & ~enough).sum())
        opened = source(oracle_cfg).open(sequence_ref(oracle_cfg, seq))
        provider = init_provider(
            fit_inputs(oracle_cfg).init,
            opened,
            body_model(fit_inputs(oracle_cfg).body, tmp_path / "oracle"),
            opened.info.calibration.cameras[oracle_cfg.dataset.camera],
        )
        est = provider.estimates(typed, rows)  # the stage asks for a sequence's rows at once
        go, bp, tr, betas = (
            getattr(est, k) for k in ("global_orient", "body_pose", "transl", "betas")
        )
        rot = axis_angle_to_matrix(
            torch.as_tensor(
                np.concatenate([go[:, None], bp.reshape(-1, 23, 3)], 1), dtype=torch.float64
            )
        ).numpy()
        box = tracks["boxes_xyxy"][rows].astype(np.float64)  # CLIFF's crop: the detection's box
        center, size = (box[:, :2] + box[:, 2:]) / 2, (box[:, 2:] - box[:, :2]).max(1)
        K = _camera_K(oracle_cfg, seq)
        write_cliff_estimates(
            cliff_path(init_dir, seq),
            tracks["frame"][rows],
            tracks["det_index"][rows],
            rot,
            betas,
            params_to_cliff_camera(tr, center, size, K),
            center,
            size,
        )
    cliff_cfg = _config(
        dataset,
        tmp_path / "cliff-out",
        **{
            "fit.batch_persons": 2,
            "fit.init_provider": "precomputed",
            "fit.init_dir": str(init_dir),
        },
    )
    report = _run(cliff_cfg)
    assert all(o.status == "done" for o in report.outcomes.values())
    for seq in ("0", "1"):
        bodies = [
            Bodies.read(next((tmp_path / out / "stages" / "fit" / seq).iterdir())).arrays()
            for out in ("oracle", "cliff-out")
        ]
        assert len(bodies[0]["frame"]) > 0
        for key in ("frame", "track_id", "det_index"):
            assert np.array_equal(bodies[0][key], bodies[1][key])
        for key in ("betas", "global_orient", "body_pose", "transl"):  # float32 storage of the file
            np.testing.assert_allclose(bodies[0][key], bodies[1][key], atol=2e-3)
        assert report.outcomes[(seq, "fit")].summary["skipped_without_estimate"] == 0
        assert report.outcomes[(seq, "fit")].summary["skipped_few_points"] == few[seq]
        assert np.all(bodies[0]["num_points"] >= oracle_cfg.fit.min_points)
        summary = report.outcomes[(seq, "fit")].summary
        assert np.all(bodies[1]["shift_m"] <= cliff_cfg.fit.max_shift_m)
        assert (
            summary["fitted"] == len(bodies[1]["frame"])
            and summary["dropped_far_from_estimate"] >= 0
        )


def _camera_K(cfg, seq):
    from flows.pipeline.inputs import sequence_ref, source

    return source(cfg).open(sequence_ref(cfg, seq)).info.calibration.cameras[cfg.dataset.camera].K


def test_labels_at_the_sensor_rate_end_to_end(dataset, tmp_path):
    """dataset.rate_hz 10: every raw frame is detected, tracked (gates scaled to 10 Hz), fitted,
    fused with per-vertex velocities, published and evaluated."""
    import numpy as np

    from flows.commands.evaluate import evaluate
    from flows.pipeline.inputs import track_inputs
    from storage.dataset import open_dataset
    from storage.products import Tracks
    from tasks.conventions import PEDESTRIAN

    out = tmp_path / "out"
    cfg = _config(dataset, out, **{"dataset.rate_hz": 10.0, "dataset.sequences": ["0"]})
    report = _run(cfg)
    assert all(o.status == "done" for o in report.outcomes.values()), report.failed
    inputs = track_inputs(cfg)
    assert (inputs.tracker.max_age, inputs.tracker.delta_t, inputs.offline.stitch_max_gap) == (
        60,
        6,
        20,
    )
    frames = read_table(out, "frames").to_pandas()
    assert frames["raw_frame"].tolist() == [0, 1, 2, 3]  # every sensor frame, not every 2nd
    tracks = Tracks.read(out / Manifest.load(out).get("0", "track").location)
    assert set(np.unique(tracks.frame).tolist()) == {0, 1, 2, 3}
    ds = open_dataset(out)
    arrays = {k: np.asarray(ds.arrays("0")[k]) for k in ("semantics", "instances", "velocity")}
    ped = arrays["semantics"] == PEDESTRIAN
    assert ped.any()
    speeds = np.linalg.norm(arrays["velocity"][ped].astype(np.float32), axis=1)
    # per-vertex velocities: the voxels of a person in a frame do not all move alike
    spread = [
        len(np.unique(arrays["velocity"][k][arrays["instances"][k] == i], axis=0))
        for k in range(4)
        for i in np.unique(arrays["instances"][k][ped[k]])
    ]
    assert max(spread) > 1 and np.isfinite(speeds).all()
    results = evaluate(out, dataset, tmp_path / "report", sample_frames=0)
    assert results["meta"]["frames"] == 4 and "tracking" in results
    assert set(results["velocity_by_limb"]) == {"legs", "arms", "torso", "all"}
