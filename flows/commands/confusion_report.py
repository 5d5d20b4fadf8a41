"""The evaluation's per-class sections: voxel counts beside the IoU, confusion matrices and where the
wrong voxels lie (tasks/metrics/confusion.py), in results.json, report.md and on the console.

``sections(occupancy, locations)`` turns the per-sequence Occ3D confusion matrices
(:class:`tasks.metrics.occupancy.OccupancyMetric`) and error locations
(:class:`tasks.metrics.confusion.ErrorLocations`) into three results sections:

- ``occupancy_classes``: {"all" | sequence: {class: {iou, gt_voxels, labelled_voxels,
  true_voxels}}}: a 0.0 IoU from three stray voxels reads differently from a class that is missed;
- ``confusion``: {"all" | sequence: {"classes": [names], "matrix": rows ground truth, columns
  labels}} over the camera-visible voxels;
- ``error_locations``: {"all" | sequence: {class: {"false" | "missed": {location: voxels}}}}.

:func:`markdown` renders one of them for report.md (flows/commands/report.py calls it),
:func:`console_text` the confusion matrices and error locations for ``mobileocc evaluate``.
"""

from __future__ import annotations

import numpy as np

from tasks import conventions as C
from tasks.metrics.confusion import KINDS, LOCATIONS, ErrorLocations, class_counts

SECTIONS = ("occupancy_classes", "confusion", "error_locations")
TITLES = {
    "occupancy_classes": "Occupancy per class: IoU beside the voxel counts",
    "confusion": "Occupancy confusion matrices",
    "error_locations": "Where the wrong voxels lie",
}
HOW_TO_READ = {
    "occupancy_classes": "Occ3D IoU per class (camera-visible voxels) with the ground-truth (GT) and "
    "labelled (lab.) voxel counts behind it, all sequences and each: an IoU of 0.0 with a "
    "handful of voxels is a few strays, with thousands a missed class.",
    "confusion": "Camera-visible voxels, rows ground truth, columns labels, per sequence and summed.",
    "error_locations": "For each class, its false voxels (labelled the class, another in the ground truth) "
    "and missed voxels (the class in the ground truth, labelled otherwise), by where they lie "
    "relative to the ground truth's voxels of the class (for missed ones: the labelled ones): "
    "touching one that is farther from the LiDAR (sensor side: a surface marked in front of "
    "where it is), touching one otherwise (far side), on the LiDAR ray through it within 3 "
    "voxels (a range error), elsewhere (a wrong label, an invented or missed object).",
}
_SHORT = {
    "adjacent_sensor_side": "sensor side",
    "adjacent_far_side": "far side",
    "along_ray": "along ray",
    "elsewhere": "elsewhere",
}


def sections(occupancy: dict, locations: dict[str, ErrorLocations]) -> dict:
    """The three results sections from {sequence: OccupancyMetric} and {sequence:
    ErrorLocations} (module docstring); "all" sums the sequences."""
    if not occupancy:
        return {}
    names = list(C.CLASS_NAMES)
    mats = {s: np.asarray(m.confusion, np.int64) for s, m in occupancy.items()}
    mats = {"all": sum(mats.values()), **mats}
    locs = dict(locations)
    if locs:
        total = ErrorLocations()
        for v in locs.values():
            total = total + v
        locs = {"all": total, **locs}
    return {
        "occupancy_classes": {s: class_counts(m) for s, m in mats.items()},
        "confusion": {s: {"classes": names, "matrix": m.tolist()} for s, m in mats.items()},
        "error_locations": {s: v.as_dict() for s, v in locs.items()},
    }


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join([" --- "] * len(header)) + "|"]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows])


def _iou(v) -> str:
    return "n/a" if v is None or (isinstance(v, float) and np.isnan(v)) else f"{100 * v:.1f}"


def _classes_md(section: dict) -> str:
    seqs = list(section)
    header = ["class"] + [f"{h} {s}" for s in seqs for h in ("IoU", "GT", "lab.")]
    rows = []
    for name in C.CLASS_NAMES[: C.FREE]:
        row = [name]
        for s in seqs:
            d = section[s].get(name, {})
            row += [
                _iou(d.get("iou")),
                str(d.get("gt_voxels", 0)),
                str(d.get("labelled_voxels", 0)),
            ]
        rows.append(row)
    return _table(header, rows)


def _confusion_md(section: dict) -> str:
    parts = []
    for s, v in section.items():
        names, m = v["classes"], v["matrix"]
        rows = [[f"**{names[i]}**"] + [str(x) for x in m[i]] for i in range(len(names))]
        parts += [f"Sequence {s}:" if s != "all" else "All sequences:", ""]
        parts += [_table(["GT \\ label"] + list(names), rows), ""]
    return "\n".join(parts).rstrip()


def _locations_md(section: dict) -> str:
    parts = []
    header = ["class"] + [f"{k} {_SHORT[loc]}" for k in KINDS for loc in LOCATIONS]
    for s, v in section.items():
        rows = [
            [name] + [str(v[name][k][loc]) for k in KINDS for loc in LOCATIONS]
            for name in C.CLASS_NAMES[: C.FREE]
            if name in v
        ]
        parts += [f"Sequence {s}:" if s != "all" else "All sequences:", ""]
        parts += [_table(header, rows) if rows else "no wrong voxel", ""]
    return "\n".join(parts).rstrip()


def markdown(name: str, section: dict) -> str:
    """The report.md body (tables) of one of :data:`SECTIONS`."""
    if name == "occupancy_classes":
        return _classes_md(section)
    if name == "confusion":
        return _confusion_md(section)
    if name == "error_locations":
        return _locations_md(section)
    raise ValueError(f"not a per-class section: {name!r}")


def console_text(results: dict) -> str:
    """Per-class counts, the confusion matrices and the error locations as plain text (the
    Markdown tables), '' when the results have no occupancy."""
    out = []
    for name in SECTIONS:
        if results.get(name):
            out += [f"## {TITLES[name]}", "", markdown(name, results[name]), ""]
    return "\n".join(out).rstrip()
