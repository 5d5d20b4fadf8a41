"""``mobileocc simulate``: write synthetic campus sequences in the CODa layout with ground truth.

Sequence ``i`` of a run is generated with the seed derived from ``(seed, i)``; its frames are made
by :class:`tasks.sim.Simulator` and written through :mod:`storage.sources.coda.writer` (raw data, as a
CODa download holds them: ``3d_comp`` sweeps with nanosecond times, ``2d_rect`` JPEG images of a
stereo pair with a non-identity rectification and its own projection matrix, 3d_bbox boxes and
3d_semantic terrain labels in CODa's ids) and :mod:`storage.gt` (``gt/{SEQ}/``, exact ground
truth). ``split_style`` writes only blocks of frames (as CODa's split downloads hold only the
annotated frames) while timestamps and poses cover every frame. Same arguments -> byte-identical
files.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

FRAME_PERIOD_NS = 100_000_000  # 10 Hz
START_UNIX_S = 1_700_000_000
#: split-style sequences hold blocks of this many raw frames, every other block (1 s on, 1 s off)
SPLIT_BLOCK_FRAMES = 10


def sequence_seed(seed: int, index: int) -> int:
    """The seed of sequence ``index`` of a run with ``seed``."""
    return int(np.random.SeedSequence([int(seed), int(index)]).generate_state(1)[0])


def split_style_frames(frames: int) -> list[int]:
    """The raw frames a split-style sequence of ``frames`` frames holds files for."""
    return [i for i in range(frames) if (i // SPLIT_BLOCK_FRAMES) % 2 == 0]


def _calibration(rig):
    """The rig as a storage Calibration: the rectified cameras with their raw cameras attached."""
    from storage.sequence_data import Calibration, CameraCalibration, RawCameraCalibration

    T0 = rig.camera("cam0").T_cam_from_lidar
    cams = {}
    for c in rig.cameras:
        raw = None
        if c.R_rect is not None:
            R4 = np.eye(4)
            R4[:3, :3] = c.R_rect.T
            P = np.hstack([c.K, np.zeros((3, 1))])
            P[0, 3] = c.K[0, 0] * (c.T_cam_from_lidar @ np.linalg.inv(T0))[0, 3]  # -fx * baseline
            raw = RawCameraCalibration(c.K_raw, c.distortion, c.R_rect, P, R4 @ c.T_cam_from_lidar)
        cams[c.name] = CameraCalibration(
            c.name, c.K, np.zeros(5), c.width, c.height, c.T_cam_from_lidar, raw
        )
    return Calibration(cams, rig.T_base_from_lidar)


def _boxes(frame) -> list:
    from storage.sequence_data import Box3D

    out = []
    p = frame.people
    for k, tid in enumerate(p.track_id):
        if np.linalg.norm(p.box_center[k, :2]) > 40.0:
            continue
        out.append(
            Box3D(
                f"Pedestrian:{int(tid)}",
                "Pedestrian",
                p.box_center[k],
                p.box_size[k],
                np.array([0.0, 0.0, p.box_yaw[k]]),
                p.occlusion[k],
            )
        )
    for ob in frame.objects:
        out.append(
            Box3D(
                f"{ob.obj.class_name}:{ob.obj.instance_id}",
                ob.obj.class_name,
                ob.center,
                ob.obj.size,
                np.array([0.0, 0.0, ob.yaw]),
                "Unknown",
            )
        )
    return out


def write_frame(out: Path, seq: int, frame, stamp_ns: int, image_ext: str = ".jpg") -> None:
    """Write one SimFrame: LiDAR, both images, boxes, CODa terrain labels, ground truth."""
    from storage.sources.coda import writer as W
    from tasks.sim.sensors import coda_semantic_ids

    s = frame.sweep
    W.write_lidar(out, seq, frame.index, s.points, s.intensity, s.time_s)
    W.write_image(out, seq, "cam0", frame.index, frame.cam0.rgb, image_ext)
    W.write_image(out, seq, "cam1", frame.index, frame.cam1.rgb, image_ext)
    W.write_boxes(out, seq, frame.index, _boxes(frame))
    W.write_semantic(out, seq, frame.index, coda_semantic_ids(s.point_class))
    write_frame_gt(out, seq, frame, stamp_ns)


def write_frame_gt(out: Path, seq: int, frame, stamp_ns: int) -> None:
    """The ground truth of one SimFrame (``gt/{SEQ}/``), whatever the format of the raw data."""
    from storage import gt as GT

    s, p = frame.sweep, frame.people
    GT.write_frame_gt(
        out,
        seq,
        frame.index,
        {
            "occupancy": frame.occupancy,
            "occupancy_instance": frame.occupancy_instance,
            "point_class": s.point_class,
            "point_instance": s.point_instance,
            "T_world_from_lidar": frame.T_world_from_lidar,
            "T_world_from_base": frame.T_world_from_base,
            "stamp_ns": np.int64(stamp_ns),
            "cam0_semantic": frame.cam0.cityscapes,
            "cam0_instance": frame.cam0.instance,
            "track_id": p.track_id,
            "betas": p.betas,
            "global_orient": p.global_orient,
            "body_pose": p.body_pose,
            "transl": p.transl,
            "vertices": p.vertices,
            "joints": p.joints,
            "velocity_base": p.velocity_base,
            "box2d": p.box2d,
            "keypoints": p.keypoints,
            "visible_fraction": p.visible_fraction,
            "box_center": p.box_center,
            "box_size": p.box_size,
            "box_yaw": p.box_yaw,
            "vertex_velocity_base": p.vertex_velocity_base,
        },
    )


#: ``--fast``: cameras at this fraction of CODa's 1224 x 1024 (612 x 512, same field of view)
FAST_IMAGE_SCALE = 0.5


def make_simulator(opts, fast: bool = False):
    """The Simulator of one sequence; ``fast``: cameras at FAST_IMAGE_SCALE (see README)."""
    from tasks.sim import Simulator
    from tasks.sim.sensors import make_rig

    return Simulator(opts, rig=make_rig(opts.sensor, image_scale=FAST_IMAGE_SCALE if fast else 1.0))


def _limit_threads() -> int:
    """One torch thread (returns the previous count). The body model's float32 sums depend on
    torch's thread count (vertices differ by ~5e-7 m between 1 and 2 threads, and so do the LiDAR
    returns on people), so every frame is made on one thread: the files are the same bytes on any
    machine and for any number of frame workers, which are the parallelism."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    return before


#: the Simulator of the sequence a frame worker is on (one sequence at a time per worker)
_WORKER_SIM: dict = {}


def _write_frames(
    out: str, seq: int, opts, fast: bool, indices: list[int], stamps_ns: list[int], image_ext: str
) -> int:
    """Simulate and write ``indices`` of sequence ``seq`` (in a frame worker or in-process)."""
    key = (seq, opts, fast)
    if _WORKER_SIM.get("key") != key:
        _WORKER_SIM.clear()
        _WORKER_SIM.update(key=key, sim=make_simulator(opts, fast))
    sim = _WORKER_SIM["sim"]
    for i, stamp in zip(indices, stamps_ns):
        write_frame(Path(out), seq, sim.frame(i), int(stamp), image_ext)
    return len(indices)


def _chunks(items: list[int], n: int) -> list[list[int]]:
    return [items[i : i + n] for i in range(0, len(items), n)]


#: raw-data formats of ``mobileocc simulate``: the CODa layout, or robot logs (one per sequence)
FORMATS = ("coda", "mcap", "ros1")


def log_cameras(rig) -> list:
    """The rig's cameras as a log records them (storage.sources.log.writer.LogCamera): the raw
    camera's K, D, R, P and extrinsic, the values the CODa calibration files hold."""
    from storage.sources.log.writer import LogCamera

    out = []
    for name, cam in _calibration(rig).cameras.items():
        if cam.raw is not None:
            r = cam.raw
            out.append(
                LogCamera(
                    name, cam.width, cam.height, r.K, r.distortion, r.R_rect, r.P_rect,
                    r.T_cam_from_lidar,
                )
            )  # fmt: skip
        else:
            P = np.hstack([cam.K, np.zeros((3, 1))])
            out.append(
                LogCamera(
                    name, cam.width, cam.height, cam.K, np.zeros(5), np.eye(3), P,
                    cam.T_cam_from_lidar,
                )
            )  # fmt: skip
    return out


def log_base_pose(T_world_from_lidar: np.ndarray, T_base_from_lidar: np.ndarray):
    """(t (3,), q_wxyz (4,)) of T_world_from_base for a log's /tf or /odom, from the LiDAR pose
    as the CODa poses file records it (storage.sources.coda.writer.recorded_pose), so both formats of a
    scene hold the same poses (exactly so for the simulator's rig, whose LiDAR is not rotated on
    the base)."""
    from storage.sources.coda import writer as W
    from tasks.poses.rotations import matrix_to_quat_wxyz, quat_wxyz_to_matrix

    t_wl, q_wl = W.recorded_pose(T_world_from_lidar)
    R_bl = np.asarray(T_base_from_lidar, np.float64)[:3, :3]
    q = (
        q_wl
        if np.array_equal(R_bl, np.eye(3))
        else matrix_to_quat_wxyz(quat_wxyz_to_matrix(q_wl) @ R_bl.T)
    )
    return t_wl - quat_wxyz_to_matrix(q) @ np.asarray(T_base_from_lidar)[:3, 3], q


def _log_records(
    out: str, seq: int, opts, fast: bool, indices: list[int], stamps_ns: list[int], image_ext: str
) -> list[dict]:
    """Simulate ``indices`` (in a frame worker or in-process): ground truth written here, the
    raw data returned for the log writer (one writer per log, in the parent)."""
    from storage.sources.coda import writer as W

    key = (seq, opts, fast)
    if _WORKER_SIM.get("key") != key:
        _WORKER_SIM.clear()
        _WORKER_SIM.update(key=key, sim=make_simulator(opts, fast))
    sim, records = _WORKER_SIM["sim"], []
    for i, stamp in zip(indices, stamps_ns):
        frame = sim.frame(i)
        write_frame_gt(Path(out), seq, frame, int(stamp))
        s = frame.sweep
        records.append(
            {
                "index": i,
                "points": s.points,
                "intensity": s.intensity,
                "t_ns": W.recorded_time_ns(s.time_s),
                "images": {
                    "cam0": W.image_bytes(frame.cam0.rgb, image_ext),
                    "cam1": W.image_bytes(frame.cam1.rgb, image_ext),
                },
            }
        )
    return records


def _write_log_sequence(
    out: Path, seq: int, opts, fast: bool, stamps: np.ndarray, image_ext: str, fmt: str,
    log_poses: str, pool, bar,
) -> None:  # fmt: skip
    """One sequence as one robot log ``out/{seq}.mcap`` / ``.bag`` (storage.sources.log.writer)."""
    from storage.sources.coda import writer as W
    from storage.sources.log.writer import SUFFIX, LogWriter

    sim = make_simulator(opts, fast)
    frames = list(range(len(stamps)))
    recorded = [W.recorded_stamp_ns(int(s)) for s in stamps]
    writer = LogWriter(
        out / f"{seq}{SUFFIX[fmt]}",
        fmt,
        log_cameras(sim.rig),
        sim.rig.T_base_from_lidar,
        poses=log_poses,
        image_format=image_ext.lstrip(".").replace("jpg", "jpeg"),
    )
    try:
        writer.write_static(recorded[0])
        size = max(1, min(16, -(-len(frames) // 8)))
        chunks = _chunks(frames, size)
        args = [
            (str(out), seq, opts, fast, c, [int(stamps[i]) for i in c], image_ext) for c in chunks
        ]
        results = (
            pool.map(_log_records, *zip(*args)) if pool is not None
            else (_log_records(*a) for a in args)
        )  # fmt: skip
        for records in results:
            for r in records:
                i, stamp = r["index"], recorded[r["index"]]
                if log_poses != "none":
                    t, q = log_base_pose(sim.robot_pose(i)[1], sim.rig.T_base_from_lidar)
                    writer.write_pose(stamp, t, q)
                writer.write_sweep(stamp, r["points"], r["intensity"], r["t_ns"])
                for cam, data in r["images"].items():
                    writer.write_image(stamp, cam, data)
                bar.update(1)
    except BaseException:
        writer.abort()
        raise
    writer.close()
    _write_sequence_gt(out, seq, sim)


def simulate(
    out: Path,
    sequences: int,
    frames: int,
    seed: int,
    pedestrians: int | None = None,
    crowd: str = "uncrowded",
    night: bool = False,
    sensor: str = "os1-128",
    progress: bool = True,
    first_id: int = 0,
    image_ext: str = ".jpg",
    split_style: bool = False,
    fast: bool = False,
    workers: int = 1,
    frame_step: int = 1,
    fmt: str = "coda",
    log_poses: str | None = None,
) -> list[int]:
    """Write ``sequences`` synthetic sequences (ids first_id..first_id+sequences-1) of ``frames``
    raw 10 Hz frames under ``out`` in the CODa layout plus ``gt/``. Returns the sequence ids
    written. Sequence ``s`` is seeded from (seed, s), so a benchmark can add sequences of another
    condition (``--night``, ``--crowd``) beside existing ones with a different ``first_id``.
    image_ext: ".jpg" (CODa's downloads) or ".png" (the devkit's own rectification tool).
    split_style: files only for :func:`split_style_frames` (timestamps, poses: every frame).
    fast: cameras at FAST_IMAGE_SCALE (612 x 512; everything else, the ground truth included, as
    without it). workers: frame worker processes (each frame is a pure function of the
    sequence's options and its index, so the files are the same bytes for any number).
    frame_step: files only for every ``frame_step``-th raw frame (2: the 5 Hz frames the pipeline
    keeps, half the simulation; timestamps and poses: every frame).
    fmt: "coda" (the CODa layout), "mcap" (ROS 2 MCAP) or "ros1" (ROS 1 bag): one log per
    sequence, ``out/{SEQ}.mcap`` / ``.bag``, with real drivers' topics (storage.sources.log.writer)
    and ``gt/`` beside. log_poses: the logs' world poses, "tf" (/tf map -> base_link; the default
    for mcap), "odometry" (nav_msgs/Odometry on /odom; the default for ros1) or "none"."""
    from tqdm import tqdm

    from tasks.sim import SimOptions

    if sequences < 0:
        raise ValueError(f"sequences must be >= 0, got {sequences}")
    if first_id < 0:
        raise ValueError(f"first_id must be >= 0, got {first_id}")
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if frame_step < 1:
        raise ValueError(f"frame_step must be >= 1, got {frame_step}")
    if fmt not in FORMATS:
        raise ValueError(f"format must be one of {FORMATS}, got {fmt!r}")
    if fmt != "coda" and (split_style or frame_step != 1):
        raise ValueError("split_style and frame_step apply to the CODa layout only")
    log_poses = log_poses or ("odometry" if fmt == "ros1" else "tf")
    out = Path(out)
    written_frames = split_style_frames(frames) if split_style else list(range(frames))
    written_frames = written_frames[::frame_step]
    bar = tqdm(
        total=sequences * len(written_frames),
        desc="simulate",
        unit="frame",
        disable=not progress or not sys.stderr.isatty(),  # a bar only on a terminal
    )
    pool = None
    if workers > 1 and sequences * len(written_frames) > 1:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        pool = ProcessPoolExecutor(
            workers, mp_context=mp.get_context("spawn"), initializer=_limit_threads
        )
    written = []
    threads = _limit_threads()
    try:
        for seq in range(first_id, first_id + sequences):
            opts = SimOptions(
                seed=sequence_seed(seed, seq),
                frames=frames,
                pedestrians=pedestrians,
                crowd=crowd,
                night=night,
                sensor=sensor,
            )
            start_ns = (START_UNIX_S + 3600 * seq) * 1_000_000_000
            stamps = start_ns + FRAME_PERIOD_NS * np.arange(frames, dtype=np.int64)
            if fmt != "coda":
                _write_log_sequence(
                    out, seq, opts, fast, stamps, image_ext, fmt, log_poses, pool, bar
                )
                written.append(seq)
                continue
            if pool is None:
                for i in written_frames:
                    _write_frames(str(out), seq, opts, fast, [i], [int(stamps[i])], image_ext)
                    bar.update(1)
            else:
                size = max(1, min(16, -(-len(written_frames) // (4 * workers))))
                futures = [
                    pool.submit(
                        _write_frames,
                        str(out),
                        seq,
                        opts,
                        fast,
                        c,
                        [int(stamps[i]) for i in c],
                        image_ext,
                    )
                    for c in _chunks(written_frames, size)
                ]
                from concurrent.futures import as_completed

                for fut in as_completed(futures):
                    bar.update(fut.result())
            _write_sequence_files(out, seq, opts, fast, frames, stamps, seed, written_frames)
            written.append(seq)
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
        _WORKER_SIM.clear()
        bar.close()
        import torch

        torch.set_num_threads(threads)
    return written


def _write_sequence_gt(out: Path, seq: int, sim) -> None:
    """``gt/{SEQ}/sequence.npz``: the grid, the body model's faces, the rig's base."""
    from storage import gt as GT

    GT.write_sequence_gt(
        out,
        seq,
        {
            "grid_range_min": np.asarray(sim.grid.range_min, np.float64),
            "grid_voxel_size_m": np.float64(sim.grid.voxel_size_m),
            "grid_shape": np.asarray(sim.grid.shape, np.int64),
            "person_faces": np.asarray(sim.person_faces, np.int64),
            "keypoint_vertex_ids": np.asarray(sim.model.keypoint_vertex_ids, np.int64),
            "T_base_from_lidar": sim.rig.T_base_from_lidar,
        },
    )


def _write_sequence_files(
    out: Path,
    seq: int,
    opts,
    fast: bool,
    frames: int,
    stamps: np.ndarray,
    seed: int,
    written_frames: list[int],
) -> None:
    """Calibration, timestamps, poses, the sequence's ground truth, then the metadata (last: its
    presence marks a complete sequence)."""
    from storage.sources.coda import writer as W

    sim = (
        make_simulator(opts, fast)
        if _WORKER_SIM.get("key") != (seq, opts, fast)
        else _WORKER_SIM["sim"]
    )
    poses = [sim.robot_pose(i)[1] for i in range(frames)]
    W.write_calibration(out, seq, _calibration(sim.rig))
    W.write_timestamps(out, seq, stamps)
    W.write_poses(out, seq, stamps, np.asarray(poses))
    _write_sequence_gt(out, seq, sim)
    fast_keys = {"simulation": "fast", "image_scale": FAST_IMAGE_SCALE} if fast else {}
    W.write_metadata(
        out,
        seq,
        {
            "synthetic": True,
            "lighting": "night" if opts.night else "day",
            "crowd": opts.crowd,
            "seed": opts.seed,
            "run_seed": int(seed),
            "frames": frames,
            "sensor": opts.sensor,
            "pedestrians": opts.num_pedestrians,
            "frame_rate_hz": 10.0,
            "generator": "mobileocc.tasks.sim",
            "trajectory": seq,
            **fast_keys,
            **W.annotation_lists(seq, written_frames, written_frames),
        },
    )
