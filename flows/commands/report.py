"""The evaluation report: ``report.md`` (Markdown tables), ``results.json`` and PNG figures.

``write_report(report_dir, results, figures)`` takes the numbers the metric kernels give
(``as_dict()`` of the :mod:`tasks.metrics` dataclasses, fit numbers of :mod:`tasks.fit.metrics`)
and renders what it finds. ``results`` (JSON-like; numpy scalars / arrays allowed):

- ``title`` str, ``meta`` {name: scalar}: header lines.
- ``static``: ``StaticCounts.as_dict()`` (per_class_iou, miou, coverage, voxel / point accuracy).
- ``pedestrian_boxes``, ``pedestrian_lidar``: {sequence: ``PRCounts.as_dict()``}, "all" included.
- ``detection``: {condition: ``DetectionCounts.as_dict()``}.
- ``detection_manual_qa``: the same, counted from the manual QA table (flows/viewer/qa.py).
- ``occupancy``: ``OccupancyScores.as_dict()``, or {name: that} for several rows.
- ``fit``: {metric: value} or {row: {metric: value}} (PVE / MPJPE / PA-MPJPE in mm, MPERE).
- ``tracking``: {sequence: ``TrackingScores.as_dict()``}.
- ``fit_acceleration``: {sequence: {fits, joints / root in m/s^2 and mm/frame^2}}, "all" included;
  ``fit_tracks``: {sequence: shape spread, swaps, gap-filled bodies}; ``fit_gap_filled``.
- ``ray_iou``: {sequence and "all": RayIoU, RayIoU@t, mAVE, OccScore, rays}; ``ray_iou_per_class``
  {threshold: {class: IoU}}; ``ray_ave_per_class`` (flows/commands/evaluate_rays.py).
- ``velocity``, ``velocity_vertex_gt``: ``VelocityErrors.as_dict()`` or {name: that};
  ``velocity_by_limb``: {limb group: AVE against the per-vertex / per-person GT}.
- any other key: a table of its scalars (rows when its values are dicts).

Ratios (IoU, precision, recall, accuracy, MOTA ...) are fractions in results.json and
percentages in report.md. NaN (undefined, e.g. a class absent everywhere) is ``null`` in the JSON
and "n/a" in the tables.

``figures`` (arrays, not written to JSON):

- ``bev``: list of {"title", "pred" (X, Y, Z) uint8, "gt" (X, Y, Z) uint8, optional "mask"
  (X, Y, Z) bool mask_camera, optional "range_min" (3,) m and "voxel_size_m"}: one triptych each
  (prediction, ground truth, difference).
- ``histograms``: {name: 1-D array} or {name: {"values": array, "xlabel": str}}.
Per-class IoU bars are drawn from ``results["occupancy"]`` and ``results["static"]``.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np

from flows.commands import confusion_report
from storage.atomic import atomic_write_text, write_atomically
from tasks import conventions as C
from tasks.metrics.bev import DIFF_COLORS

_PERCENT = {
    "iou",
    "miou",
    "geometric_iou",
    "free_returns_share",
    "unclassified_share",
    "precision",
    "recall",
    "f1",
    "coverage",
    "voxel_accuracy",
    "point_accuracy",
    "mota",
    "idf1",
    "hota",
    "deta",
    "assa",
    "miss_vis",
}
_LABELS = {
    "free_returns_share": "free returns (%)",
    "unclassified_share": "unclassified (%)",
    "geometric_iou": "IoU (geom.)",
    "miou": "mIoU",
    "f1": "F1",
    "mota": "MOTA",
    "idf1": "IDF1",
    "hota": "HOTA",
    "deta": "DetA",
    "assa": "AssA",
    "miss_vis": "Miss_vis %",
    "ave_o": "AVE-O (m/s)",
    "ave_t": "AVE-T (m/s)",
    "coverage": "GT point coverage",
    "voxel_accuracy": "Voxel-level accuracy",
    "point_accuracy": "Point-level accuracy",
    "num_voxels_o": "voxels (O)",
    "num_voxels_t": "voxels (T)",
    "pred_total": "pred. voxels",
    "ref_total": "ref. voxels",
    "num_objects": "GT boxes",
    "num_voxels": "voxels",
    "ray_iou": "RayIoU",
    "ray_iou_1m": "RayIoU@1m",
    "ray_iou_2m": "RayIoU@2m",
    "ray_iou_4m": "RayIoU@4m",
    "mave": "mAVE (m/s)",
    "occ_score": "OccScore",
    "ave_o_vertex_gt": "AVE-O vs vertex GT",
    "ave_t_vertex_gt": "AVE-T vs vertex GT",
    "ave_o_person_gt": "AVE-O vs person GT",
    "ave_t_person_gt": "AVE-T vs person GT",
    "PVE_mm": "PVE (mm)",
    "MPJPE_mm": "MPJPE (mm)",
    "PA_MPJPE_mm": "PA-MPJPE (mm)",
}
_DIFF_COLORS = DIFF_COLORS  # tasks.metrics.bev: the same colours as the 3D viewer's

_HOW_TO_READ = {
    "trajectory": "The world poses each log's labels were built with (its /tf, odometry topic or "
    "LiDAR odometry) against the simulator's: ATE = RMSE of the positions after the best rigid "
    "alignment, rotation error relative to the first pose, final drift = end-pose error over the "
    "path length. Lower is better.",
    "static": "Static voxel labels against labelled ground-truth LiDAR points. IoU is per point (a point "
    "takes its voxel's label); coverage = GT points whose voxel is occupied; the accuracies are "
    "over covered points / occupied voxels holding GT points (majority GT label). Higher is better.",
    "pedestrian_boxes": "Pedestrian voxels against GT 3D boxes, camera-visible voxels only, bottom 0.1 m of each "
    "box left out. Precision: labelled pedestrian voxels inside a box; recall: occupied box "
    "voxels labelled pedestrian. Boxes hold air and feet, so both are conservative.",
    "pedestrian_lidar": "Pedestrian voxels against voxelised LiDAR body points at +-1 voxel tolerance. "
    "Precision: pedestrian voxels near a LiDAR body voxel; recall: LiDAR body voxels near "
    "a pedestrian voxel. 'all' sums the counts of every sequence.",
    "detection_manual_qa": "Manual QA (`mobileocc view --qa`, the paper's Table 4 bottom): per condition, "
    "labelled persons a reviewer marked T (correct) or W (not a person), persons the labels "
    "missed M_vis (visible) / M_occ (occluded). Recall = T / (T + M_vis), precision = "
    "T / (T + W).",
    "detection": "Per condition: T matched persons (IoU >= 0.5), M_vis / M_occ missed visible / occluded, W false "
    "positives. Recall = T / (T + M_vis), precision = T / (T + W).",
    "occupancy": "Occ3D metric over camera-visible voxels: IoU per class, mIoU over the 9 semantic classes "
    "(n/a: class in neither grid, left out of the mean; an unclassified voxel where the truth has "
    "class c counts against c), IoU (geom.) = occupied (unclassified included) vs free, "
    "unclassified share = unclassified voxels among the occupied ones.",
    "label_honesty": "Needs no ground truth. Free returns share: voxels holding this frame's LiDAR "
    "returns that the labels call free with nothing occupied among their 26 neighbours, in "
    "26-connected clusters of >= 5 such voxels, over every return-holding voxel (0 is honest: a "
    "return is a surface). Unclassified share: occupied voxels with no class (no segmenter or "
    "geometric classes) among the occupied ones; pedestrian voxels without body: a tracked "
    "person's returns with no fitted body near them. Voxels with mask_lidar = 1.",
    "fit": "Body fit errors: PVE / MPJPE in mm (lower is better), PA-MPJPE after similarity alignment, "
    "MPERE relative edge-length error (unitless).",
    "fit_acceleration": "Acceleration error of the fitted joints along their tracks (fits whose "
    "track has matched fits in the frames just before and after, of the same GT person): "
    "|a_fit - a_GT| of the second difference of world positions, mean over such fits and all "
    "24 joints, or the root (pelvis) alone; m/s^2 and mm/frame^2 at the published rate. Lower "
    "is better.",
    "fit_tracks": "Per sequence: per-track spread of the shapes (RMS distance of a track's betas to its "
    "mean, 0 = one shape per person), fits with keypoints mirrored, left / right swaps decided "
    "(flipped / kept / undecided: kept as detected), bodies filled in frames a track coasted "
    "over (and dropped: the sweep saw through them), fits warm-started.",
    "fit_gap_filled": "Bodies interpolated for frames without a detection, matched to the GT person "
    "whose pelvis is nearest (within 0.5 m): their MPJPE / PVE in mm.",
    "box_heading": "Published pedestrian box yaw of each fitted person matched to a GT person vs the GT heading, "
    "degrees (lower is better); axis off 45 share: boxes whose axis is more than 45 deg off "
    "modulo 180 (l and w swapped).",
    "box_visibility": "Visible fraction of each matched fitted person's box in cam0 as the nuScenes export "
    "computes it (from the voxel grid) vs the GT visible fraction (mesh silhouette pixels); "
    "shares of boxes in the same / a neighbouring nuScenes visibility bin, binned lower.",
    "tracking": "MOTA = 1 - (misses + false positives + id switches) / GT boxes; IDF1 = identity F1; "
    "HOTA = sqrt(DetA x AssA) averaged over IoU thresholds 0.05..0.95. Higher is better.",
    "velocity": "Absolute velocity error of pedestrian voxels (m/s, lower is better): AVE-O over voxels pedestrian "
    "in both, AVE-T over all GT pedestrian voxels (a missed voxel counts with zero velocity). "
    "Ground truth: each person's own velocity on all its voxels.",
    "velocity_vertex_gt": "AVE as above against the per-vertex ground truth: each GT pedestrian voxel moves with "
    "the mean velocity of the body surface in it (a swinging leg's voxels faster than the "
    "torso's).",
    "ray_iou": "SparseOcc / OpenOcc's RayIoU over the full grids (no masks): query rays from up to 8 LiDAR "
    "positions of the sequence (the frame's own and those over the grid, evenly thinned in time), "
    "LiDAR-like rings, 1 deg azimuth; a ray counts "
    "when its ground-truth first hit is occupied; true positive: same class and first-hit depth "
    "within 1 / 2 / 4 m; mean over classes (free excluded) and thresholds. mAVE: velocity error "
    "(m/s) at the true-positive rays at 2 m, mean over the moving classes with any (pedestrian, "
    "car, truck, two-wheeler, as the reference; our labels move pedestrians only, so a vehicle's "
    "AVE is 0 where both sides say 0); OccScore = 0.9 RayIoU + 0.1 max(1 - mAVE, 0).",
    "ray_iou_per_class": "RayIoU per class at each depth threshold (n/a: no ray hits the class on either side).",
    "velocity_by_limb": "AVE per limb group of the GT voxel (the group of its nearest GT vertex, from the body "
    "model's skinning weights), against the per-vertex GT and against the per-person GT; "
    "m/s, lower is better.",
}
_TITLES = {
    "static": "Static semantic voxels (vs GT LiDAR points)",
    "pedestrian_boxes": "Pedestrian voxels (vs GT 3D boxes)",
    "pedestrian_lidar": "Pedestrian voxels (vs LiDAR body GT)",
    "detection": "Detection robustness",
    "detection_manual_qa": "Detection robustness (manual QA)",
    "occupancy": "Semantic occupancy (Occ3D metric)",
    "fit": "Body fit accuracy",
    "fit_acceleration": "Body fit acceleration error",
    "fit_tracks": "Bodies along tracks",
    "fit_gap_filled": "Gap-filled bodies",
    "box_heading": "Pedestrian box heading (vs GT)",
    "box_visibility": "Pedestrian box visibility (vs GT)",
    "tracking": "Tracking",
    "velocity": "Pedestrian velocity (AVE)",
    "velocity_vertex_gt": "Pedestrian velocity (AVE) vs per-vertex GT",
    "velocity_by_limb": "Pedestrian velocity (AVE) per limb group",
    "trajectory": "Trajectory of robot logs (published poses vs GT)",
    "label_honesty": "Label honesty (no ground truth needed)",
    "ray_iou": "RayIoU and OccScore (ray-based, SparseOcc / OpenOcc)",
    "ray_iou_per_class": "RayIoU per class",
    "ray_ave_per_class": "Ray AVE per moving class (m/s, true positives at 2 m)",
}
_COLUMNS = {
    "pedestrian_boxes": ["precision", "recall", "f1", "pred_total", "ref_total"],
    "pedestrian_lidar": ["precision", "recall", "f1", "pred_total", "ref_total"],
    "detection": ["T", "M_vis", "M_occ", "W", "recall", "precision", "miss_vis"],
    "detection_manual_qa": ["T", "M_vis", "M_occ", "W", "recall", "precision", "miss_vis"],
    "tracking": ["mota", "idf1", "hota", "deta", "assa", "switches", "num_objects"],
    "label_honesty": [
        "free_returns_share",
        "free_return_voxels",
        "return_voxels",
        "unclassified_share",
        "occupied_voxels",
        "pedestrian_voxels",
        "pedestrian_voxels_without_body",
    ],
    "velocity": ["ave_o", "ave_t", "num_voxels_o", "num_voxels_t"],
    "velocity_vertex_gt": ["ave_o", "ave_t", "num_voxels_o", "num_voxels_t"],
}
_MAX_PNG_BYTES = 300_000
_TITLES.update(confusion_report.TITLES)
_HOW_TO_READ.update(confusion_report.HOW_TO_READ)


class ReportError(ValueError):
    """Results or figures that the report writer cannot render."""


# ---- JSON ---------------------------------------------------------------------------------------


def to_jsonable(value):
    """Plain JSON types: numpy scalars / arrays to Python, NaN / inf to None, tuples to lists."""
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        v = float(value)
        return v if math.isfinite(v) else None
    if value is None or isinstance(value, str):
        return value
    raise ReportError(f"results: cannot write a {type(value).__name__} ({value!r}) to JSON")


def write_json(path: Path | str, value) -> Path:
    """``value`` (:func:`to_jsonable`) as indented JSON at ``path``, folders made."""
    return atomic_write_text(path, json.dumps(to_jsonable(value), indent=1) + "\n")


# ---- Markdown -----------------------------------------------------------------------------------


def _fmt(key: str, value) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    if isinstance(value, bool):
        return str(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if (
            key in _PERCENT
            or key.endswith("_iou")
            or key in C.CLASS_NAMES
            or key.startswith("ray_iou_")
            or key == "occ_score"
        ):
            return f"{100 * value:.1f}"
        return f"{value:.1f}" if abs(value) >= 10 else f"{value:.3f}"
    return str(value)


def _label(key: str) -> str:
    return _LABELS.get(key, key.replace("_", " ").capitalize() if key.islower() else key)


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join([" --- "] * len(header)) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def _as_rows(section: dict) -> dict[str, dict]:
    """{row: {column: value}}: a section whose values are all dicts is already rows; else one row."""
    if section and all(isinstance(v, dict) for v in section.values()):
        return section
    return {"all": section}


def _flatten(row: dict) -> dict:
    """Inline per_class_iou into the row (class columns after the summary columns)."""
    out = {k: v for k, v in row.items() if not isinstance(v, dict)}
    for v in row.values():
        if isinstance(v, dict):
            out.update(v)
    return out


def _rows_table(name: str, section: dict) -> str:
    rows = {r: _flatten(v) for r, v in _as_rows(section).items()}
    cols = _COLUMNS.get(name)
    if cols is None:
        cols = []
        for v in rows.values():
            cols += [k for k in v if k not in cols]
    cols = [c for c in cols if any(c in v for v in rows.values())]
    header = [""] + [_label(c) for c in cols]
    body = [[str(r)] + [_fmt(c, v.get(c)) for c in cols] for r, v in rows.items()]
    return _table(header, body)


def _static_table(section: dict) -> str:
    iou = section.get("per_class_iou", {})
    per = " / ".join(_fmt("iou", v) for v in iou.values())
    rows = [[f"mIoU ({' / '.join(iou)})", f"{_fmt('miou', section.get('miou'))} ({per})"]]
    for key in ("coverage", "voxel_accuracy", "point_accuracy"):
        if key in section:
            rows.append([_label(key), _fmt(key, section[key])])
    for key in ("num_points", "num_voxels"):
        if key in section:
            rows.append([key.replace("_", " "), _fmt(key, section[key])])
    return _table(["metric", "value (%)"], rows)


def _transposed(name: str, section: dict) -> str:
    """Paper layout for the per-sequence P / R / F1 tables: metrics as rows, sequences as columns."""
    seqs = list(section)
    keys = ["precision", "recall", "f1"]
    rows = [
        [_label(k) if k != "f1" else "F1"] + [_fmt(k, section[s].get(k)) for s in seqs]
        for k in keys
    ]
    counts = [
        ["pred / ref voxels"]
        + [
            f"{section[s].get('pred_total', 'n/a')} / {section[s].get('ref_total', 'n/a')}"
            for s in seqs
        ]
    ]
    return _table(["Seq"] + [str(s) for s in seqs], rows + counts)


def _section_markdown(name: str, section, figure_names: list[str]) -> str:
    title = _TITLES.get(name, name.replace("_", " ").capitalize())
    parts = [f"## {title}", ""]
    if name in _HOW_TO_READ:
        parts += [f"*How to read this:* {_HOW_TO_READ[name]}", ""]
    if not isinstance(section, dict):
        parts.append(f"{_fmt(name, section)}")
    elif name == "static":
        parts.append(_static_table(section))
    elif name in confusion_report.SECTIONS:
        parts.append(confusion_report.markdown(name, section))
    elif name in ("pedestrian_boxes", "pedestrian_lidar") and all(
        isinstance(v, dict) for v in section.values()
    ):
        parts.append(_transposed(name, section))
    else:
        parts.append(_rows_table(name, section))
    for fig in figure_names:
        parts += ["", f"![{fig}](figures/{fig}.png)"]
    return "\n".join(parts) + "\n"


def section_table(name: str, section) -> str:
    """One results section (to_jsonable form) as its Markdown table, without the how-to-read
    line (the console summary of `mobileocc evaluate`)."""
    return _rows_table(name, section) if isinstance(section, dict) else _fmt(name, section)


# ---- figures ------------------------------------------------------------------------------------


def _new_figure(w: float, h: float):
    from matplotlib.figure import Figure  # Agg canvas, no pyplot global state

    return Figure(figsize=(w, h), dpi=100, layout="constrained")


def _save(fig, path: Path) -> Path:
    with write_atomically(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
        if tmp.stat().st_size > _MAX_PNG_BYTES:  # keep the report light: retry smaller
            fig.savefig(tmp, dpi=70, format="png")
    return path


def _iou_bars(path: Path, per_class: dict, miou, title: str) -> Path:
    names = list(per_class)
    vals = np.array(
        [np.nan if v is None else float(v) for v in per_class.values()], dtype=np.float64
    )
    colors = [
        C.CLASS_COLORS[C.CLASS_NAMES.index(n)] / 255.0 if n in C.CLASS_NAMES else (0.5, 0.5, 0.5)
        for n in names
    ]
    fig = _new_figure(6.5, 3.2)
    ax = fig.subplots()
    x = np.arange(len(names))
    ax.bar(x, np.nan_to_num(100 * vals), color=colors, edgecolor="black", linewidth=0.6)
    for xi, v in zip(x, vals):
        ax.text(
            xi,
            (0 if np.isnan(v) else 100 * v) + 1.5,
            "n/a" if np.isnan(v) else f"{100 * v:.1f}",
            ha="center",
            va="bottom",
            fontsize=8,
        )
    if miou is not None and not (isinstance(miou, float) and math.isnan(miou)):
        ax.axhline(100 * float(miou), color="black", linestyle="--", linewidth=1)
        ax.text(
            len(names) - 0.5,
            100 * float(miou) + 1.5,
            f"mIoU {100 * float(miou):.1f}",
            ha="right",
            fontsize=8,
        )
    ax.set_xticks(x, names, rotation=30, ha="right", fontsize=8)
    ax.set_ylim(0, 110)
    ax.set_ylabel("IoU (%)")
    ax.set_title(title, fontsize=10)
    return _save(fig, path)


def _histogram(path: Path, name: str, values, xlabel: str) -> Path:
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    v = v[np.isfinite(v)]
    fig = _new_figure(5.0, 3.0)
    ax = fig.subplots()
    if len(v):
        ax.hist(
            v, bins=min(40, max(5, len(v) // 5)), color="#4c72b0", edgecolor="white", linewidth=0.4
        )
        ax.axvline(
            np.mean(v), color="black", linestyle="--", linewidth=1, label=f"mean {np.mean(v):.3g}"
        )
        ax.axvline(
            np.median(v),
            color="#dd8452",
            linestyle=":",
            linewidth=1.5,
            label=f"median {np.median(v):.3g}",
        )
        ax.legend(fontsize=8)
    else:
        ax.text(0.5, 0.5, "no values", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("count")
    ax.set_title(f"{name} (n = {len(v)})", fontsize=10)
    return _save(fig, path)


def _class_rgb(top: np.ndarray) -> np.ndarray:
    rgb = np.empty(top.shape + (3,), dtype=np.uint8)
    known = top != C.UNLABELED
    rgb[known] = C.CLASS_COLORS[np.minimum(top[known], C.FREE)]
    rgb[~known] = C.UNKNOWN_COLOR
    return rgb


def _bev_triptych(path: Path, sample: dict) -> Path:
    from matplotlib.patches import Patch

    from tasks.metrics.bev import DIFF_NAMES, bev_difference, bev_top_labels

    try:
        pred, gt = np.asarray(sample["pred"]), np.asarray(sample["gt"])
    except KeyError as err:
        raise ReportError(
            f"figures['bev'] sample {sample.get('title', '?')!r}: missing {err}"
        ) from None
    mask = sample.get("mask")
    gt_top = bev_top_labels(gt, mask)
    pred_top = bev_top_labels(pred, mask)
    diff = bev_difference(pred, gt, mask)
    X, Y = gt_top.shape
    lo = np.asarray(sample.get("range_min", (0.0, 0.0, 0.0)), dtype=np.float64)
    vs = float(sample.get("voxel_size_m", 1.0))
    unit = "m" if "voxel_size_m" in sample else "voxels"
    # x (forward) up, y (left) to the left: rows = x descending, columns = y descending
    extent = (lo[1] + Y * vs, lo[1], lo[0], lo[0] + X * vs)
    flip = lambda a: np.flip(a, axis=(0, 1))  # noqa: E731
    fig = _new_figure(11.0, 4.6)
    axes = fig.subplots(1, 3)
    panels = [
        (_class_rgb(pred_top), "prediction"),
        (_class_rgb(gt_top), "ground truth"),
        (_DIFF_COLORS[diff], "difference"),
    ]
    for ax, (img, name) in zip(axes, panels):
        ax.imshow(flip(img), extent=extent, interpolation="nearest")
        ax.set_title(name, fontsize=10)
        ax.set_xlabel(f"y ({unit}, left +)", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0].set_ylabel(f"x ({unit}, forward)", fontsize=8)
    present = sorted(set(np.unique(pred_top)) | set(np.unique(gt_top)))
    cls_handles = [
        Patch(facecolor=C.CLASS_COLORS[c] / 255.0, edgecolor="black", label=C.CLASS_NAMES[c])
        for c in present
        if c < C.FREE
    ]
    cls_handles += [
        Patch(facecolor="white", edgecolor="black", label="free"),
        Patch(facecolor=C.UNKNOWN_COLOR / 255.0, edgecolor="black", label="unknown"),
    ]
    diff_handles = [
        Patch(
            facecolor=_DIFF_COLORS[k] / 255.0,
            edgecolor="black",
            label=f"{DIFF_NAMES[k]} ({int(np.sum(diff == k))} columns)",
        )
        for k in (1, 2, 3, 4, 5)
    ]
    fig.legend(
        handles=cls_handles,
        loc="outside lower left",
        ncol=4,
        fontsize=7,
        frameon=False,
        title="classes (left, middle)",
        title_fontsize=7,
    )
    fig.legend(
        handles=diff_handles,
        loc="outside lower right",
        ncol=3,
        fontsize=7,
        frameon=False,
        title="difference (right)",
        title_fontsize=7,
    )
    fig.suptitle(
        f"{sample.get('title', 'sample')}: top-down view, highest occupied voxel per column",
        fontsize=10,
    )
    return _save(fig, path)


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "_", str(text)).strip("_").lower() or "figure"


# ---- entry point --------------------------------------------------------------------------------


def write_report(report_dir, results: dict, figures: dict | None = None) -> Path:
    """Write ``report.md``, ``results.json`` and ``figures/*.png`` under ``report_dir``.

    results / figures as in the module docstring. Returns the path of ``report.md``.
    """
    if not isinstance(results, dict):
        raise ReportError(f"results must be a dict of sections, got {type(results).__name__}")
    figures = figures or {}
    out = Path(report_dir)
    fig_dir = out / "figures"
    fig_dir.mkdir(parents=True, exist_ok=True)
    jsonable = to_jsonable(results)
    atomic_write_text(out / "results.json", json.dumps(jsonable, indent=2, allow_nan=False) + "\n")

    section_figs: dict[str, list[str]] = {}
    for name in ("occupancy", "static"):
        sec = jsonable.get(name)
        if (
            isinstance(sec, dict)
            and isinstance(sec.get("per_class_iou"), dict)
            and sec["per_class_iou"]
        ):
            fig = f"{name}_class_iou"
            _iou_bars(
                fig_dir / f"{fig}.png",
                sec["per_class_iou"],
                sec.get("miou"),
                f"{_TITLES[name]}: IoU per class",
            )
            section_figs.setdefault(name, []).append(fig)

    md = [f"# {results.get('title', 'mobileocc evaluation report')}", ""]
    meta = results.get("meta") or {}
    md += [f"- **{k}**: {v}" for k, v in jsonable.get("meta", {}).items()] + ([""] if meta else [])
    md += [
        "Ratios are percentages; n/a = undefined (nothing to count). Numbers: `results.json`.",
        "",
    ]
    for name, section in jsonable.items():
        if name in ("title", "meta"):
            continue
        md.append(_section_markdown(name, section, section_figs.get(name, [])))

    samples = figures.get("bev") or []
    if samples:
        md += [
            "## Sample frames (bird's-eye view)",
            "",
            "*How to read this:* each column of the grid seen from above, coloured by its highest occupied "
            "voxel (grey: never seen, white: free). Difference, voxel by voxel in the column, its most "
            "frequent error: orange wrong class, blue missed (occupied in ground truth only), red extra "
            "(occupied in the prediction only); green: every occupied voxel right.",
            "",
        ]
        for k, sample in enumerate(samples):
            fig = f"bev_{k:02d}_{_slug(sample.get('title', 'sample'))}"
            _bev_triptych(fig_dir / f"{fig}.png", sample)
            md += [f"![{sample.get('title', fig)}](figures/{fig}.png)", ""]
    hists = figures.get("histograms") or {}
    if hists:
        md += [
            "## Error distributions",
            "",
            "*How to read this:* histogram of per-item errors; dashed line mean, dotted line median.",
            "",
        ]
        for name, spec in hists.items():
            values, xlabel = (
                (spec.get("values"), spec.get("xlabel", name))
                if isinstance(spec, dict)
                else (spec, name)
            )
            fig = f"hist_{_slug(name)}"
            _histogram(fig_dir / f"{fig}.png", name, values, xlabel)
            md += [f"![{name}](figures/{fig}.png)", ""]
    return atomic_write_text(out / "report.md", "\n".join(md).rstrip() + "\n")
