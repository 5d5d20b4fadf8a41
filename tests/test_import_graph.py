"""No import cycle among our modules: the graph of flows/, tasks/, storage/ and configs/ built from
the source. Imports inside functions count (they close a cycle as surely as top-level ones, only
later); relative imports are resolved; ``from pkg import name`` is an edge to the submodule
``pkg.name`` when ``name`` is one, else to ``pkg``. A package's ``__init__`` is a module of its own
(importing ``a.b`` is an edge to ``a.b`` only: Python tolerates a submodule importing its own
half-initialised package, so parents are no edges)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("flows", "tasks", "storage", "configs")


def module_files(root: Path, packages=PACKAGES) -> dict[str, tuple[Path, bool]]:
    """dotted module name -> (file, is a package's __init__)."""
    found = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            is_init = parts[-1] == "__init__"
            found[".".join(parts[:-1] if is_init else parts)] = (path, is_init)
    return found


def _imported(name: str, is_init: bool, node: ast.AST, known) -> set[str]:
    """The modules of ours one import statement of module ``name`` imports."""
    if isinstance(node, ast.Import):
        return {a.name for a in node.names if a.name in known}
    if not isinstance(node, ast.ImportFrom):
        return set()
    base = node.module or ""
    if node.level:  # relative: from the module's package, one level up per extra dot
        package = name.split(".") if is_init else name.split(".")[:-1]
        package = package[: len(package) - (node.level - 1)]
        base = ".".join(package + ([node.module] if node.module else []))
    out = set()
    for alias in node.names:
        if f"{base}.{alias.name}" in known:
            out.add(f"{base}.{alias.name}")
        elif base in known:
            out.add(base)
    return out


def import_graph(root: Path = ROOT, packages=PACKAGES) -> dict[str, set[str]]:
    """module -> the modules of ours it imports anywhere in its source."""
    known = module_files(root, packages)
    graph = {}
    for name, (path, is_init) in known.items():
        edges = set()
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            edges |= _imported(name, is_init, node, known)
        graph[name] = edges - {name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle ``[a, b, ..., a]`` per strongly connected group of modules (Tarjan's algorithm,
    then the shortest way back to the group's first module)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    groups: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while not group or group[-1] != v:
                group.append(stack.pop())
            if len(group) > 1:
                groups.append(sorted(group))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return [_way_back(group[0], graph, set(group)) for group in groups]


def _way_back(start: str, graph: dict[str, set[str]], members: set[str]) -> list[str]:
    """The shortest cycle from ``start`` through ``members`` (breadth first)."""
    parent: dict[str, str | None] = {start: None}
    queue = [start]
    for v in queue:
        for w in sorted(graph[v] & members):
            if w == start:
                path = [v]
                while parent[path[-1]] is not None:
                    path.append(parent[path[-1]])
                return [*reversed(path), start]
            if w not in parent:
                parent[w] = v
                queue.append(w)
    raise AssertionError(f"{start} is in no cycle")


def test_no_import_cycle():
    found = cycles(import_graph())
    assert not found, "import cycles:\n" + "\n".join(" -> ".join(c) for c in found)


def test_the_graph_resolves_imports_and_finds_a_planted_cycle(tmp_path):
    pkg = tmp_path / "flows"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("LIMIT = 3\n")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "a.py").write_text("def f():\n    from flows import b  # a module: the edge is a -> b\n")
    (pkg / "b.py").write_text("from .sub import c\nfrom flows import LIMIT\n")
    (pkg / "sub" / "c.py").write_text("import flows.a\nfrom .. import LIMIT\n")
    (pkg / "sub" / "d.py").write_text("from . import c\n")
    graph = import_graph(tmp_path, ("flows",))
    assert graph == {
        "flows": set(),
        "flows.a": {"flows.b"},
        "flows.b": {"flows.sub.c", "flows"},
        "flows.sub": set(),
        "flows.sub.c": {"flows.a", "flows"},
        "flows.sub.d": {"flows.sub.c"},
    }
    assert cycles(graph) == [["flows.a", "flows.b", "flows.sub.c", "flows.a"]]
    (pkg / "sub" / "c.py").write_text("from .. import LIMIT\n")  # the cycle broken
    assert cycles(import_graph(tmp_path, ("flows",))) == []
