"""``mobileocc evaluate``: label quality of a built dataset against ground truth, as a report.

``evaluate(dataset, gt, report_dir)`` reads the published dataset (storage/dataset.py), the stage
products of the run that built it (stage folders named in ``OUT/manifest.json``) and the ground
truth beside the raw data (``GT/gt/{SEQ}/``, storage/GT_FORMAT.md), hands arrays to the metric
kernels of tasks/metrics and tasks/fit/metrics.py, and writes ``report.md``, ``results.json`` and
figures through flows/commands/report.py. A section whose inputs are absent (no fit product, no ground
truth for a sequence, a grid that is not the ground truth's) is replaced by a note saying why.

Definitions beyond the kernels' own (each kernel's docstring has the rest):
- frames: the published frames of each sequence (frames table ``raw_frame``), base frame grids;
- static: GT LiDAR points of the frame (organised sweep order, reader's ``min_range_m``) in the
  base frame, pedestrian points (class 0 or a pedestrian instance) left out; a point in a free
  voxel takes the voxel 3 ``map.surface_noise_m`` further along its ray when that one is occupied
  (the voxel of the surface the range noise threw it in front of: tasks/metrics/static.py);
- per-class counts, confusion matrices, where each class's wrong voxels lie: over the same
  camera-visible voxels as the Occ3D metric, the sensor the LiDAR centre
  (flows/commands/confusion_report.py, tasks/metrics/confusion.py);
- pedestrian vs boxes: GT boxes (LiDAR frame) moved to the base frame, mask_camera visible voxels;
- pedestrian vs LiDAR body: GT points with a pedestrian instance that project into cam0, voxelised;
  evaluated region = voxels whose centre projects into cam0 (the camera frustum on the grid);
- detection: GT persons with a finite box2d and visible_fraction > 0; "visible" when
  visible_fraction >= ``VISIBLE_FRACTION`` (the GT_FORMAT "Medium" occlusion level or better);
  condition "night" for night sequences, else the sequence's crowd ("crowded" / "uncrowded");
- tracking: the same GT persons, ids = GT track ids, against the track product's rows;
- fit: each fitted row's detection box matched (IoU >= 0.5, Hungarian) to the GT persons' box2d
  of its frame; vertices / joints from the configured body model;
- velocity: GT velocity grid = velocity_base of the person on each of its occupancy_instance voxels
  (per-person GT); per-vertex GT = on each of those voxels the mean of the GT vertex velocities
  over the body surface in it (the fuse stage's rule, tasks/metrics/velocity.py
  ``vertex_velocity_grid``), its limb group (legs / arms / torso) that of the nearest GT vertex
  (skinning weights of the simulator's body model); both over camera-visible voxels;
- box heading: the published box yaw (instances table) of each matched fitted row vs the GT
  person's heading (box_yaw), both about base z (tasks/metrics/heading.py);
- box visibility: the nuScenes export's visible fraction of each matched fitted row's box vs the
  GT person's visible_fraction, and their nuScenes visibility bins;
- trajectory (robot logs): the published T_world_from_lidar of each frame (the frames table: the
  log's /tf or odometry, or its LiDAR odometry) vs the ground truth's, absolute trajectory error after a rigid
  alignment (tasks/metrics/trajectory.py), with the pose source.
- RayIoU / OccScore (SparseOcc / OpenOcc's ray metric, full grids, flow = velocity):
  flows/commands/evaluate_rays.py, tasks/metrics/rayiou.py.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flows.commands.evaluate_rays import SequenceRays, ray_sections
from storage.dataset import open_dataset
from storage.export.common import sequence_info
from storage.export.nuscenes import visibility_token, visible_fractions_of_boxes
from storage.gt import gt_dir, read_frame_gt, read_sequence_gt
from storage.manifest import Manifest, data_root_for
from storage.products import Bodies, Detections, Tracks
from tasks import conventions as C
from tasks.geometry import match_boxes, transform_points
from tasks.metrics._common import PRCounts
from tasks.metrics.confusion import ErrorLocations, error_locations
from tasks.metrics.detection import DetectionCounts, detection_counts
from tasks.metrics.free_returns import (
    FreeReturnCounts,
    LabelCounts,
    free_return_counts,
    label_counts,
)
from tasks.metrics.heading import heading_errors_deg, heading_summary
from tasks.metrics.occupancy import OccupancyMetric
from tasks.metrics.pedestrian import (
    pedestrian_box_counts,
    pedestrian_lidar_counts,
    person_point_counts,
    voxelize_points,
)
from tasks.metrics.static import StaticCounts, static_counts
from tasks.metrics.tracking import tracking_scores
from tasks.metrics.trajectory import trajectory_error
from tasks.metrics.velocity import (
    LIMB_GROUPS,
    VelocityErrors,
    limb_velocity_errors,
    velocity_errors,
    vertex_limb_groups,
    vertex_velocity_grid,
    voxel_velocity_errors,
)
from tasks.occupancy.grid import GridSpec
from tasks.occupancy.settings import MapParams

#: a GT person counts as "visible" for detection when at least this fraction of its silhouette shows
VISIBLE_FRACTION = 0.3
#: 2D IoU for a fitted row's box to claim a GT person
FIT_MATCH_IOU = 0.5


class EvaluateError(ValueError):
    """The dataset or the ground truth cannot be evaluated (names the path and what is missing)."""


# ---- locating inputs ----------------------------------------------------------------------------


def _stage_folder(out: Path, manifest: Manifest, sequence: str, stage: str) -> Path | None:
    """The stage's output folder of ``sequence``: the manifest's record, else the only (or newest)
    key folder under ``OUT/stages/<stage>/<sequence>/`` (runs driven without the manifest)."""
    rec = manifest.get(sequence, stage)
    if rec is not None and rec.status == "done" and rec.location and (out / rec.location).is_dir():
        return out / rec.location
    base = out / "stages" / stage / sequence
    keys = (
        sorted(
            (
                p
                for p in base.glob("*")
                if p.is_dir() and not p.name.startswith(".") and (p / "summary.json").exists()
            ),
            key=lambda p: p.stat().st_mtime,
        )
        if base.is_dir()
        else []
    )
    return keys[-1] if keys else None


def _gt_root(out: Path, manifest: Manifest, gt: Path | None) -> Path:
    """``--gt`` when given, else the raw data root the dataset was built from (OUT's manifest)."""
    return data_root_for(out, gt)


def _boxes_to_base(T_base_from_lidar: np.ndarray, centers, yaws) -> tuple[np.ndarray, np.ndarray]:
    """Box centres (B, 3) and yaws (B,) from the LiDAR frame to the base frame (rotation about z)."""
    R = T_base_from_lidar[:3, :3]
    return transform_points(T_base_from_lidar, centers), np.asarray(yaws, np.float64) + np.arctan2(
        R[1, 0], R[0, 0]
    )


def _in_image(points_lidar: np.ndarray, cam) -> np.ndarray:
    """(N,) bool: the LiDAR-frame points that project into the camera image (in front of it)."""
    pc = transform_points(cam.T_cam_from_lidar, points_lidar)
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = cam.K[0, 0] * pc[:, 0] / z + cam.K[0, 2]
        v = cam.K[1, 1] * pc[:, 1] / z + cam.K[1, 2]
    return (z > 0.1) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)


def _frustum(shape, range_min, voxel_size_m: float, T_base_from_lidar, cam) -> np.ndarray:
    """(X, Y, Z) bool: voxels whose centre projects into the camera image."""
    idx = np.indices(shape).reshape(3, -1).T
    centres = np.asarray(range_min) + (idx + 0.5) * voxel_size_m
    return _in_image(transform_points(np.linalg.inv(T_base_from_lidar), centres), cam).reshape(
        shape
    )


def _gt_persons(gtf) -> np.ndarray:
    """Rows of the GT persons seen by cam0 (finite box and some visible pixels)."""
    return np.flatnonzero(np.all(np.isfinite(gtf.box2d), axis=1) & (gtf.visible_fraction > 0))


def _condition(metadata: dict) -> str:
    if str(metadata.get("lighting", "day")).lower() in ("night", "dark"):
        return "night"
    return str(metadata.get("crowd", "unknown"))


def _body_model(config: dict):
    from storage.body_model_files import load_body_model
    from tasks.body.model import BodyModel
    from tasks.body.procedural import default_body_model

    path = ((config or {}).get("fit") or {}).get("body_model_path")
    return BodyModel(load_body_model(Path(path))) if path else default_body_model()


def _posed(model, params: dict, rows) -> tuple[np.ndarray, np.ndarray]:
    import torch

    from tasks.body.params import BodyParams

    with torch.no_grad():
        out = model(
            *(
                torch.as_tensor(np.asarray(params[k])[rows], dtype=torch.float32)
                for k in BodyParams.FIELDS
            )
        )
    return out.vertices.numpy(), out.joints.numpy()


# ---- per sequence -------------------------------------------------------------------------------


class _Totals:
    """Counts of every section, per sequence and summed."""

    def __init__(self) -> None:
        self.occ: dict[str, OccupancyMetric] = {}
        self.locations: dict[str, ErrorLocations] = {}  # where each class's wrong voxels lie
        self.static: dict[str, StaticCounts] = {}
        self.boxes: dict[str, PRCounts] = {}
        self.lidar: dict[str, PRCounts] = {}
        self.detection: dict[str, DetectionCounts] = {}
        self.tracking: dict = {}
        self.velocity: dict[str, VelocityErrors] = {}
        self.velocity_vertex: dict[str, VelocityErrors] = {}
        #: "vertex" / "person" GT -> limb group -> AVE counts
        self.limbs: dict[str, dict[str, VelocityErrors]] = {
            g: {n: VelocityErrors() for n in LIMB_GROUPS} for g in ("vertex", "person")
        }
        self.limb_groups: dict[
            str, np.ndarray | None
        ] = {}  # sequence -> (V,) limb of each GT vertex
        self.fit: dict[str, dict[str, list]] = {}
        #: sequence -> matched fits along their tracks, for the acceleration error:
        #: (track_id, frame position, stamp s, GT track id, joints world (24, 3), GT joints world)
        self.fit_tracks: dict[str, list[tuple]] = {}
        #: sequence -> gap-filled bodies' errors and counts, the fit stage's summary
        self.fit_gaps: dict[str, dict] = {}
        self.fit_summary: dict[str, dict] = {}
        self.person_points: dict[str, PRCounts] = {}
        self.notes: dict[str, str] = {}
        #: sequence -> absolute trajectory error of the published poses (tasks.metrics.trajectory)
        self.trajectory: dict[str, dict] = {}
        self.hist: dict[str, list] = {"velocity_error": [], "PVE_mm": [], "MPJPE_mm": []}
        self.samples: list[dict] = []
        self.rays: dict = {}  # sequence -> evaluate_rays.SequenceRays (RayIoU / OccScore)
        #: sequence -> (FreeReturnCounts, LabelCounts): label honesty, no ground truth needed
        self.honesty: dict[str, tuple[FreeReturnCounts, LabelCounts]] = {}


def _label_honesty(ds, data_root: Path, seq: str, tot: _Totals, config: dict) -> None:
    """Free returns and the unclassified / pedestrian voxel counts of every frame of ``seq``
    (tasks/metrics/free_returns.py): the sweeps from the recorded data under data_root, the
    labels from the dataset. Needs no ground truth."""
    arrays = ds.arrays(seq, lazy="zarr")
    attrs = ds.attrs(seq)
    range_min = np.asarray(attrs["range_min"], np.float64)
    vs = float(attrs["voxel_size_m"])
    raw_frames = [int(r) for r in ds.table("frames", seq).column("raw_frame").to_pylist()]
    try:
        rec = open_recorded_sequence(config, data_root, seq)
    except Exception as exc:  # the raw data moved: the labels alone still give counts
        tot.notes[f"label honesty {seq}"] = (
            f"sweeps of {seq} not readable under {data_root} ({str(exc).splitlines()[0][:160]}): "
            "free returns not counted"
        )
        rec = None
    T_bl = None if rec is None else np.asarray(rec.info.calibration.T_base_from_lidar, np.float64)
    fr, lc = FreeReturnCounts(), LabelCounts()
    for k, raw in enumerate(raw_frames):
        sem = np.asarray(arrays["semantics"][k])
        mask = np.asarray(arrays["mask_lidar"][k]).astype(bool)
        lc = lc + label_counts(sem, mask, np.asarray(arrays["instances"][k]))
        if rec is not None:
            pts = transform_points(T_bl, rec.frame(rec.position(raw)).points_lidar)
            fr = fr + free_return_counts(sem, mask, pts, range_min, vs)
    tot.honesty[seq] = (fr, lc)


def _evaluate_sequence(
    ds,
    out: Path,
    manifest: Manifest,
    gt_root: Path,
    seq: str,
    tot: _Totals,
    sample_positions: set[int],
    config: dict,
) -> None:
    arrays = ds.arrays(seq, lazy="zarr")
    attrs = ds.attrs(seq)
    range_min = np.asarray(attrs["range_min"], np.float64)
    vs = float(attrs["voxel_size_m"])
    raw_frames = [int(r) for r in ds.table("frames", seq).column("raw_frame").to_pylist()]
    data_root, gt_root = gt_root, gt_root if gt_root.is_dir() else gt_root.parent
    _label_honesty(ds, data_root, seq, tot, config)
    if not (gt_dir(gt_root, seq) / "sequence.npz").exists():
        tot.notes[f"sequence {seq}"] = f"no ground truth under {gt_root}/gt/{seq}: not evaluated"
        return
    gseq = read_sequence_gt(gt_root, seq)
    coda = open_recorded_sequence(config, data_root, seq)
    cam = coda.info.calibration.cameras[((config.get("dataset") or {}).get("camera")) or "cam0"]
    T_bl = np.asarray(gseq.T_base_from_lidar, np.float64)
    shape = tuple(arrays["semantics"].shape[1:4])
    same_grid = (
        shape == tuple(gseq.grid_shape)
        and abs(vs - gseq.grid_voxel_size_m) < 1e-9
        and np.allclose(range_min, gseq.grid_range_min)
    )
    if not same_grid:
        tot.notes[f"occupancy {seq}"] = (
            f"grid {shape} at {vs} m differs from the ground truth's "
            f"{tuple(gseq.grid_shape)} at {gseq.grid_voxel_size_m} m: occupancy, "
            "velocity and BEV comparisons skipped"
        )
    condition = "night" if coda.info.is_night else _condition(coda.info.metadata)
    # a return up to 3 sigma of range noise in front of its surface belongs to the surface's voxel
    noise_tol = 3 * float(
        (config.get("map") or {}).get("surface_noise_m", MapParams.surface_noise_m)
    )
    frustum = _frustum(shape, range_min, vs, T_bl, cam)
    if same_grid:
        tot.rays[seq] = SequenceRays(
            ds.table("frames", seq), range_min, range_min + np.asarray(shape) * vs, vs
        )

    detect_dir = _stage_folder(out, manifest, seq, "detect")
    track_dir = _stage_folder(out, manifest, seq, "track")
    fit_dir = _stage_folder(out, manifest, seq, "fit")
    tracks = Tracks.read(track_dir).arrays() if track_dir is not None else None
    bodies = (
        Bodies.read(fit_dir).arrays()
        if fit_dir is not None and (fit_dir / "bodies.npz").exists()
        else None
    )
    if detect_dir is None:
        tot.notes[f"detection {seq}"] = "no detect stage output: detection robustness skipped"
    if tracks is None:
        tot.notes[f"tracking {seq}"] = "no track stage output: tracking skipped"
    if bodies is None or len(bodies.get("frame", ())) == 0:
        tot.notes[f"fit {seq}"] = (
            "no fit bodies.npz (fit not run or fitted nobody): fit metrics not available"
        )
        bodies = None
    model = _body_model(config) if bodies is not None else None

    occ = tot.occ.setdefault(seq, OccupancyMetric())
    st, bx, li, ve, pp = StaticCounts(), PRCounts(), PRCounts(), VelocityErrors(), PRCounts()
    vv = VelocityErrors()
    track_frames, fit_rows = (
        [],
        {k: [] for k in ("pve", "mpjpe", "pa_mpjpe", "mpere", "heading", "visible", "visible_gt")},
    )
    boxed = [r for r in ds.table("instances", seq).to_pylist() if r["box3d_center"] is not None]
    box_yaw = {(int(r["track_id"]), int(r["frame"])): r["box3d_yaw"] for r in boxed}
    visible = visible_fractions_of_boxes(
        ds, seq, sequence_info(ds, seq), boxed
    )  # the nuScenes export's
    poses = np.asarray(ds.table("frames", seq).column("T_world_from_lidar").to_pylist()).reshape(
        -1, 4, 4
    )
    gt_poses = []
    for k, raw in enumerate(raw_frames):
        gtf = read_frame_gt(gt_root, seq, raw)
        gt_poses.append(gtf.T_world_from_lidar)
        pred = np.asarray(arrays["semantics"][k])
        mask_cam = np.asarray(arrays["mask_camera"][k]).astype(bool)
        # static semantics vs labelled GT points (pedestrian points out)
        sweep = coda.frame(coda.position(raw))  # the reader's min / max range (the config's)
        pcls = gtf.point_class[sweep.point_index].copy()
        pinst = gtf.point_instance[sweep.point_index]
        is_ped = (pcls == C.PEDESTRIAN) | ((pinst >= 1) & (pinst < 1000))
        pcls[is_ped] = C.UNLABELED
        pts_base = transform_points(T_bl, sweep.points_lidar)
        st = st + static_counts(pred, range_min, vs, pts_base, pcls, T_bl[:3, 3], noise_tol)
        # pedestrian vs boxes and vs LiDAR body points
        centers, yaws = _boxes_to_base(T_bl, gtf.box_center, gtf.box_yaw)
        bx = bx + pedestrian_box_counts(
            pred, range_min, vs, centers, gtf.box_size, yaws, visible=mask_cam
        )
        body_pts = (pinst >= 1) & (pinst < 1000) & _in_image(sweep.points_lidar, cam)
        li = li + pedestrian_lidar_counts(
            pred, voxelize_points(pts_base[body_pts], range_min, vs, shape), region=frustum
        )
        if same_grid:
            occ.update(pred, gtf.occupancy, mask_cam)
            tot.locations[seq] = tot.locations.get(seq, ErrorLocations()) + error_locations(
                pred, gtf.occupancy, mask_cam, (T_bl[:3, 3] - range_min) / vs
            )
            gvel = np.zeros(shape + (2,), np.float32)
            for j, tid in enumerate(gtf.track_id):
                gvel[gtf.occupancy_instance == tid] = gtf.velocity_base[j]
            pvel = np.asarray(arrays["velocity"][k]).astype(np.float32)
            ve = ve + velocity_errors(pred, pvel, gtf.occupancy, gvel, mask_cam)
            tot.rays[seq].add(k, pred, gtf.occupancy, pvel, gvel)
            vv = _vertex_velocity(
                tot,
                seq,
                gseq,
                gtf,
                T_bl,
                GridSpec(tuple(range_min), tuple(range_min + np.asarray(shape) * vs), vs),
                pred,
                pvel,
                gvel,
                mask_cam,
                vv,
            )
            tot.hist["velocity_error"].append(
                voxel_velocity_errors(pred, pvel, gtf.occupancy, gvel, mask_cam)[0]
            )
            if len(tot.samples) < len(sample_positions) + 1 and (seq, k) in sample_positions:
                tot.samples.append(
                    {
                        "title": f"sequence {seq} frame {raw} ({condition})",
                        "pred": pred,
                        "gt": gtf.occupancy,
                        "mask": mask_cam,
                        "range_min": range_min,
                        "voxel_size_m": vs,
                    }
                )
        persons = _gt_persons(gtf)
        vis = gtf.visible_fraction[persons] >= VISIBLE_FRACTION
        if detect_dir is not None:
            det = Detections.read(detect_dir, Detections.file_name(raw)).arrays()
            tot.detection[condition] = tot.detection.get(
                condition, DetectionCounts()
            ) + detection_counts(gtf.box2d[persons], vis, det["boxes_xyxy"])
        if tracks is not None:
            r = tracks["frame"] == raw
            track_frames.append(
                (
                    gtf.track_id[persons].astype(np.int64),
                    gtf.box2d[persons],
                    tracks["track_id"][r],
                    tracks["boxes_xyxy"][r],
                )
            )
            rows = np.flatnonzero(r & (tracks["gt_index"] >= 0))  # oracle rows know their person
            if rows.size:
                off = tracks["points_offsets"]
                pp = pp + person_point_counts(
                    pinst,
                    [tracks["points_index"][off[j] : off[j + 1]] for j in rows],
                    gtf.track_id[tracks["gt_index"][rows]],
                )
        if bodies is not None and detect_dir is not None:
            here = bodies["frame"] == raw
            _gap_filled_errors(
                tot,
                seq,
                model,
                bodies,
                np.flatnonzero(here & bodies["gap_filled"]),
                gtf,
                persons,
                gseq,
            )
            rows = np.flatnonzero(here & ~bodies["gap_filled"])
            if rows.size:
                det = Detections.read(detect_dir, Detections.file_name(raw)).arrays()
                boxes = det["boxes_xyxy"][bodies["det_index"][rows]]
                gi, fi = match_boxes(gtf.box2d[persons], boxes, FIT_MATCH_IOU)
                if gi.size:
                    pv, pj = _posed(model, bodies, rows[fi])
                    from tasks.fit.metrics import fit_metrics

                    m = fit_metrics(
                        pv,
                        pj,
                        gtf.vertices[persons[gi]],
                        gtf.joints[persons[gi]],
                        gseq.person_faces,
                    )
                    for key in ("pve", "mpjpe", "pa_mpjpe", "mpere"):
                        fit_rows[key].append(np.asarray(m[key], np.float64))
                    T_w = coda.info.poses[coda.position(raw)]
                    for j, b in enumerate(rows[fi]):
                        tot.fit_tracks.setdefault(seq, []).append(
                            (
                                int(bodies["track_id"][b]),
                                k,
                                float(coda.info.stamps_ns[coda.position(raw)]) * 1e-9,
                                int(gtf.track_id[persons[gi[j]]]),
                                transform_points(T_w, pj[j]),
                                transform_points(T_w, gtf.joints[persons[gi[j]]]),
                            )
                        )
                    _, gt_yaw = _boxes_to_base(
                        T_bl, gtf.box_center[persons[gi]], gtf.box_yaw[persons[gi]]
                    )
                    pub = [box_yaw.get((int(bodies["track_id"][b]), k)) for b in rows[fi]]
                    fit_rows["heading"].append(
                        heading_errors_deg(
                            [y for y in pub if y is not None],
                            [g for y, g in zip(pub, gt_yaw) if y is not None],
                        )
                    )
                    keys = [(k, int(bodies["track_id"][b])) for b in rows[fi]]  # (frame, track id)
                    fit_rows["visible"].append(np.array([visible.get(key, np.nan) for key in keys]))
                    fit_rows["visible_gt"].append(
                        gtf.visible_fraction[persons[gi]].astype(np.float64)
                    )
    tot.static[seq], tot.boxes[seq], tot.lidar[seq], tot.velocity[seq] = st, bx, li, ve
    if coda.kind == "log" and len(gt_poses):  # a log's poses (/tf, odometry, LiDAR odometry)
        tot.trajectory[seq] = {
            "pose source": getattr(coda, "pose_source", "poses file"),
            **vars(trajectory_error(poses, np.stack(gt_poses))),
        }
    if pp.pred_total:
        tot.person_points[seq] = pp
    if vv.n_t:
        tot.velocity_vertex[seq] = vv
    if not same_grid:
        tot.occ.pop(seq)
        tot.locations.pop(seq, None)
        tot.velocity.pop(seq)
    if tracks is not None:
        tot.tracking[seq] = tracking_scores(track_frames)
    if bodies is not None:
        import json

        from tasks.fit.shape import shape_spread

        summary = (
            json.loads((fit_dir / "summary.json").read_text())
            if (fit_dir / "summary.json").exists()
            else {}
        )
        fitted = ~bodies["gap_filled"]
        tot.fit_summary[seq] = {
            "shape_spread": shape_spread(bodies["track_id"][fitted], bodies["betas"][fitted]),
            "keypoints_mirrored": int(bodies["mirrored"].sum()),
            **{
                k: summary[k]
                for k in (
                    "flips_flipped",
                    "flips_kept",
                    "flips_undecided",
                    "gap_filled",
                    "gap_dropped_seen_through",
                    "warm_started",
                )
                if k in summary
            },
            "gap_filled_bodies": int(bodies["gap_filled"].sum()),
        }
        got = {k: np.concatenate(v) if v else np.zeros(0) for k, v in fit_rows.items()}
        tot.fit[seq] = got
        tot.hist["PVE_mm"].append(got["pve"])
        tot.hist["MPJPE_mm"].append(got["mpjpe"])


#: a gap-filled body claims the GT person whose pelvis is nearest, within this distance (m)
GAP_MATCH_M = 0.5


def _gap_filled_errors(tot: _Totals, seq: str, model, bodies: dict, rows, gtf, persons, gseq):
    """MPJPE / PVE of the bodies the fit interpolated for frames without a detection, each
    matched to the nearest GT person of its frame by pelvis (within GAP_MATCH_M)."""
    g = tot.fit_gaps.setdefault(seq, {"bodies": 0, "matched": 0, "mpjpe": [], "pve": []})
    g["bodies"] += len(rows)
    if not len(rows) or not len(persons):
        return
    from tasks.fit.metrics import fit_metrics

    pv, pj = _posed(model, bodies, rows)
    d = np.linalg.norm(pj[:, None, 0] - gtf.joints[persons][None, :, 0], axis=-1)
    near = d.argmin(1)
    ok = d[np.arange(len(rows)), near] < GAP_MATCH_M
    if ok.any():
        m = fit_metrics(
            pv[ok],
            pj[ok],
            gtf.vertices[persons[near[ok]]],
            gtf.joints[persons[near[ok]]],
            gseq.person_faces,
        )
        g["matched"] += int(ok.sum())
        g["mpjpe"].append(np.asarray(m["mpjpe"], np.float64))
        g["pve"].append(np.asarray(m["pve"], np.float64))


def acceleration_errors(records: list[tuple], step_s: float) -> dict:
    """Acceleration error of fitted joints along their tracks: for every matched fit whose
    track has matched fits in the published frames just before and after it, all three of the
    same GT person, |a_fit - a_gt| with a the second divided difference of the world positions;
    mean over such fits and joints (all 24, and the root alone), in m/s^2 and in mm/frame^2 at
    the step ``step_s`` (the published frames' nominal step)."""
    from tasks.fit.refine import acceleration_error

    if not records:
        return {"fits": 0}
    key = np.array([(r[0], r[3]) for r in records])
    ids = np.unique(key, axis=0, return_inverse=True)[1].reshape(-1)  # one id per (track, GT)
    pos = np.array([r[1] for r in records])
    t = np.array([r[2] for r in records])
    pred = np.stack([r[4] for r in records])
    gt = np.stack([r[5] for r in records])
    # neighbours must be adjacent published frames: stamps more than 1.5 steps apart do not tie
    joints, ok = acceleration_error(ids, t, pred, gt, 1.5 * step_s)
    root, _ = acceleration_error(ids, t, pred[:, :1], gt[:, :1], 1.5 * step_s)
    del pos
    f2 = step_s * step_s * 1000.0
    n = int(ok.sum())
    mean = lambda a: float(np.nanmean(a)) if n else float("nan")  # noqa: E731
    return {
        "fits": n,
        "joints_m_s2": mean(joints),
        "joints_mm_frame2": mean(joints) * f2,
        "root_m_s2": mean(root),
        "root_mm_frame2": mean(root) * f2,
    }


def _limb_groups(gseq) -> np.ndarray | None:
    """(V,) limb group of each GT body vertex, from the simulator's body model (the procedural
    one) when its mesh is the ground truth's; None otherwise."""
    from tasks.body.procedural import default_body_model

    model = default_body_model()
    faces = np.asarray(model.faces)
    if faces.shape != gseq.person_faces.shape or not np.array_equal(faces, gseq.person_faces):
        return None
    return vertex_limb_groups(model.lbs_weights.numpy())


def _vertex_velocity(
    tot: _Totals,
    seq: str,
    gseq,
    gtf,
    T_bl,
    spec: GridSpec,
    pred,
    pvel,
    gvel,
    mask,
    vv: VelocityErrors,
) -> VelocityErrors:
    """Add one frame's AVE against the per-vertex GT (and per limb group against both GTs)."""
    if seq not in tot.limb_groups:
        tot.limb_groups[seq] = _limb_groups(gseq)
    groups = tot.limb_groups[seq]
    if gtf.vertex_velocity_base is None or groups is None:
        tot.notes[f"velocity per vertex {seq}"] = (
            "ground truth without vertex_velocity_base (simulated before it existed)"
            if groups is not None
            else "the ground truth's body mesh is not the simulator's procedural one: no limb groups"
        )
        return vv
    verts = (
        np.stack([transform_points(T_bl, v) for v in gtf.vertices])
        if len(gtf.vertices)
        else gtf.vertices
    )
    gvv, group = vertex_velocity_grid(
        spec,
        gtf.occupancy_instance,
        gtf.track_id,
        verts,
        gseq.person_faces,
        gtf.vertex_velocity_base[..., :2],
        groups,
    )
    for name, g in (("vertex", gvv), ("person", gvel)):
        per = limb_velocity_errors(pred, pvel, gtf.occupancy, g, group, mask)
        tot.limbs[name] = {n: tot.limbs[name][n] + per[n] for n in LIMB_GROUPS}
    return vv + velocity_errors(pred, pvel, gtf.occupancy, gvv, mask)


def _limb_table(limbs: dict[str, dict[str, VelocityErrors]]) -> dict:
    """{limb group and "all": AVE-O / AVE-T against the per-vertex and the per-person GT}."""
    rows = {
        **{n: (limbs["vertex"][n], limbs["person"][n]) for n in LIMB_GROUPS},
        "all": tuple(_sum(limbs[g].values()) for g in ("vertex", "person")),
    }
    return {
        n: {
            "ave_o_vertex_gt": v.ave_o,
            "ave_t_vertex_gt": v.ave_t,
            "ave_o_person_gt": p.ave_o,
            "ave_t_person_gt": p.ave_t,
            "num_voxels_o": v.n_o,
            "num_voxels_t": v.n_t,
        }
        for n, (v, p) in rows.items()
    }


# ---- entry point --------------------------------------------------------------------------------


def _sum(values):
    it = iter(values)
    total = next(it)
    for v in it:
        total = total + v
    return total


def visibility_agreement(ours, gt) -> dict:
    """Visible fractions (N,) of the export vs the ground truth's: same / within-one nuScenes bin
    shares, share binned lower than the truth, median |difference|."""
    ok = np.isfinite(ours) & np.isfinite(gt)
    ours, gt = np.asarray(ours)[ok], np.asarray(gt)[ok]
    if ours.size == 0:
        return {"boxes": 0}
    b = np.array([int(visibility_token(v)) for v in ours]) - np.array(
        [int(visibility_token(v)) for v in gt]
    )
    return {
        "boxes": int(ours.size),
        "same_bin_share": float(np.mean(b == 0)),
        "within_one_bin_share": float(np.mean(np.abs(b) <= 1)),
        "lower_bin_share": float(np.mean(b < 0)),
        "median_abs_difference": float(np.median(np.abs(ours - gt))),
    }


def _fit_row(v: dict) -> dict:
    n = len(v["pve"])
    mean = lambda a: float(np.mean(a)) if n else float("nan")
    return {
        "PVE_mm": mean(v["pve"]),
        "MPJPE_mm": mean(v["mpjpe"]),
        "PA_MPJPE_mm": mean(v["pa_mpjpe"]),
        "MPERE": mean(v["mpere"]),
        "persons": n,
    }


def _published_step(ds) -> float:
    """The published frames' nominal step (s): the median stamp difference of the first
    sequence with two frames (0.2 s when none has)."""
    for seq in ds.sequences:
        t = np.asarray(ds.table("frames", seq).column("stamp_ns").to_pylist(), np.float64) * 1e-9
        if len(t) >= 2:
            return float(np.median(np.diff(np.sort(t))))
    return 0.2


def _sample_positions(ds, sample_frames: int) -> set:
    """``sample_frames`` (sequence, frame position) pairs spread over the sequences and frames."""
    pairs = []
    for seq in ds.sequences:
        n = int(ds.arrays(seq, lazy="zarr")["semantics"].shape[0])
        pairs += [(seq, k) for k in range(n)]
    if not pairs or sample_frames <= 0:
        return set()
    pick = np.unique(
        np.linspace(0, len(pairs) - 1, min(sample_frames, len(pairs))).round().astype(int)
    )
    return {pairs[i] for i in pick}


def open_recorded_sequence(config: dict, root: Path, sequence: str):
    """The reader (CODa or robot log) of ``sequence`` under ``root`` with the dataset settings of a recorded
    config (``OUT/manifest.json`` meta.config; the defaults when none was recorded)."""
    from configs.schema import Config, load_config
    from flows.pipeline.inputs import open_sequence

    cfg = Config.model_validate(config) if config else load_config()
    return open_sequence(
        cfg.model_copy(update={"dataset": cfg.dataset.model_copy(update={"root": Path(root)})}),
        sequence,
    )


def open_for_evaluation(dataset: Path, data: Path | None):
    """(OUT, its manifest, the recorded config, the raw data root holding the labels, the
    published dataset); EvaluateError naming what is missing."""
    out = Path(dataset)
    manifest = Manifest.load(out)
    config = manifest.meta.get("config") or {}
    root = _gt_root(out, manifest, data)
    ds = open_dataset(out)
    if not ds.sequences:
        raise EvaluateError(f"{out}: no published sequence to evaluate (run the pipeline first)")
    return out, manifest, config, root, ds


def withdrawn_sequences(ds) -> dict[str, str]:
    """sequence -> the first line of why its last run failed, for every sequence the sequences
    table marks failed (withdrawn from the dataset, so not evaluated)."""
    return {
        str(row["sequence"]): (row.get("error") or "").splitlines()[0][:200]
        for row in ds.table("sequences").to_pylist()
        if row.get("status") != "ok"
    }


def evaluate(
    dataset: Path,
    gt: Path | None,
    report_dir: Path,
    sample_frames: int = 3,
) -> dict:
    """Evaluate the dataset at ``dataset`` (OUT) against the ground truth under ``gt`` (the raw data
    root holding ``gt/``; None = the ``dataset.root`` recorded in OUT/manifest.json). Writes
    report.md, results.json and figures/ under ``report_dir``; returns the results dict.
    (CODa's own labels: flows/commands/evaluate_coda.py.)"""
    out, manifest, config, gt_root, ds = open_for_evaluation(dataset, gt)
    tot = _Totals()
    for seq, why in withdrawn_sequences(ds).items():
        tot.notes[f"sequence {seq}"] = f"withdrawn, not evaluated: its last run failed ({why})"
    positions = _sample_positions(ds, sample_frames)
    for seq in ds.sequences:
        _evaluate_sequence(ds, out, manifest, gt_root, seq, tot, positions, config)

    results: dict = {
        "title": "mobileocc label quality",
        "meta": {
            "dataset": str(out),
            "ground truth": str(gt_root),
            "sequences": ", ".join(ds.sequences),
            "frames": sum(
                int(ds.arrays(s, lazy="zarr")["semantics"].shape[0]) for s in ds.sequences
            ),
            "body source": ds.attrs(ds.sequences[0]).get("body_source", "?"),
        },
    }
    if tot.occ:
        results["occupancy"] = _sum_metric(tot.occ).as_dict()
        results["occupancy_by_sequence"] = {
            s: _brief(m.compute().as_dict()) for s, m in tot.occ.items()
        }
        from flows.commands.confusion_report import sections

        results.update(sections(tot.occ, tot.locations))
    if tot.honesty:
        results["label_honesty"] = _honesty_section(tot.honesty)
    if tot.trajectory:
        results["trajectory"] = tot.trajectory
    results.update(ray_sections(tot.rays))
    if tot.static:
        results["static"] = _sum(tot.static.values()).as_dict()
        results["static_by_sequence"] = {s: _brief(v.as_dict()) for s, v in tot.static.items()}
    if tot.boxes:
        results["pedestrian_boxes"] = {
            **{s: v.as_dict() for s, v in tot.boxes.items()},
            "all": _sum(tot.boxes.values()).as_dict(),
        }
        results["pedestrian_lidar"] = {
            **{s: v.as_dict() for s, v in tot.lidar.items()},
            "all": _sum(tot.lidar.values()).as_dict(),
        }
    if tot.detection:
        results["detection"] = {
            **{c: v.as_dict() for c, v in tot.detection.items()},
            "all": _sum(tot.detection.values()).as_dict(),
        }
    from flows.viewer.qa import manual_qa_section  # the paper's Table 4 bottom, beside the above

    manual, note = manual_qa_section(out, {s: ds.store_path(s).stem for s in ds.sequences})
    if manual:
        results["detection_manual_qa"] = manual
    if note:
        tot.notes["manual QA"] = note
    if tot.tracking:
        results["tracking"] = {
            **{s: v.as_dict() for s, v in tot.tracking.items()},
            "all": _sum(tot.tracking.values()).as_dict(),
        }
    if tot.person_points:  # the track stage's LiDAR points per person vs per-point GT instances
        results["person_points"] = {
            **{s: v.as_dict() for s, v in tot.person_points.items()},
            "all": _sum(tot.person_points.values()).as_dict(),
        }
    if tot.fit:
        allfit = {
            k: np.concatenate([v[k] for v in tot.fit.values()])
            for k in ("pve", "mpjpe", "pa_mpjpe", "mpere")
        }
        results["fit"] = {**{s: _fit_row(v) for s, v in tot.fit.items()}, "all": _fit_row(allfit)}
        step = _published_step(ds)
        results["fit_acceleration"] = {
            **{q: acceleration_errors(v, step) for q, v in tot.fit_tracks.items()},
            "all": acceleration_errors([r for v in tot.fit_tracks.values() for r in v], step),
        }
        results["fit_tracks"] = tot.fit_summary
        if tot.fit_gaps:
            gaps = [g for g in tot.fit_gaps.values()]
            cat = lambda k: (
                np.concatenate([x for g in gaps for x in g[k]])
                if any(g[k] for g in gaps)
                else np.zeros(0)
            )  # noqa: E731
            results["fit_gap_filled"] = {
                "bodies": sum(g["bodies"] for g in gaps),
                "matched": sum(g["matched"] for g in gaps),
                "MPJPE_mm": float(cat("mpjpe").mean()) if cat("mpjpe").size else float("nan"),
                "PVE_mm": float(cat("pve").mean()) if cat("pve").size else float("nan"),
            }
        results["box_heading"] = heading_summary(
            np.concatenate([v["heading"] for v in tot.fit.values()])
        )
        results["box_visibility"] = visibility_agreement(
            *(np.concatenate([v[k] for v in tot.fit.values()]) for k in ("visible", "visible_gt"))
        )
    if tot.velocity:
        results["velocity"] = {
            **{s: v.as_dict() for s, v in tot.velocity.items()},
            "all": _sum(tot.velocity.values()).as_dict(),
        }
    if tot.velocity_vertex:
        results["velocity_vertex_gt"] = {
            **{s: v.as_dict() for s, v in tot.velocity_vertex.items()},
            "all": _sum(tot.velocity_vertex.values()).as_dict(),
        }
        results["velocity_by_limb"] = _limb_table(tot.limbs)
    if tot.notes:
        results["notes"] = {k: {"note": v} for k, v in tot.notes.items()}
    hist = {}
    if tot.hist["velocity_error"]:
        hist["pedestrian voxel velocity error"] = {
            "values": np.concatenate(tot.hist["velocity_error"]),
            "xlabel": "|v_pred - v_gt| (m/s), voxels pedestrian in both",
        }
    for key, label in (
        ("PVE_mm", "PVE (mm) per fitted person"),
        ("MPJPE_mm", "MPJPE (mm) per fitted person"),
    ):
        if tot.hist[key]:
            hist[f"fit {key}"] = {"values": np.concatenate(tot.hist[key]), "xlabel": label}
    from flows.commands.report import to_jsonable, write_report

    write_report(report_dir, results, {"bev": tot.samples, "histograms": hist})
    return to_jsonable(results)


def _honesty_section(honesty: dict) -> dict:
    """{sequence: row, "all": row}: the free-returns share and the label counts (no GT needed)."""
    rows = {s: {**fr.as_dict(), **lc.as_dict()} for s, (fr, lc) in honesty.items()}
    fr = _sum([f for f, _ in honesty.values()])
    lc = _sum([c for _, c in honesty.values()])
    return {**rows, "all": {**fr.as_dict(), **lc.as_dict()}}


def _sum_metric(metrics: dict[str, OccupancyMetric]):
    total = OccupancyMetric()
    for m in metrics.values():
        total.confusion += m.confusion
    return total.compute()


def _brief(row: dict) -> dict:
    """A per-sequence row: the summary numbers and per-class IoU."""
    return {k: v for k, v in row.items() if k not in ("num_points_ignored", "confusion")}
