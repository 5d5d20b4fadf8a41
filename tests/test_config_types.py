"""The config tree a type checker sees: every section is a class written out in configs/schema.py
(no model made at run time), so ``config.fit.iterations`` is a declared ``int`` to an editor and
to mypy."""

from __future__ import annotations

import ast
import dataclasses
import typing
from collections.abc import Iterator
from pathlib import Path

import pytest
from pydantic import BaseModel

from configs import schema
from configs.schema import Config, load_config

ROOT = Path(__file__).resolve().parents[1]


def _is_section(tp: typing.Any) -> bool:
    return isinstance(tp, type) and (issubclass(tp, BaseModel) or dataclasses.is_dataclass(tp))


def sections(cls: type = Config, path: str = "") -> Iterator[tuple[str, type]]:
    """(dotted path, class) of the config and every section in it (presets' entries included)."""
    yield path, cls
    for name, tp in typing.get_type_hints(cls).items():
        for arg in (tp, *typing.get_args(tp)):
            if _is_section(arg) and arg is not Path:
                yield from sections(arg, f"{path}.{name}" if path else name)


def test_every_section_is_a_class_declared_in_the_schema():
    declared = {
        node.name
        for node in ast.walk(ast.parse(Path(schema.__file__).read_text()))
        if isinstance(node, ast.ClassDef)
    }
    found = {cls.__name__: path for path, cls in sections()}
    assert len(found) >= 20  # the tree: dataset, detect (oracle, models ...), ..., dask
    assert set(found) <= declared, set(found) - declared


def test_every_key_is_a_declared_attribute():
    """typing.get_type_hints of each section names every key of the resolved config (the
    kernels' fields come from the settings dataclasses the section subclasses)."""
    dump = load_config().model_dump(mode="json")
    for path, cls in sections():
        if path.endswith("presets"):
            continue  # an entry of fit.presets, absent from the default config
        node = dump
        for key in filter(None, path.split(".")):
            node = node[key]
        hints = typing.get_type_hints(cls)
        assert set(node) == set(hints) - {"model_config"}, path
    assert typing.get_type_hints(schema.FitConfig)["iterations"] is int
    assert "lambda_3d" in typing.get_type_hints(schema.LossWeightsConfig)


@pytest.mark.slow
def test_mypy_checks_attribute_access(tmp_path, monkeypatch):
    """mypy over configs/ and a file that reads the config: no error but the two planted ones
    (a misspelled key, a value used as the wrong type)."""
    api = pytest.importorskip("mypy.api")
    usage = tmp_path / "use_config.py"
    usage.write_text(
        "from configs.schema import load_config\n"
        "config = load_config()\n"
        "iterations: int = config.fit.iterations\n"
        "rate: float = config.fit.learning_rate + config.dataset.rate_hz\n"
        "weight: float = config.fit.weights.factor(config.fit.weights.lambda_3d)\n"
        "recall: float = config.detect.oracle.day_recall * config.track.world_check.tol_m\n"
        "kind: str = config.detect.models.detector.kind\n"
        "wrong: str = config.fit.iterations\n"
        "config.fit.iteratons\n"
    )
    monkeypatch.chdir(ROOT)
    out, err, status = api.run(
        [
            "--config-file",
            str(ROOT / "pyproject.toml"),
            "--cache-dir",
            str(tmp_path / "cache"),
            "--no-error-summary",
            "configs",
            str(usage),
        ]
    )
    errors = [line for line in out.splitlines() if ": error:" in line]
    assert status == 1 and len(errors) == 2, out + err
    assert errors[0].startswith(f"{usage}:8:") and "incompatible types" in errors[0].lower()
    assert errors[1].startswith(f"{usage}:9:") and '"iteratons"' in errors[1]
