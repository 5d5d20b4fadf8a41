"""Stage inputs are the cache key: every setting a stage reads changes its key, nothing else does.

The mutation test changes every leaf of the default config, one at a time, to another valid value
and checks, for every stage: its key changed exactly when its inputs object changed or an upstream
key changed (the old hand-written slice table failed this for ``track.person_points.assoc_min_iou``,
which the map stage reads). Every leaf is read by some stage (or the dataset-level exports), or is
declared a runtime setting, or belongs to a provider the default config does not choose.
"""

from __future__ import annotations

import itertools
from typing import Any

import pytest

from configs.schema import ConfigError, load_config
from flows.pipeline.dag import STAGES
from flows.pipeline.inputs import (
    PER_SEQUENCE_KEYS,
    RUNTIME_KEYS,
    dataset_export_inputs,
    inputs_hash,
    sequence_ref,
    stage_inputs,
)
from flows.pipeline.plan import unit_keys
from tests.oracle import oracle_config

#: leaves only read when a provider the default config does not choose is chosen (each checked
#: below with that provider)
PROVIDER_ONLY = {
    "detect.precomputed_dir": {
        "detect.image_provider": "precomputed",
        "detect.precomputed_dir": "/p",
    },
    "fit.init_dir": {"fit.init_provider": "precomputed", "fit.init_dir": "/c"},
    "fuse.gt_min_points": {"fuse.body_source": "ground-truth"},
    "fit.cliff_path": {"fit.init_provider": "cliff", "fit.cliff_path": "/m.onnx"},
    # choosing the provider needs its directory or file
    "detect.image_provider": {"detect.precomputed_dir": "/p"},
    "fit.init_provider": {"fit.init_dir": "/c", "fit.cliff_path": "/m.onnx"},
    # a model kind that needs a file, or masks that do not come with BlazePose's keypoints
    "detect.models.detector.kind": {
        "detect.image_provider": "models",
        "detect.models.detector.path": "/d.onnx",
    },
    "detect.models.keypoints.kind": {
        "detect.image_provider": "models",
        "detect.models.masks.kind": "none",
        "detect.models.keypoints.path": "/k.onnx",
    },
    # the oracle's seed: read by the simulator's oracle only (configs/oracle.yaml)
    "detect.seed": {"detect.image_provider": "oracle"},
}
#: every leaf under these prefixes is read only with the provider chosen
PROVIDER_PREFIXES = {
    "detect.models.": {"detect.image_provider": "models"},
    # the oracle's noise: with the simulator's oracle only (not the default since issue 38)
    "detect.oracle.": {"detect.image_provider": "oracle"},
    # how robot logs are read: only with the log source
    "dataset.log.": {"dataset.format": "log"},
}
#: leaves read only in part: of ``fit.presets`` only the preset ``fit.preset`` names counts
#: (test_a_chosen_custom_preset_is_in_the_fit_key); track.scale_min_hits acts only where
#: dataset.rate_hz differs from track.gates_rate_hz (test_scale_min_hits_is_in_the_track_key_at_10_hz)
READ_IN_PART = {"fit.presets", "track.scale_min_hits"}


def _leaves(tree: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(tree, dict) and tree and not prefix.endswith(("cityscapes_to_class", "presets")):
        out: dict[str, Any] = {}
        for k, v in tree.items():
            out.update(_leaves(v, f"{prefix}.{k}" if prefix else str(k)))
        return out
    return {prefix: tree}


def _candidates(value: Any) -> list[Any]:
    """Other values a leaf could take (the first that validates is used)."""
    if isinstance(value, bool):
        return [not value]
    if isinstance(value, int):
        return [value + 1, value - 1, value * 2]
    if isinstance(value, float):
        return [
            round(value * 1.1 + 0.01, 6),
            round(value * 0.9, 6),
            value + 1.0,
            round(value / 2, 6),
        ]
    if isinstance(value, str):
        return [
            "3d_comp",
            "3d_raw",
            "2d_raw",
            "cam1",
            "unknown",
            "metadata",
            "rays",
            "zbuffer",
            "ground-truth",
            "oracle",
            "none",
            "precomputed",
            "lidar-clusters",
            "cpu",
            "cuda",
            "v1.0-mini",
            "3dpw",
            "ut_campus",
            "thread",
            "dask",
            "yolox",
            "person",
            "log",
            "coda",
            "lidar-odometry",
            "never",
            "undecided",
            "geometry",
            value + "x",
        ]
    if value is None:
        return ["/x", 0.05, 2, 0.5, [256, 512]]
    if isinstance(value, list):
        if value and all(isinstance(v, int) and not isinstance(v, bool) for v in value):
            return [[value[0] + 1, *value[1:]], [*value[:-1], value[-1] + 1]]
        if value and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
            return [
                [value[0] + 0.2, *value[1:]],
                [value[0] - 0.2, *value[1:]],
                [*value[:-1], round(value[-1] * 0.9, 6)],
                [*value[:-1], value[-1] + 0.1],
            ]
        return [value[:-1], value + ["nuscenes"], ["0"], ["terrain"]]
    if isinstance(value, dict):
        return [
            {**value, 10: "terrain"},
            {},
            {"cam0": {"image_topic": "/x/image"}},
            {
                "mine": {
                    "rho_px": 100,
                    "lambda_theta": 1,
                    "lambda_a": 1,
                    "lambda_beta": 1,
                    "lambda_3d": 1,
                    "lambda_occ": 1,
                    "w": 0.2,
                    "j_conf": 0.5,
                }
            },
        ]
    raise AssertionError(f"no mutation for {value!r}")


def _mutate(base: dict, key: str, extra: dict | None = None):
    for candidate in _candidates(base[key]):
        if candidate == base[key]:
            continue
        try:
            return load_config(overrides={**(extra or {}), key: candidate})
        except ConfigError:
            continue
    return None


def _state(config) -> tuple[dict[str, str], dict[str, str]]:
    inputs = stage_inputs(config)
    keys = unit_keys(inputs, "fingerprint")
    return ({s: inputs_hash(v) for s, v in inputs.items()}, {s: k for s, (k, _) in keys.items()})


def _check_keys_follow_inputs(base_cfg, mutated, key: str) -> bool:
    """Assert the key rule for one mutation; return whether any stage (or the dataset exports)
    read the changed leaf."""
    (h0, k0), (h1, k1) = _state(base_cfg), _state(mutated)
    for stage, upstream in STAGES.items():
        expected = h0[stage] != h1[stage] or any(k0[u] != k1[u] for u in upstream)
        assert (k0[stage] != k1[stage]) == expected, (key, stage)
    exports = inputs_hash(dataset_export_inputs(base_cfg)) != inputs_hash(
        dataset_export_inputs(mutated)
    )
    return exports or any(h0[s] != h1[s] for s in STAGES)


def test_every_leaf_changes_exactly_the_keys_of_the_stages_that_read_it():
    base_cfg = load_config()
    base = _leaves(base_cfg.model_dump(mode="json"))
    unread, untested = [], []
    for key in sorted(base):
        if key.startswith(tuple(PER_SEQUENCE_KEYS)):
            continue  # in the sequence's fingerprint: test_a_sequences_own_settings_rerun_it_alone
        if key.startswith(tuple(RUNTIME_KEYS)):
            mutated = _mutate(base, key)
            if mutated is not None:
                assert _state(mutated) == _state(base_cfg), f"runtime setting {key} changed a key"
            continue
        extra = PROVIDER_ONLY.get(key) or next(
            (v for k, v in PROVIDER_PREFIXES.items() if key.startswith(k)), None
        )
        cfg = load_config(overrides=extra) if extra else base_cfg
        leaves = _leaves(cfg.model_dump(mode="json"))
        mutated = _mutate(leaves, key, extra)
        if mutated is None:
            untested.append(key)
            continue
        if not _check_keys_follow_inputs(cfg, mutated, key) and key not in READ_IN_PART:
            unread.append(key)
    assert not untested, f"no valid mutation found for {untested}"
    assert not unread, f"settings that no stage reads (dead config or a missing input): {unread}"


def test_scale_min_hits_is_in_the_track_key_at_10_hz():
    """At the gates' own rate min_hits is the same either way (the key too); at 10 Hz it doubles."""
    at = {
        hz: [
            load_config(overrides={"dataset.rate_hz": hz, "track.scale_min_hits": s})
            for s in (False, True)
        ]
        for hz in (5.0, 10.0)
    }
    assert _state(at[5.0][0])[1]["track"] == _state(at[5.0][1])[1]["track"]
    assert _state(at[10.0][0])[1]["track"] != _state(at[10.0][1])[1]["track"]


def test_the_old_slice_table_misses_the_map_stages_iou_and_the_inputs_do_not():
    """The bug this design fixes: the map stage reads track.person_points.assoc_min_iou."""
    a = load_config()
    b = load_config(overrides={"track.person_points.assoc_min_iou": 0.9})
    (ha, ka), (hb, kb) = _state(a), _state(b)
    assert ha["map"] != hb["map"] and ka["map"] != kb["map"]
    assert ha["detect"] == hb["detect"] and ka["detect"] == kb["detect"]


def test_a_chosen_custom_preset_is_in_the_fit_key():
    mine = {
        "rho_px": 100,
        "lambda_theta": 1,
        "lambda_a": 1,
        "lambda_beta": 1,
        "lambda_3d": 300,
        "lambda_occ": 1,
        "w": 0.2,
        "j_conf": 0.5,
    }
    a = load_config(overrides={"fit.presets": {"mine": mine}, "fit.preset": "mine"})
    b = load_config(
        overrides={"fit.presets": {"mine": {**mine, "lambda_3d": 301}}, "fit.preset": "mine"}
    )
    c = load_config(overrides={"fit.presets": {"mine": mine, "other": mine}, "fit.preset": "mine"})
    assert _state(a)[1]["fit"] != _state(b)[1]["fit"]
    assert _state(a)[1]["fit"] == _state(c)[1]["fit"]


def test_provider_settings_only_count_for_the_chosen_provider():
    """Oracle noise does not rerun a detect stage that reads precomputed files, and vice versa."""
    pre = {
        "detect.image_provider": "precomputed",
        "detect.precomputed_dir": "/p",
        "detect.lidar_provider": "precomputed",
    }
    a, b = (
        load_config(overrides=pre),
        load_config(overrides={**pre, "detect.oracle.box_jitter": 0.2}),
    )
    assert _state(a)[1]["detect"] == _state(b)[1]["detect"]
    a, b = oracle_config(), oracle_config({"detect.oracle.box_jitter": 0.2})
    assert _state(a)[1]["detect"] != _state(b)[1]["detect"]


@pytest.mark.parametrize("stage_a, stage_b", list(itertools.combinations(STAGES, 2)))
def test_inputs_objects_are_hashable_and_distinct_per_stage(stage_a, stage_b):
    inputs = stage_inputs(load_config())
    assert inputs_hash(inputs[stage_a]) != inputs_hash(inputs[stage_b])


def test_a_sequences_own_settings_rerun_it_alone():
    """dataset.lighting names sequences: it enters their fingerprints, not every stage's inputs."""
    a = load_config()
    b = load_config(overrides={"dataset.lighting": {"7": "night"}})
    assert _state(a) == _state(b)
    files = "files-fingerprint"
    assert sequence_ref(b, "7").fingerprint(files) != sequence_ref(a, "7").fingerprint(files)
    assert (
        sequence_ref(b, "8").fingerprint(files) == sequence_ref(a, "8").fingerprint(files) == files
    )


def test_a_spec_keeps_its_name_in_the_key():
    """The provider specs were renamed (OracleProvider -> OracleSpec, ...): the JSON of a key
    names each by its KEY_TYPE, its old name, so no key changed; two specs never share one."""
    import dataclasses

    from flows.pipeline import inputs

    specs = [
        c
        for c in vars(inputs).values()
        if isinstance(c, type) and dataclasses.is_dataclass(c) and hasattr(c, "KEY_TYPE")
    ]
    assert len(specs) == 7 and len({c.KEY_TYPE for c in specs}) == len(specs)
    assert all(c.__name__.endswith("Spec") and c.KEY_TYPE.endswith("Provider") for c in specs)
    # the oracle's detect (configs/oracle.yaml, the default before issue 38)
    detect = inputs.to_jsonable(stage_inputs(oracle_config())["detect"])
    assert (detect["image"]["type"], detect["lidar"]["type"]) == (
        "OracleProvider",
        "LidarClustersProvider",
    )
