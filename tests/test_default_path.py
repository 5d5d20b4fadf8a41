"""The default config is the real path (issue 38): it reads no ground truth, runs end to end on a
simulated sequence whose gt/ is removed, and a config that reads gt/ is refused where there is
none, before any work, naming the settings and the config to use."""

from __future__ import annotations

import shutil

import pytest

from configs.schema import CONFIG_DIR, load_config
from flows import cli
from flows.commands.perception_sources import stage_sources, truth_settings
from storage.manifest import Manifest
from storage.tables import read_table
from tests.oracle import ORACLE_ARGS, oracle_config

pytestmark = [pytest.mark.slow]

#: few fit iterations: these tests are about which inputs are read, not fit quality
CHEAP = ["--set", "fit.iterations=5", "--set", "dataset.sequences=['0']", "--quiet"]


def test_which_configs_read_the_ground_truth():
    for name in ("default", "robot-log", "coda", "coda-onnx"):
        assert truth_settings(load_config(CONFIG_DIR / f"{name}.yaml")) == [], name
    assert truth_settings(oracle_config()) == ["detect.image_provider", "fit.init_provider"]
    bundled = load_config(CONFIG_DIR / "bundled-models.yaml")
    assert truth_settings(bundled) == ["detect.models.semantic.kind", "fit.init_provider"]
    exact = load_config(CONFIG_DIR / "ground-truth-inputs.yaml")
    assert truth_settings(exact) == [
        "detect.image_provider",
        "detect.lidar_provider",
        "fit.init_provider",
        "fuse.body_source",
    ]
    sources = stage_sources(load_config())
    assert sources["semantics"].startswith("none") and sources["fit start"] == "lidar-keypoints"
    assert not any("gt/" in v for v in sources.values()), sources
    assert all("(gt/)" in stage_sources(oracle_config())[k] for k in ("detect image", "fit start"))


@pytest.fixture()
def no_truth(copy_dataset):
    """The shared simulated sequences without their gt/ folder: a recording as a user has it."""
    data = copy_dataset()
    shutil.rmtree(data / "gt")
    return data


def test_default_config_runs_end_to_end_without_ground_truth(no_truth, tmp_path, capsys):
    out = tmp_path / "out"
    args = ["--data", str(no_truth), "--out", str(out), *CHEAP[:-1]]  # progress on: not --quiet
    code = cli.main(["rebuild", *args])
    text = capsys.readouterr()
    assert code == 0, text.out + text.err
    assert not (no_truth / "gt").exists()
    manifest = Manifest.load(out)
    assert all(manifest.get("0", s).status == "done" for s in ("detect", "fit", "export"))
    assert read_table(out, "frames", "0").num_rows == 2
    # not a terminal: a plain line per stage, no progress bar's carriage returns
    assert "\r" not in text.err and "detect: 1 unit(s) ended" in text.err, text.err
    # status with only --out takes the config the dataset was built with: nothing is stale
    assert cli.main(["status", "--out", str(out)]) == 0
    text = capsys.readouterr()
    assert "0 unit(s) stale or failed" in text.out and "note:" not in text.err, text
    # another config is named, with the keys where it differs
    assert cli.main(["status", *ORACLE_ARGS, "--out", str(out), *CHEAP[:-1]]) == 0
    text = capsys.readouterr()
    assert "6 unit(s) stale" in text.out and "in 3 key(s)" in text.err, text
    for key in ("detect.image_provider ('models' -> 'oracle')", "fit.init_provider"):
        assert key in text.err, text.err
    assert "dask." not in text.err and "output.root" not in text.err


def test_a_config_that_reads_gt_is_refused_where_there_is_none(no_truth, tmp_path, capsys):
    out = tmp_path / "out"
    capsys.readouterr()
    code = cli.main(["rebuild", *ORACLE_ARGS, "--data", str(no_truth), "--out", str(out), *CHEAP])
    err = capsys.readouterr().err
    assert code == cli.EXIT_USAGE, err
    for says in ("detect.image_provider: models", "fit.init_provider: lidar-keypoints", "oracle"):
        assert says in err, err
    assert "sequence(s) 0 " in err and "Traceback" not in err
    assert not (out / "manifest.json").exists()  # refused before any work
    code = cli.main(["reprocess", *ORACLE_ARGS, "--data", str(no_truth), "--out", str(out)])
    assert code == cli.EXIT_USAGE and "fit.init_provider" in capsys.readouterr().err


def test_check_data_prints_each_stages_source_and_refuses_gt_it_lacks(
    no_truth, synthetic_root, capsys
):
    capsys.readouterr()
    assert cli.main(["check-data", *ORACLE_ARGS, "--data", str(no_truth)]) == cli.EXIT_USAGE
    text = capsys.readouterr().out
    lines = [line for line in text.splitlines() if line.startswith(("  0:", "  1:"))]
    assert sum("NEEDS gt/" in line and "detect image oracle (gt/)" in line for line in lines) == 2
    assert "REFUSED" in text and "ready to run" not in text
    assert cli.main(["check-data", "--data", str(no_truth)]) == 0
    text = capsys.readouterr().out
    assert text.count("reads no gt/") == 2 and "semantics none" in text, text
    assert cli.main(["check-data", *ORACLE_ARGS, "--data", str(synthetic_root)]) == 0
    assert capsys.readouterr().out.count("reads gt/ (present)") == 2


def test_missing_bundled_models_say_make_setup(no_truth, tmp_path, capsys):
    out, empty = tmp_path / "out", tmp_path / "no-models"
    capsys.readouterr()
    args = ["--set", f"detect.models.bundled_dir={empty}"]
    code = cli.main(["rebuild", "--data", str(no_truth), "--out", str(out), *args, *CHEAP])
    err = capsys.readouterr().err
    assert code == cli.EXIT_USAGE and "make setup" in err and str(empty) in err, err
    assert not (out / "manifest.json").exists()


def test_check_data_names_the_calibration_of_the_source_in_hand():
    """Issue 38: a log's ground-height warning named CODa's calib_os1_to_base.yaml."""
    from types import SimpleNamespace

    import numpy as np

    from flows.commands.check_data import _figures

    xy = np.mgrid[-5:5:0.25, -5:5:0.25].reshape(2, -1).T
    ground = np.c_[xy, np.full(len(xy), -1.0)].astype(np.float32)  # 1 m below the base
    calib = SimpleNamespace(cameras={}, T_base_from_lidar=np.eye(4), T_cam1_from_cam0=None)
    said = {}
    for log in (False, True):
        problems: list[str] = []
        facts = SimpleNamespace(
            seq=SimpleNamespace(info=SimpleNamespace(calibration=calib)),
            sample_points=[ground],
            problem=lambda blocking, msg, out=problems: out.append(msg),
        )
        assert abs(_figures(facts, "cam0", log=log)["ground"] + 1.0) < 0.05
        [said[log]] = problems
    assert "calib_os1_to_base.yaml" in said[False] and "/tf_static" not in said[False]
    assert "/tf_static" in said[True] and "calib_os1" not in said[True]
