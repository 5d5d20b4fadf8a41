"""``mobileocc evaluate --labels coda``: label quality against CODa's own annotations (the paper's
label-quality table, protocol of its "Occupancy Label Quality" section).

- Static: every published frame with a ``3d_semantic`` file; its labelled points (CODa terrain ids
  mapped to our classes by :mod:`tasks.metrics.coda_labels`; Unlabeled / Unknown ignored) moved to
  the base frame and looked up in the frame's grid (:func:`tasks.metrics.static.static_counts`:
  per-class IoU, mIoU over the classes present, GT point coverage, point / voxel accuracy; a
  point in a free voxel takes the voxel 3 ``map.surface_noise_m`` further along its ray when that
  one is occupied, as in the synthetic evaluation).
- Pedestrians vs boxes: the frame's ``3d_bbox`` boxes whose class maps to pedestrian, in the base
  frame (yaw only: the grid test is yaw-oriented; CODa pedestrian boxes have roll / pitch ~ 0),
  camera-visible voxels (mask_camera), bottom 0.1 m of each box left out
  (:func:`tasks.metrics.pedestrian.pedestrian_box_counts`).
- Pedestrians vs LiDAR body: the sweep's points inside those boxes (full r / p / y box, above the
  bottom 0.1 m, projecting into the camera), voxelised, against the pedestrian voxels in the camera
  frustum at +-1 voxel (:func:`tasks.metrics.pedestrian.pedestrian_lidar_counts`).

The frames are read through the CODa reader with the dataset settings recorded in
``OUT/manifest.json`` (lidar source, ranges, frame selection), from ``data`` (default: the
recorded ``dataset.root``). Boxes the reader skipped (storage.sources.coda.read_boxes) and class names
the mapping does not know are counted in the report's "labels" section.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flows.commands.evaluate import (
    _boxes_to_base,
    _frustum,
    _in_image,
    open_for_evaluation,
    open_recorded_sequence,
)
from flows.commands.report import to_jsonable, write_report
from tasks import conventions as C
from tasks.geometry import points_in_boxes, transform_points
from tasks.metrics._common import PRCounts
from tasks.metrics.coda_labels import box_class, semantic_to_classes
from tasks.metrics.pedestrian import (
    pedestrian_box_counts,
    pedestrian_lidar_counts,
    voxelize_points,
)
from tasks.metrics.static import StaticCounts, static_counts
from tasks.occupancy.settings import MapParams

#: the bottom of each pedestrian box left out (the paper: "exclude the bottom 0.1 m")
BOTTOM_EXCLUDE_M = 0.1


def _sum(values, zero):
    total = zero
    for v in values:
        total = total + v
    return total


def evaluate_coda(
    dataset: Path, data: Path | None, report_dir: Path, sample_frames: int = 0
) -> dict:
    """Evaluate the dataset at ``dataset`` (OUT) against the CODa labels of the raw data at
    ``data`` (None: the recorded dataset.root). Writes report.md and results.json under
    ``report_dir``; returns the results dict."""

    out, manifest, config, root, ds = open_for_evaluation(dataset, data)
    camera = ((config.get("dataset") or {}).get("camera")) or "cam0"
    static, boxes, lidar = {}, {}, {}
    labels = {
        "frames": 0,
        "frames with 3d_semantic": 0,
        "frames with 3d_bbox": 0,
        "pedestrian boxes": 0,
        "boxes skipped (malformed)": 0,
        "boxes of unknown class": 0,
    }
    unknown: set[str] = set()
    for seq in ds.sequences:
        coda = open_recorded_sequence(config, root, seq)
        arrays = ds.arrays(seq, lazy="zarr")
        attrs = ds.attrs(seq)
        range_min = np.asarray(attrs["range_min"], np.float64)
        vs = float(attrs["voxel_size_m"])
        shape = tuple(arrays["semantics"].shape[1:4])
        cam = coda.info.calibration.cameras[camera]
        T_bl = coda.info.calibration.T_base_from_lidar
        frustum = _frustum(shape, range_min, vs, T_bl, cam)
        # a return up to 3 sigma of range noise in front of its surface belongs to its voxel
        noise_tol = 3 * float(
            (config.get("map") or {}).get("surface_noise_m", MapParams.surface_noise_m)
        )
        st, bx, li = StaticCounts(), PRCounts(), PRCounts()
        raw_frames = [int(r) for r in ds.table("frames", seq).column("raw_frame").to_pylist()]
        for k, raw in enumerate(raw_frames):
            frame = coda.frame(coda.position(raw))
            labels["frames"] += 1
            pred = np.asarray(arrays["semantics"][k])
            pts_base = transform_points(T_bl, frame.points_lidar)
            if frame.semantic_labels is not None:
                labels["frames with 3d_semantic"] += 1
                st = st + static_counts(
                    pred,
                    range_min,
                    vs,
                    pts_base,
                    semantic_to_classes(frame.semantic_labels),
                    T_bl[:3, 3],
                    noise_tol,
                )
            if not coda.path("3d_bbox", "os1", raw, ".json").exists():
                continue
            labels["frames with 3d_bbox"] += 1
            labels["boxes skipped (malformed)"] += len(frame.box_problems)
            for b in frame.boxes:
                if box_class(b.class_name) is None:
                    unknown.add(b.class_name)
            peds = [b for b in frame.boxes if box_class(b.class_name) == C.PEDESTRIAN]
            labels["pedestrian boxes"] += len(peds)
            mask_cam = np.asarray(arrays["mask_camera"][k]).astype(bool)
            if peds:
                from storage.sources.coda import box_rotation

                centers = np.array([b.center for b in peds])
                sizes = np.array([b.size for b in peds])
                rots = np.array([box_rotation(b.rpy) for b in peds])
                c_base, yaw_base = _boxes_to_base(T_bl, centers, [b.rpy[2] for b in peds])
                bx = bx + pedestrian_box_counts(
                    pred,
                    range_min,
                    vs,
                    c_base,
                    sizes,
                    yaw_base,
                    visible=mask_cam,
                    bottom_exclude_m=BOTTOM_EXCLUDE_M,
                )
                body = points_in_boxes(
                    frame.points_lidar, centers, sizes, rots, bottom_exclude_m=BOTTOM_EXCLUDE_M
                )
                body &= _in_image(frame.points_lidar, cam)
                gt_body = voxelize_points(pts_base[body], range_min, vs, shape)
            else:
                gt_body = np.zeros(shape, bool)
            li = li + pedestrian_lidar_counts(pred, gt_body, region=frustum)
        static[seq], boxes[seq], lidar[seq] = st, bx, li
    labels["boxes of unknown class"] = len(unknown)
    results: dict = {
        "title": "mobileocc label quality vs CODa labels",
        "meta": {
            "dataset": str(out),
            "CODa root": str(root),
            "sequences": ", ".join(ds.sequences),
            "labels": "3d_semantic (terrain ids mapped by tasks/metrics/coda_labels.py), "
            "3d_bbox pedestrian boxes",
        },
    }
    all_static = _sum(static.values(), StaticCounts())
    if all_static.num_points:
        results["static"] = all_static.as_dict()
        results["static_by_sequence"] = {
            s: {
                k: v for k, v in c.as_dict().items() if k not in ("num_points_ignored", "confusion")
            }
            for s, c in static.items()
        }
    if labels["pedestrian boxes"]:
        results["pedestrian_boxes"] = {
            **{s: v.as_dict() for s, v in boxes.items()},
            "all": _sum(boxes.values(), PRCounts()).as_dict(),
        }
        results["pedestrian_lidar"] = {
            **{s: v.as_dict() for s, v in lidar.items()},
            "all": _sum(lidar.values(), PRCounts()).as_dict(),
        }
    results["labels"] = labels
    notes = {}
    from flows.viewer.qa import manual_qa_section  # the paper's Table 4 bottom

    manual, note = manual_qa_section(out, {s: ds.store_path(s).stem for s in ds.sequences})
    if manual:
        results["detection_manual_qa"] = manual
    if note:
        notes["manual QA"] = {"note": note}
    if unknown:
        notes["unknown box classes"] = {
            "note": ", ".join(sorted(unknown)) + " (not in the mapping: left out)"
        }
    if not all_static.num_points:
        notes["static"] = {
            "note": "no 3d_semantic file among the published frames: static section skipped"
        }
    if not labels["pedestrian boxes"]:
        notes["pedestrians"] = {
            "note": "no pedestrian box among the published frames: pedestrian sections skipped"
        }
    if notes:
        results["notes"] = notes
    write_report(report_dir, results, {})
    return to_jsonable(results)
