"""The layers: flows -> {tasks, storage, configs}; kernels and storage stay free of orchestration
and formats; a stage reads through storage, calls kernels in tasks/ and writes through storage.
configs/ may import tasks/: a config section is made from its kernel's parameter dataclass
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


#: what a stage module (flows/stages/*.py) leaves to storage/: file formats and file handling
STAGE_NO_FORMATS = (
    *("json", "pickle", "csv", "zipfile", "io", "tempfile", "os", "shutil"),
    *("zarr", "pyarrow", "fsspec", "h5py", "PIL", "imageio", "cv2", "yaml"),
)
#: ... and to tasks/: the numerical libraries of the kernels
STAGE_NO_NUMERICS = ("scipy", "torch", "numba", "open3d", "sklearn")
#: file reads and writes by method (Path, ndarray) or by numpy function
FILE_METHODS = {
    *("read_text", "write_text", "read_bytes", "write_bytes", "tofile"),
    *("mkdir", "touch", "unlink", "rmdir", "rename", "symlink_to", "hardlink_to"),
}
NUMPY_FILE_FUNCTIONS = {"load", "save", "savez", "savez_compressed", "fromfile", "loadtxt"}
#: matrix algebra is a kernel's (frames composed and inverted: tasks/); a length
#: (np.linalg.norm) or array bookkeeping (indexing, stacking, masks) is a stage's business
NUMPY_MATRIX_FUNCTIONS = {
    *("matmul", "dot", "einsum", "tensordot", "inner", "outer", "cross"),
    *("linalg.inv", "linalg.pinv", "linalg.solve", "linalg.lstsq", "linalg.svd", "linalg.det"),
    *("linalg.eig", "linalg.eigh", "linalg.qr", "linalg.cholesky"),
}


def _numpy_name(func: ast.expr) -> str | None:
    """``linalg.inv`` for ``np.linalg.inv`` / ``numpy.linalg.inv``; None for anything else."""
    parts = []
    while isinstance(func, ast.Attribute):
        parts.append(func.attr)
        func = func.value
    if isinstance(func, ast.Name) and func.id in ("np", "numpy") and parts:
        return ".".join(reversed(parts))
    return None


def stage_violations(root: Path = ROOT) -> list[str]:
    """Where a module of flows/stages/ reaches past storage/ for a file or past tasks/ for
    numerics: imports of format or numerical libraries, file calls, matrix algebra."""
    bad = []
    for path in sorted((root / "flows" / "stages").glob("*.py")):
        found = [
            (lineno, f"imports {module}")
            for lineno, module in imported_modules(path)
            if module.split(".")[0] in (*STAGE_NO_FORMATS, *STAGE_NO_NUMERICS)
        ]
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.BinOp) and isinstance(node.op, ast.MatMult):
                found.append((node.lineno, "multiplies matrices (@)"))
            if not isinstance(node, ast.Call):
                continue
            name = _numpy_name(node.func)
            if isinstance(node.func, ast.Name) and node.func.id == "open":
                found.append((node.lineno, "calls open"))
            elif name in NUMPY_FILE_FUNCTIONS or name in NUMPY_MATRIX_FUNCTIONS:
                found.append((node.lineno, f"calls np.{name}"))
            elif isinstance(node.func, ast.Attribute) and node.func.attr in FILE_METHODS:
                found.append((node.lineno, f"calls .{node.func.attr}"))
        bad += [f"{path.relative_to(root)}:{n} {what}" for n, what in sorted(found)]
    return bad


def test_stages_read_and_write_through_storage_and_compute_in_tasks():
    assert stage_violations() == []


def test_the_stage_check_catches_each_kind(tmp_path):
    (tmp_path / "flows" / "stages").mkdir(parents=True)
    (tmp_path / "flows" / "stages" / "bad.py").write_text(
        "import json\n"
        "from scipy.spatial import cKDTree\n"
        "import numpy as np\n"
        "def run_bad(ctx):\n"
        "    T = ctx.a @ np.linalg.inv(ctx.b)\n"
        "    np.save(ctx.out_dir / 'x.npy', T)\n"
        "    (ctx.out_dir / 'y.txt').write_text(str(np.linalg.norm(T)))\n"
        "    with open(ctx.out_dir / 'z') as fh:\n"
        "        return {'sum': float(np.einsum('ij->', T))}\n"
    )
    assert stage_violations(tmp_path) == [
        "flows/stages/bad.py:1 imports json",
        "flows/stages/bad.py:2 imports scipy.spatial",
        "flows/stages/bad.py:5 calls np.linalg.inv",
        "flows/stages/bad.py:5 multiplies matrices (@)",
        "flows/stages/bad.py:6 calls np.save",
        "flows/stages/bad.py:7 calls .write_text",
        "flows/stages/bad.py:8 calls open",
        "flows/stages/bad.py:9 calls np.einsum",
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


def entry_points(root: Path = ROOT, layers=("flows", "tasks", "configs")) -> list[str]:
    """Modules other than flows/cli.py that define a top-level ``main`` or an
    ``if __name__ == "__main__":`` block."""
    found = []
    for layer in layers:
        for path in sorted((root / layer).rglob("*.py")):
            if path == root / "flows" / "cli.py":
                continue
            for node in ast.parse(path.read_text()).body:
                if isinstance(node, ast.FunctionDef) and node.name == "main":
                    found.append(f"{path.relative_to(root)}:{node.lineno} def main")
                if isinstance(node, ast.If) and "__main__" in ast.unparse(node.test):
                    found.append(f"{path.relative_to(root)}:{node.lineno} __main__")
    return found


def test_one_cli():
    """One entry point, ``mobileocc`` (flows/cli.py): every command is a subcommand of it."""
    assert entry_points() == []


def test_the_check_catches_a_second_entry_point(tmp_path):
    (tmp_path / "flows" / "bench").mkdir(parents=True)
    (tmp_path / "flows" / "bench" / "x.py").write_text(
        "def main(argv=None):\n    pass\n\n\nif __name__ == '__main__':\n    main()\n"
    )
    assert entry_points(tmp_path) == [
        "flows/bench/x.py:1 def main",
        "flows/bench/x.py:5 __main__",
    ]
