"""One home per default: a kernel takes its settings dataclass, never a loose keyword with a
default of its own.

The settings dataclasses are the ones the config sections are made of (configs/schema.py). A
function anywhere in tasks/ fails the check when a parameter

- has the name of a settings field and a default (a second default: ``fit_persons(nn_every=1)``
  where FitSettings says 5), or
- defaults to a settings field or a settings constant (``camera_method=FuseSettings.
  camera_method``, ``weights=FIT_PRESETS["3dpw"]``): the kernel should take the settings object.

A parameter may default to a whole settings object, ``params: TrackerParams = TrackerParams()``:
that is the home itself. Where the same name means something else, the name changes
(``fit_persons``' floor of LiDAR points is ``LIDAR_MIN_POINTS``, not ``min_points``); the few
names that stay are listed in OTHER_MEANING with what they mean.
"""

from __future__ import annotations

import ast
import dataclasses
import typing
from pathlib import Path

from configs.schema import Config

ROOT = Path(__file__).resolve().parents[1]

#: names every generator and tensor helper has: a function's own ``seed`` or ``device`` is not
#: FitSettings.seed / .device (fit_persons takes those in its FitSettings)
GENERIC = {"seed", "device"}
#: (function or dataclass, parameter): the same name as a setting, another meaning, kept; a name
#: several modules define is written module.function
OTHER_MEANING: dict[tuple[str, str], str] = {
    # a detection matches the ground truth at IoU 0.5: the benchmarks' definition (OC-SORT's
    # association gate is TrackerParams.iou_threshold)
    ("match_boxes", "iou_threshold"): "the benchmark's matching IoU",
    ("detection_counts", "iou_threshold"): "the benchmark's matching IoU",
    ("tracking_scores", "iou_threshold"): "the benchmark's matching IoU",
    # a projection's own near plane (PersonPointParams.min_depth_m is the person-points step's)
    ("project", "min_depth_m"): "check-data's sanity projection",
    ("stereo_row_error_px", "min_depth_m"): "check-data's stereo check",
    ("static_map.project_points", "min_depth_m"): "the static map's projection",
    ("project_lidar_boxes", "min_depth_m"): "LiDAR boxes as image proposals",
    # the Mask2Former export's input (None: the export's); semantic.input_size is the segmenter's
    ("QueryInstanceMasks.__init__", "input_size"): "the mask model's input size",
    # the simulated world: the sensors' range, the ground-truth grid (simulate, not a stage)
    ("LidarSpec", "max_range_m"): "a simulated LiDAR's range",
    ("LidarNoise", "max_range_m"): "a simulated LiDAR's range",
    ("GridSpec", "voxel_size_m"): "the simulator's ground-truth grid (tasks/sim/groundtruth.py)",
}


def settings_classes() -> dict[str, type]:
    """The kernels' settings dataclasses: every plain dataclass a config section is made of."""
    found: dict[str, type] = {}

    def walk(cls: type) -> None:
        for base in cls.__mro__:
            if dataclasses.is_dataclass(base) and base.__module__.startswith("tasks."):
                found[base.__name__] = base
        for tp in typing.get_type_hints(cls).values():
            for arg in (tp, *typing.get_args(tp)):
                if isinstance(arg, type) and arg.__module__ == "configs.schema":
                    walk(arg)

    walk(Config)
    for cls in list(found.values()):  # and what the kernels build of them (FitWeights)
        found |= {s.__name__: s for s in cls.__subclasses__() if s.__module__.startswith("tasks.")}
    return found


def _settings_constants(tree: ast.Module, classes: set[str]) -> set[str]:
    """Module-level names bound to settings objects (``FIT_PRESETS = {"3dpw": FitWeights(...)}``)."""
    names = set()
    for node in tree.body:
        targets = (
            [node.target]
            if isinstance(node, ast.AnnAssign)
            else node.targets
            if isinstance(node, ast.Assign)
            else []
        )
        value = getattr(node, "value", None)
        calls = [n for n in ast.walk(value) if isinstance(n, ast.Call)] if value else []
        if any(isinstance(c.func, ast.Name) and c.func.id in classes for c in calls):
            names |= {t.id for t in targets if isinstance(t, ast.Name)}
    return names


def _signature_defaults(node: ast.AST) -> list[tuple[str, ast.expr]]:
    """(parameter, default) of a function, or (field, default) of a dataclass."""
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
        a = node.args
        positional = a.posonlyargs + a.args
        pairs = list(zip(positional[len(positional) - len(a.defaults) :], a.defaults))
        pairs += [(p, d) for p, d in zip(a.kwonlyargs, a.kw_defaults) if d is not None]
        return [(p.arg, d) for p, d in pairs]
    if isinstance(node, ast.ClassDef) and any(
        "dataclass" in ast.unparse(d) for d in node.decorator_list
    ):
        return [
            (s.target.id, s.value)
            for s in node.body
            if isinstance(s, ast.AnnAssign) and isinstance(s.target, ast.Name) and s.value
        ]
    return []


def _scopes(tree: ast.AST, prefix: str = ""):
    """(qualified name, node) of every function and class, methods as ``Class.method``."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            name = f"{prefix}{node.name}"
            yield name, node
            yield from _scopes(node, f"{name}.")
        else:
            yield from _scopes(node, prefix)


def violations(sources: dict[str, str], classes: dict[str, type]) -> list[str]:
    """``path:function(parameter=default)``: what the module docstring forbids."""
    fields = {f.name for cls in classes.values() for f in dataclasses.fields(cls)}
    trees = {path: ast.parse(text) for path, text in sources.items()}
    constants = set().union(*(_settings_constants(t, set(classes)) for t in trees.values()))
    refers = set(classes) | constants
    found = []
    for path, tree in trees.items():
        for name, node in _scopes(tree):
            if name in classes:
                continue  # the home itself
            for param, default in _signature_defaults(node):
                whole = (  # ``X()``: the settings object with its home's defaults
                    isinstance(default, ast.Call)
                    and isinstance(default.func, ast.Name)
                    and default.func.id in classes
                    and not default.args
                    and not default.keywords
                )
                named = {n.id for n in ast.walk(default) if isinstance(n, ast.Name)}
                restated = param in fields and param not in GENERIC
                if (restated or named & refers) and not whole:
                    where = {(name, param), (f"{Path(path).stem}.{name}", param)}
                    if not where & set(OTHER_MEANING):
                        found.append(f"{path}:{name}({param}={ast.unparse(default)})")
    return found


def _tasks_sources() -> dict[str, str]:
    return {str(p.relative_to(ROOT)): p.read_text() for p in sorted((ROOT / "tasks").rglob("*.py"))}


def test_no_kernel_restates_a_settings_default():
    assert violations(_tasks_sources(), settings_classes()) == []


def test_other_meanings_are_still_there():
    """An entry of OTHER_MEANING whose function or parameter is gone is a stale excuse."""
    params = {
        (qualified, param)
        for path, text in _tasks_sources().items()
        for name, node in _scopes(ast.parse(text))
        for param, _ in _signature_defaults(node)
        for qualified in (name, f"{Path(path).stem}.{name}")
    }
    assert set(OTHER_MEANING) <= params, set(OTHER_MEANING) - params


def test_the_check_catches_planted_defaults():
    classes = settings_classes()
    assert {"FitSettings", "FitWeights", "FuseSettings", "MapParams", "OracleNoise"} <= set(classes)
    planted = {
        "tasks/a.py": (
            "from tasks.fit.settings import FitSettings\n"
            "PRESETS = {'x': FitSettings(iterations=3)}\n"
            "def fit(x, nn_every=1): ...\n"
            "def fit2(x, *, rate=FitSettings.learning_rate): ...\n"
            "def fit3(x, settings=PRESETS['x']): ...\n"
            "def fine(x, settings=FitSettings(), nn_every_other=3, *, lam): ...\n"
            "class K:\n"
            "    def __init__(self, camera_pixel_stride=None): ...\n"
            "@dataclass\n"
            "class D:\n"
            "    min_pose_flag: float = 0.3\n"
            "    other: float = 0.3\n"
        )
    }
    assert violations(planted, classes) == [
        "tasks/a.py:fit(nn_every=1)",
        "tasks/a.py:fit2(rate=FitSettings.learning_rate)",
        "tasks/a.py:fit3(settings=PRESETS['x'])",
        "tasks/a.py:K.__init__(camera_pixel_stride=None)",
        "tasks/a.py:D(min_pose_flag=0.3)",
    ]
