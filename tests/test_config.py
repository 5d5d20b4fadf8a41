"""Typed configuration: every YAML validates; misspelled keys and bad values are reported by path."""

from __future__ import annotations

from pathlib import Path

import pytest

from configs.schema import PAPER_PRESETS, ConfigError, config_hash, load_config
from tasks import conventions

CONFIGS = sorted((Path(__file__).resolve().parents[1] / "configs").glob("*.yaml"))


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_every_yaml_validates(path):
    cfg = load_config(path)
    assert cfg.fuse.grid.shape == (48, 48, 24)


def test_default_matches_conventions():
    cfg = load_config()
    assert [c.name for c in cfg.classes] == list(conventions.CLASS_NAMES)
    assert [list(c.color) for c in cfg.classes] == conventions.CLASS_COLORS.tolist()
    table = {k: cfg.class_id(v) for k, v in cfg.map.cityscapes_to_class.items()}
    for cs_id in range(19):
        assert conventions.CITYSCAPES_TO_CLASS[cs_id] == table.get(cs_id, conventions.UNLABELED)
    assert cfg.dataset.frame_stride == 2


def test_paper_presets():
    assert set(PAPER_PRESETS) == {"3dpw", "sloper4d", "humanm3", "ut_campus"}
    assert PAPER_PRESETS["humanm3"].w == -1.0 and PAPER_PRESETS["3dpw"].lambda_3d == 800
    cfg = load_config(overrides={"fit.preset": "sloper4d"})
    assert cfg.fit.weights.lambda_occ == 55 and cfg.fit.weights.j_conf == 0.7


def test_misspelled_nested_key_is_reported_with_its_path(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("extends: %s\nfuse:\n  grid:\n    voxel_sise_m: 0.1\ntrack:\n  max_age: -3\n"
                   % (CONFIGS[0].parent / "default.yaml"))
    with pytest.raises(ConfigError) as info:
        load_config(bad)
    paths = [p for p, _ in info.value.errors]
    assert "fuse.grid.voxel_sise_m" in paths and "track.max_age" in paths
    assert "unknown key" in str(info.value)


@pytest.mark.parametrize("override, message", [
    ({"fuse.grid.voxel_size_m": 0.07}, "not a multiple of voxel_size_m"),
    ({"fit.preset": "nope"}, "preset 'nope' is not one of"),
    ({"detect.image_provider": "precomputed"}, "precomputed_dir is required"),
    ({"fit.init_provider": "precomputed"}, "fit.init_dir is required"),
    ({"dataset.rate_hz": 3.0}, "must be a whole number"),
    ({"map.cityscapes_to_class": {10: "sky"}}, "is not an occupied class"),
])
def test_cross_field_rules(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(overrides=override)


def test_frozen_and_hash_changes_with_content():
    cfg = load_config()
    with pytest.raises(Exception):
        cfg.fuse.grid.voxel_size_m = 0.1  # type: ignore[misc]
    assert config_hash(cfg) == config_hash(load_config())
    assert config_hash(cfg) != config_hash(load_config(overrides={"fuse.grid.voxel_size_m": 0.1}))


def test_stage_slices_isolate_stages():
    a = load_config()
    b = load_config(overrides={"fuse.grid.voxel_size_m": 0.1})
    for stage in ("detect", "track", "fit", "map", "export"):
        assert a.stage_slice(stage) == b.stage_slice(stage), stage
    assert a.stage_slice("fuse") != b.stage_slice("fuse")
    moved = load_config(overrides={"dataset.root": "/elsewhere"})
    assert a.stage_slice("detect") == moved.stage_slice("detect")


def _kwargs(fn) -> set[str]:
    import inspect

    return {n for n, p in inspect.signature(fn).parameters.items() if p.default is not inspect._empty}


def test_config_sections_mirror_kernel_parameters():
    """Flows hand config sections to kernels as keyword arguments: the names must line up."""
    import dataclasses

    from configs.schema import LidarClustersConfig, OracleNoise as OracleCfg, PersonPointsConfig
    from tasks.fit.losses import FitWeights
    from tasks.perception.lidar_clusters import detect_pedestrians_lidar
    from tasks.perception.oracle import OracleNoise
    from tasks.perception.person_points import person_point_indices
    from tasks.track.ocsort import PedestrianTracker

    assert set(OracleCfg.model_fields) == {f.name for f in dataclasses.fields(OracleNoise)}
    assert set(LidarClustersConfig.model_fields) == _kwargs(detect_pedestrians_lidar)
    pp = set(PersonPointsConfig.model_fields) - {"assoc_min_iou"}
    assert pp == _kwargs(person_point_indices) - {"masks", "expected_range_m"}
    from configs.schema import TrackConfig
    assert _kwargs(PedestrianTracker.__init__) <= set(TrackConfig.model_fields)
    assert {f.name for f in dataclasses.fields(FitWeights)} == {
        "rho_px", "lambda_theta", "lambda_a", "lambda_beta", "lambda_3d", "lambda_occ", "w", "j_conf",
        "conf_power", "square_lambdas"}
