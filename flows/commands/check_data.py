"""``mobileocc check-data --data DIR [--config FILE] [--deep]``: is a CODa download or a folder of
robot logs ready for a run?

For every selected sequence it prints one table row (frames found and how they were selected,
LiDAR channels, missing / truncated files, labels present, camera calibration, reprojection
figures, time unit, intensity, pose / timestamp agreement, day / night) and then each problem.
Then, per sequence, the perception source each stage will use and whether the run reads the
simulator's ground truth (flows/commands/perception_sources.py). Exit code 2 when the config reads
gt/ that a sequence lacks, or the bundled models it runs are missing (a run would be refused);
1 when a problem blocks a run (missing or truncated files of selected frames, an unreadable
sequence, images that are not the calibration's size), else 0.

Fast: file sizes, a directory listing, the small text files, three sweeps per sequence and one
image header per camera (storage/sources/coda/check.py). ``--deep`` reads every sweep, label file and
image header. The figures come from tasks/metrics/calibration.py:

- ``rows``: median |v_cam0 - v_cam1| px of the sampled LiDAR points in both rectified images
  (0 for a consistent rectification);
- ``in img``: share of the sampled points inside the configured camera's image;
- ``ground``: ground height in the base frame (0 when T_base_from_lidar is right).

Robot logs (storage/sources/log/check.py): one row per log (sweeps and their rate, frames kept,
the LiDAR's point layout, cameras, base frame, pose source, the same figures), then per log every
topic (type, messages, rate, frame id) with what it is used as, and what is missing.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from configs.schema import Config
from storage.sources.coda.check import SequenceFacts, inspect_sequence
from storage.sources.log.check import LogCheckFacts, inspect_log
from tasks.metrics.calibration import (
    ground_height_m,
    in_image_fraction,
    projection_difference_px,
    stereo_row_error_px,
)

#: thresholds above which a figure becomes a warning
MAX_ROW_ERROR_PX = 1.0
MAX_PROJECTION_DIFF_PX = 2.0
MAX_GROUND_OFFSET_M = 0.3
MIN_IN_IMAGE = 0.02
MAX_EXTRINSIC_MISMATCH_M = 0.01
#: points the figures use (of the ~3 x 100k sampled returns)
MAX_FIGURE_POINTS = 30000


def _figures(facts: SequenceFacts, camera: str, log: bool = False) -> dict:
    """Reprojection and ground figures of the sampled sweeps (adds warnings to facts, naming
    where the calibration came from: CODa's calibration files, or a log's /tf_static)."""
    seq = facts.seq
    calib = seq.info.calibration
    pts = (
        np.concatenate(facts.sample_points) if facts.sample_points else np.zeros((0, 3), np.float32)
    )
    pts = pts[:: max(1, len(pts) // MAX_FIGURE_POINTS)]  # evenly spread over the sampled sweeps
    out: dict = {}
    cams = calib.cameras
    view = lambda c: (c.K, c.T_cam_from_lidar, c.width, c.height)  # noqa: E731
    if "cam0" in cams and "cam1" in cams and len(pts):
        out["rows"] = stereo_row_error_px(pts, view(cams["cam0"]), view(cams["cam1"]))
        if out["rows"] > MAX_ROW_ERROR_PX:
            facts.problem(
                False,
                f"a LiDAR point lands {out['rows']:.1f} px apart in rows of the two rectified "
                "images (median): rectification or extrinsics disagree",
            )
    if camera in cams and len(pts):
        cam = cams[camera]
        out["in_image"] = in_image_fraction(pts, *view(cam))
        if out["in_image"] < MIN_IN_IMAGE:
            facts.problem(
                False,
                f"only {out['in_image']:.1%} of the sampled points fall in the {camera} image: "
                + (
                    f"check the /tf_static chain from the LiDAR to the {camera} optical frame and "
                    "its CameraInfo"
                    if log
                    else f"check calib_os1_to_{camera}.yaml"
                ),
            )
        if cam.raw is not None and cam.raw.P_lidar_to_rect is not None:
            out["file_P"] = projection_difference_px(
                pts, *view(cam)[:2], cam.raw.P_lidar_to_rect, cam.width, cam.height
            )
            if out["file_P"] > MAX_PROJECTION_DIFF_PX:
                facts.problem(
                    False,
                    f"calib_os1_to_{camera}.yaml projection_matrix projects {out['file_P']:.1f} px "
                    "from the rectified pinhole (median); the reader uses P[:, :3] R T",
                )
    if len(pts):
        out["ground"] = ground_height_m(pts, calib.T_base_from_lidar)
        if np.isfinite(out["ground"]) and abs(out["ground"]) > MAX_GROUND_OFFSET_M:
            facts.problem(
                False,
                f"the ground lies at z = {out['ground']:+.2f} m in the base frame (expected ~0): "
                + (
                    "check the /tf_static transform from the base frame to the LiDAR (or "
                    "dataset.lidar_height_m where the TF tree has no base frame)"
                    if log
                    else "check calib_os1_to_base.yaml / dataset.lidar_height_m"
                ),
            )
    if calib.T_cam1_from_cam0 is not None and "cam1" in cams and cams["cam1"].raw is not None:
        derived = calib.T_cam1_from_cam0 @ cams["cam0"].raw.T_cam_from_lidar
        gap = float(np.linalg.norm(derived[:3, 3] - cams["cam1"].raw.T_cam_from_lidar[:3, 3]))
        if gap > MAX_EXTRINSIC_MISMATCH_M:
            facts.problem(
                False,
                f"calib_os1_to_cam1.yaml and calib_cam0_to_cam1 @ calib_os1_to_cam0 differ by "
                f"{gap * 100:.1f} cm",
            )
    return out


def _baseline_m(calib) -> float:
    if calib.T_cam1_from_cam0 is not None:
        return float(np.linalg.norm(calib.T_cam1_from_cam0[:3, 3]))
    cam1 = calib.cameras.get("cam1")
    if cam1 is not None and cam1.raw is not None and cam1.raw.P_rect[0, 3] != 0:
        return float(-cam1.raw.P_rect[0, 3] / cam1.raw.P_rect[0, 0])
    return float("nan")


def _row(facts: SequenceFacts, fig: dict, camera: str) -> list[str]:
    if facts.seq is None:
        return [facts.sequence, "-", "-", "-", "-", "-", "-", "-", "-", "-", "-", "BLOCKED"]
    info = facts.seq.info
    calib = info.calibration
    n = info.num_frames
    cam = calib.cameras.get(camera)
    kind = "split" if facts.lidar_files < info.num_stamps else "all"
    frames = f"{n} of {facts.lidar_files}/{info.num_stamps} ({kind})"
    bad = sum(len(v) for v in facts.missing.values()) + len(facts.truncated)
    files = "ok" if not bad else f"{bad} bad"
    lidar = "/".join(f"{c}ch" for c in sorted(facts.channels)) or "-"
    labels = f"box {facts.bbox_files} sem {facts.semantic_files}"
    if cam is not None:
        rect = (
            "R,P"
            if cam.rectified and cam.raw is not None and not np.allclose(cam.raw.R_rect, np.eye(3))
            else ("P" if cam.rectified else "raw")
        )
        camera_txt = f"{cam.width}x{cam.height} f{cam.K[0, 0]:.0f} b{_baseline_m(calib):.3f} {rect}"
    else:
        camera_txt = "-"
    reproj = []
    if "rows" in fig:
        reproj.append(f"rows {fig['rows']:.2f}px")
    if "in_image" in fig:
        reproj.append(f"in img {fig['in_image']:.0%}")
    if "ground" in fig and np.isfinite(fig["ground"]):
        reproj.append(f"ground {fig['ground']:+.2f}m")
    if facts.time_max_ns is None:
        time_txt = "none (4ch)"
    elif facts.time_max_ns == 0:
        time_txt = "all 0"
    elif facts.time_max_ns < 1.0:
        time_txt = f"seconds? (max {facts.time_max_ns:.3g})"
    else:
        time_txt = f"ns, <= {facts.time_max_ns / 1e6:.1f} ms"
    intensity = (
        f"0 in {len(facts.intensity_zero)}/{facts.frames_read}"
        if facts.intensity_zero
        else f"ok ({facts.frames_read} read)"
    )
    poses = f"dt {facts.pose_stamp_diff_s * 1e3:.1f} ms"
    light = f"{info.lighting} ({info.lighting_source})"
    status = "BLOCKED" if facts.blocking else ("warn" if facts.problems else "OK")
    return [
        facts.sequence,
        frames,
        lidar,
        files,
        labels,
        camera_txt,
        ", ".join(reproj) or "-",
        time_txt,
        intensity,
        poses,
        light,
        status,
    ]


HEADER = [
    "seq",
    "frames (kept of files/stamps)",
    "lidar",
    "files",
    "labels",
    "camera (rectified)",
    "reprojection",
    "time",
    "intensity",
    "poses",
    "lighting",
    "status",
]


def format_table(rows: list[list[str]]) -> str:
    widths = [max(len(r[i]) for r in [HEADER, *rows]) for i in range(len(HEADER))]
    line = lambda r: "  ".join(v.ljust(w) for v, w in zip(r, widths)).rstrip()  # noqa: E731
    return "\n".join([line(HEADER), "  ".join("-" * w for w in widths), *(line(r) for r in rows)])


LOG_HEADER = [
    "log",
    "sweeps (rate)",
    "frames kept",
    "lidar",
    "cameras (rectified)",
    "base",
    "poses",
    "reprojection",
    "lighting",
    "status",
]


def _log_row(facts: LogCheckFacts, fig: dict) -> list[str]:
    if facts.seq is None:
        return [facts.sequence, "-", "-", "-", "-", "-", "-", "-", "-", "BLOCKED"]
    seq, f = facts.seq, facts.facts
    stamps = seq.index.streams[seq.lidar_topic].stamp_ns
    rate = (len(stamps) - 1) / ((int(stamps[-1]) - int(stamps[0])) / 1e9) if len(stamps) > 1 else 0
    cams = []
    for c in f.cameras:
        cal = seq.info.calibration.cameras[c.name]
        how = "rect" if c.rectified else ("raw->rect" if c.info.needs_rectifying() else "raw")
        cams.append(f"{c.name} {cal.width}x{cal.height} {how}")
    reproj = []
    if "rows" in fig:
        reproj.append(f"rows {fig['rows']:.2f}px")
    if "in_image" in fig:
        reproj.append(f"in img {fig['in_image']:.0%}")
    if "ground" in fig and np.isfinite(fig["ground"]):
        reproj.append(f"ground {fig['ground']:+.2f}m")
    info = seq.info
    status = "BLOCKED" if facts.blocking else ("warn" if facts.problems else "OK")
    return [
        facts.sequence,
        f"{len(stamps)} ({rate:.1f} Hz)",
        f"{info.num_frames} (every {seq.frame_stride})",
        f.lidar_topic,
        ", ".join(cams) or "-",
        f.base_frame or "default",
        f.pose_source,
        ", ".join(reproj) or "-",
        f"{info.lighting} ({info.lighting_source})",
        status,
    ]


def _topic_table(facts: LogCheckFacts) -> list[str]:
    """Every topic of the log: type, messages, rate, frame id, what it is used as."""
    f, seq = facts.facts, facts.seq
    used = {f.lidar_topic: "LiDAR"}
    for c in f.cameras:
        used[c.image_topic] = f"{c.name} image"
        used[c.info_topic] = f"{c.name} CameraInfo"
    used.setdefault("/tf_static", "calibration")
    if seq.pose_source.startswith("/tf"):
        used["/tf"] = "poses"
    for name, *_ in f.topics:
        if seq.pose_source.startswith(name + " "):
            used[name] = "poses"
    rows = [
        [name, msgtype.replace("/msg/", "/"), str(count), f"{rate:.1f}" if rate else "-",
         frame_id or "-", used.get(name, "")]
        for name, msgtype, count, rate, frame_id in f.topics
    ]  # fmt: skip
    header = ["topic", "type", "messages", "Hz", "frame id", "used as"]
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    line = lambda r: "    " + "  ".join(v.ljust(w) for v, w in zip(r, widths)).rstrip()  # noqa: E731
    return [line(header), *(line(r) for r in rows)]


def _check_logs(config: Config, ids: list[str], deep: bool) -> tuple[int, str]:
    from flows.pipeline.inputs import open_sequence

    root = config.dataset.root
    rows, notes, blocking = [], [], False
    for sid in ids:
        facts = inspect_log(lambda s: open_sequence(config, s, with_poses=False), sid, deep=deep)
        fig = _figures(facts, config.dataset.camera, log=True) if facts.seq is not None else {}
        rows.append(_log_row(facts, fig))
        if facts.seq is not None:
            f = facts.facts
            notes.append(f"  {sid}: {facts.seq.path}: {facts.seq.info.selection}")
            notes.append(f"  {sid}: LiDAR points: {f.lidar_layout}")
            notes += _topic_table(facts)
        for b, msg in facts.problems:
            notes.append(f"  {sid}: {'BLOCKING' if b else 'warning'}: {msg}")
        blocking |= facts.blocking
    mode = (
        "deep: every selected sweep and image decoded"
        if deep
        else "fast: the index, 3 sweeps and 1 image per camera per log"
    )
    widths = [max(len(r[i]) for r in [LOG_HEADER, *rows]) for i in range(len(LOG_HEADER))]
    line = lambda r: "  ".join(v.ljust(w) for v, w in zip(r, widths)).rstrip()  # noqa: E731
    table = "\n".join([line(LOG_HEADER), "  ".join("-" * w for w in widths), *map(line, rows)])
    text = [
        f"check-data {root} (robot logs; {mode}; camera {config.dataset.camera})",
        "",
        table,
        "",
    ]
    text += ["details:", *notes] if notes else []
    n_block = sum(r[-1] == "BLOCKED" for r in rows)
    text += ["", f"{len(rows)} log(s): " + (f"{n_block} blocked" if blocking else "ready to run")]
    return (1 if blocking else 0), "\n".join(text)


def check_data(
    config: Config,
    deep: bool = False,
    sequences: list[str] | None = None,
    config_path: Path | None = None,
) -> tuple[int, str]:
    """(exit code, report text) for the dataset of ``config`` (dataset.root, dataset.sequences):
    the data's checks, then per sequence the perception source of each stage; exit code 2 when
    the config reads ground truth (gt/) that a sequence lacks (flows/commands/perception_sources.py),
    1 when a problem of the data blocks a run, else 0."""
    from flows.commands.perception_sources import run_problem, source_lines
    from flows.pipeline.plan import selected_sequences

    root = config.dataset.root
    ids = sequences if sequences is not None else selected_sequences(config)
    if not ids:
        return 1, (
            f"{root}: no sequence found (expected the CODa layout, timestamps/<SEQ>.txt ..., or "
            "robot logs: .bag / .mcap files or ROS 2 bag folders)"
        )
    code, text = _check_sequences(config, ids, deep)
    head, _, tail = text.rpartition("\n\n")  # the last paragraph is the verdict
    given = config_path if config_path is not None else "configs/default.yaml"
    text = "\n".join([head, "", f"perception per sequence (config {given}):"])
    text += "\n" + "\n".join(source_lines(config, ids)) + "\n\n" + tail
    problem = run_problem(config, ids, config_path)
    if problem is not None:
        return 2, f"{text.replace('ready to run', 'not ready')}\nREFUSED: {problem}"
    return code, text


def _check_sequences(config: Config, ids: list[str], deep: bool) -> tuple[int, str]:
    from flows.pipeline.inputs import open_sequence, source

    root = config.dataset.root
    if source(config).kind == "log":
        return _check_logs(config, ids, deep)
    rows, notes, blocking = [], [], False
    for sid in ids:
        facts = inspect_sequence(lambda s: open_sequence(config, s), sid, deep=deep)
        fig = _figures(facts, config.dataset.camera) if facts.seq is not None else {}
        rows.append(_row(facts, fig, config.dataset.camera))
        if facts.seq is not None:
            notes.append(f"  {sid}: {facts.seq.info.selection}")
        for b, msg in facts.problems:
            notes.append(f"  {sid}: {'BLOCKING' if b else 'warning'}: {msg}")
        blocking |= facts.blocking
    mode = (
        "deep: every file read" if deep else "fast: sizes, 3 sweeps and 1 image header per sequence"
    )
    text = [
        f"check-data {root} ({mode}; lidar {config.dataset.lidar_source}, images "
        f"{config.dataset.image_source}, camera {config.dataset.camera})",
        "",
        format_table(rows),
        "",
    ]
    text += ["details:", *notes] if notes else []
    n_block = sum(r[-1] == "BLOCKED" for r in rows)
    text += [
        "",
        f"{len(rows)} sequence(s): " + (f"{n_block} blocked" if blocking else "ready to run"),
    ]
    return (1 if blocking else 0), "\n".join(text)
