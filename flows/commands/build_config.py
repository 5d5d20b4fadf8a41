"""The config a dataset was built with: ``status``, ``reprocess`` and ``export`` use it unless told
otherwise (issue 38: without the build's ``--config`` every unit was called stale).

The run records its resolved config in ``OUT/manifest.json`` (``meta.config``, with
``meta.data_root``: flows/pipeline/units.py run_units). With no ``--config`` these commands take
that record (``--set`` / ``--data`` still apply on top); with one (and no ``--data``: the recorded
raw data root), the keys where it differs from the record are named (how a run is spread, ``dask.*``, and where its data and output are, are
left out: they change no output).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from configs.schema import Config, config_from_tree, load_config
from storage.manifest import DATA_ROOT_KEY, Manifest

#: keys that say where and how a run goes, not what it computes: never named as a difference
WHERE_AND_HOW = ("dask.", "output.root", "dataset.root")


def built_config_tree(out: Path | str) -> dict | None:
    """The resolved config recorded by the last run into ``out`` (None: no run recorded one)."""
    if not (Path(out) / "manifest.json").is_file():
        return None
    meta = Manifest.load(Path(out)).meta
    tree = meta.get("config")
    if not tree:
        return None
    tree = dict(tree)
    if meta.get(DATA_ROOT_KEY):  # absolute: the record's dataset.root may be relative
        tree["dataset"] = {**tree.get("dataset", {}), "root": meta[DATA_ROOT_KEY]}
    return tree


def _leaves(tree: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(tree, dict) and tree:
        out: dict[str, Any] = {}
        for key, value in tree.items():
            out.update(_leaves(value, f"{prefix}.{key}" if prefix else str(key)))
        return out
    return {prefix: tree}


def differing_keys(built: dict, given: dict) -> list[tuple[str, Any, Any]]:
    """(key, built value, given value) of every leaf that differs, what-it-computes keys only."""
    a, b = _leaves(built), _leaves(given)
    return [
        (key, a.get(key), b.get(key))
        for key in sorted(set(a) | set(b))
        if a.get(key) != b.get(key) and not key.startswith(WHERE_AND_HOW)
    ]


def config_for_dataset(
    config_path: Path | None, overrides: dict[str, Any], out: Path | str | None
) -> tuple[Config, str | None]:
    """(config, note): with no ``config_path`` the config recorded for the dataset at ``out``
    (the default config where none is recorded), else the file given, with a note naming the keys
    where it differs from the recorded one (None when it does not, or none is recorded)."""
    if out is None:
        out = load_config(config_path, overrides).output.root
    built = built_config_tree(out)
    if built is None:
        return load_config(config_path, overrides), None
    if config_path is None:
        return config_from_tree(built, f"{out}/manifest.json (the config it was built with)",
                                overrides), None  # fmt: skip
    # the raw data are where the dataset was built from, unless --data says otherwise
    root = {"dataset.root": built["dataset"]["root"]} if "root" in built.get("dataset", {}) else {}
    config = load_config(config_path, {**root, **overrides})
    diff = differing_keys(built, config.model_dump(mode="json"))
    if not diff:
        return config, None
    shown = ", ".join(f"{k} ({a!r} -> {b!r})" for k, a, b in diff[:12])
    more = f" and {len(diff) - 12} more" if len(diff) > 12 else ""
    return config, (
        f"note: config {config_path} differs from the one {out} was built with (recorded in its "
        f"manifest.json; leave --config out to use that one) in {len(diff)} key(s): {shown}{more}"
    )
