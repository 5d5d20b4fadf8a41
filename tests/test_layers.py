"""The layers of DESIGN.md: kernels and storage stay free of orchestration and formats; stages stay
thin. configs/ may import tasks/: a config section is made from its kernel's parameter dataclass
(configs/schema.py, one home per default)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

FORBIDDEN = {
    # layer: (module prefixes it must never import, why)
    "tasks": (
        "prefect",
        "dask.distributed",
        "distributed",
        "zarr",
        "pyarrow",
        "fsspec",
        "storage",
        "flows",
        "configs",
        # model files open in storage/network_files.py; adapters take runners
        "onnxruntime",
        "ai_edge_litert",
    ),
    "storage": ("flows", "prefect", "distributed", "dask.distributed"),
    "configs": ("flows", "storage", "prefect"),
}


def imported_modules(path: Path) -> list[tuple[int, str]]:
    tree = ast.parse(path.read_text(), filename=str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append((node.lineno, node.module))
    return found


def violations(layer: str, root: Path = ROOT) -> list[str]:
    bad = []
    for path in sorted((root / layer).rglob("*.py")):
        for lineno, module in imported_modules(path):
            for prefix in FORBIDDEN[layer]:
                if module == prefix or module.startswith(prefix + "."):
                    bad.append(f"{path.relative_to(root)}:{lineno} imports {module}")
    return bad


@pytest.mark.parametrize("layer", sorted(FORBIDDEN))
def test_layer_imports(layer):
    assert violations(layer) == []


def test_the_check_catches_a_violation(tmp_path):
    (tmp_path / "tasks").mkdir()
    (tmp_path / "tasks" / "bad.py").write_text(
        "def f():\n    import zarr\n    from prefect import flow\n"
    )
    assert violations("tasks", tmp_path) == [
        "tasks/bad.py:2 imports zarr",
        "tasks/bad.py:3 imports prefect",
    ]


def test_tests_take_kernels_from_tasks():
    """Algorithms live in tasks/: from a stage module (flows/stages/<stage>.py) a test imports its
    ``run_<stage>`` only, never a helper (the shared providers and context are not stages)."""
    stages = {f"flows.stages.{s}" for s in ("detect", "track", "fit", "map", "fuse", "export")}
    bad = []
    for path in sorted((ROOT / "tests").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module in stages:
                bad += [
                    f"{path.name}: {node.module}.{a.name}"
                    for a in node.names
                    if not a.name.startswith("run_")
                ]
    assert bad == []
