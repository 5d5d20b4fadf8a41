"""Typed configuration: every YAML validates; misspelled keys and bad values are reported by path."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

from configs.schema import Config, ConfigError, config_hash, load_config
from tasks import conventions
from tasks.fit.weights import FIT_PRESETS

CONFIGS = sorted((Path(__file__).resolve().parents[1] / "configs").glob("*.yaml"))


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_every_yaml_validates(path):
    cfg = load_config(path)
    assert cfg.fuse.grid.shape == (48, 48, 24)


def test_default_matches_conventions():
    cfg = load_config()
    table = {k: conventions.CLASS_NAMES.index(v) for k, v in cfg.map.cityscapes_to_class.items()}
    for cs_id in range(19):
        assert conventions.CITYSCAPES_TO_CLASS[cs_id] == table.get(cs_id, conventions.UNLABELED)
    assert cfg.dataset.frame_stride == 2


def test_paper_presets():
    assert set(FIT_PRESETS) == {"3dpw", "sloper4d", "humanm3", "ut_campus"}
    assert FIT_PRESETS["humanm3"].w == -1.0 and FIT_PRESETS["3dpw"].lambda_3d == 800
    cfg = load_config(overrides={"fit.preset": "sloper4d"})
    assert cfg.fit.weights.lambda_occ == 55 and cfg.fit.weights.j_conf == 0.7
    mine = {
        "rho_px": 50,
        "lambda_theta": 1,
        "lambda_a": 2,
        "lambda_beta": 3,
        "lambda_3d": 4,
        "lambda_occ": 5,
        "w": 0.1,
        "j_conf": 0.5,
    }
    cfg = load_config(
        overrides={"fit.presets": {"mine": mine}, "fit.preset": "mine", "fit.conf_power": 1.0}
    )
    w = cfg.fit.weights
    assert (w.rho_px, w.lambda_occ, w.conf_power, w.square_lambdas) == (50, 5, 1.0, True)


def test_misspelled_nested_key_is_reported_with_its_path(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text(
        "extends: %s\nfuse:\n  grid:\n    voxel_sise_m: 0.1\ntrack:\n  max_age: -3\n"
        % (CONFIGS[0].parent / "default.yaml")
    )
    with pytest.raises(ConfigError) as info:
        load_config(bad)
    paths = [p for p, _ in info.value.errors]
    assert "fuse.grid.voxel_sise_m" in paths and "track.max_age" in paths
    assert "unknown key" in str(info.value)


@pytest.mark.parametrize(
    "override, message",
    [
        ({"fuse.grid.voxel_size_m": 0.07}, "not a multiple of voxel_size_m"),
        ({"fit.preset": "nope"}, "preset 'nope' is not one of"),
        ({"detect.image_provider": "precomputed"}, "precomputed_dir is required"),
        ({"fit.init_provider": "precomputed"}, "fit.init_dir is required"),
        ({"dataset.rate_hz": 3.0}, "must be a whole number"),
        ({"map.cityscapes_to_class": {10: "sky"}}, "is not an occupied class"),
    ],
)
def test_cross_field_rules(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(overrides=override)


def test_frozen_and_hash_changes_with_content():
    cfg = load_config()
    with pytest.raises(ValidationError):
        cfg.fuse.grid.voxel_size_m = 0.1  # type: ignore[misc]
    assert config_hash(cfg) == config_hash(load_config())
    assert config_hash(cfg) != config_hash(load_config(overrides={"fuse.grid.voxel_size_m": 0.1}))


def _yaml_leaves(tree, prefix=""):
    if isinstance(tree, dict) and not prefix.endswith(
        ("cityscapes_to_class", "presets", "lighting")
    ):
        for k, v in tree.items():
            yield from _yaml_leaves(v, f"{prefix}.{k}" if prefix else str(k))
    else:
        yield prefix, tree


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_yaml_files_set_only_what_differs_from_the_defaults(path):
    """One home per default: a YAML restating what it extends (the schema's defaults, or the file
    named by ``extends``) is a second copy that can drift."""
    import yaml

    raw = yaml.safe_load(path.read_text()) or {}
    parent = raw.pop("extends", None)
    base = (load_config(path.parent / parent) if parent else Config()).model_dump(mode="json")
    for key, value in _yaml_leaves(raw):
        node = base
        for part in key.split("."):
            node = node[part]
        assert node != value, f"{path.name}: {key} = {value!r} restates what it extends"


def test_kernel_sections_take_their_defaults_from_the_kernels():
    """The config's defaults of a kernel's settings are the kernel dataclass's own."""
    import dataclasses

    from tasks.occupancy.settings import FreeSpaceParams, FuseSettings, MapParams
    from tasks.perception.oracle import OracleNoise
    from tasks.track.offline import Confirmation, OfflineParams, WorldCheck

    cfg = load_config()
    for section, kernel in (
        (cfg.detect.oracle, OracleNoise),
        (cfg.map, MapParams),
        (cfg.map.freespace, FreeSpaceParams),
        (cfg.track.world_check, WorldCheck),
        (cfg.track.confirm, Confirmation),
        (cfg.track, OfflineParams),
        (cfg.fuse, FuseSettings),
    ):
        assert section.to(kernel) == kernel(), kernel.__name__
        assert {f.name for f in dataclasses.fields(kernel)} <= {
            f.name for f in dataclasses.fields(section)
        }
