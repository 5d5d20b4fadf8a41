"""Peak memory of the map and fuse stages against the length of a sequence (issue 17).

``bench_memory(frames, work_dir)`` writes one synthetic sequence per length in the CODa layout
(a walk along a campus-like strip of constant density, tasks/occupancy/synthetic.py
``campus_strip``: out for half the frames at 0.2 m per frame, 1 m/s at 5 Hz, then back over the
same places, so every length revisits its whole path; organised OS1-128 sweeps ray cast from each
pose; the walk back re-uses the sweeps of the way out by hard links, the robot reversing), plus
detections as the detect stage would write them (a road / building semantic image, no people).
Then, for each length, the real map stage and the real fuse stage (``execute_unit``, default
settings, bodies from the fit stage: none here) each run in a fresh spawned process, and the
process reports ``resource.getrusage(RUSAGE_SELF).ru_maxrss``: its peak, its baseline (the peak
after imports and opening the sequence, before the stage) and what the stage added. With
``untiled``, the whole-sequence reference mapper (:class:`tasks.occupancy.mapping.SequenceMapper`,
the design before tiles) is measured the same way on the same sequence.

Run: ``mobileocc bench memory --work DIR [--frames 200 1000 2000] [--untiled] [--json FILE]``.
"""

from __future__ import annotations

import json
import os
import resource
import time
from pathlib import Path

import numpy as np

from flows.bench.common import machine, make_config, spawned
from storage.atomic import atomic_write_text, move_into_place

STEP_M = 0.2
#: ray range of the synthetic sweeps, m (the OS1's nominal range)
SWEEP_RANGE_M = 120.0
#: sequence ids: the length (5 Hz frames) plus this
SEQ_BASE = 700_000


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _write_detections(
    folder: Path, raw_frames: list[int], K: np.ndarray, height: int, width: int
) -> None:
    """One Detections product (rows below the horizon road, above building, nobody), hard-linked
    as every frame's, and the detect stage's summary."""
    from storage.products import Detections

    semantic = np.where(np.arange(height)[:, None] > K[1, 2], 0, 2).astype(np.uint8) * np.ones(
        (1, width), np.uint8
    )
    d = Detections.empty(H=height, W=width)
    first = Detections(**{**d.arrays(), "semantic": semantic}).write(
        folder, Detections.file_name(raw_frames[0])
    )
    for raw in raw_frames[1:]:
        target = folder / f"{Detections.file_name(raw)}.npz"
        if not target.exists():
            os.link(first, target)
    # the frames the detect stage produced (the later stages read them from its summary)
    atomic_write_text(
        folder / "summary.json",
        json.dumps({"implemented": True, "frames": list(raw_frames), "failed_frames": []}),
    )


def make_sequences(root: Path, frames: list[int], seed: int = 0) -> dict[int, dict]:
    """Write the synthetic sequences (id SEQ_BASE + length) under root/data and their detections
    under root/detect/<id>; returns {length: {"sequence", "detect_dir", "distinct_sweeps", ...}}."""
    from flows.commands.simulate import _calibration
    from storage.sources.coda import writer as W
    from tasks.occupancy.synthetic import (
        build_scene,
        campus_strip,
        organised_sweep,
        os1_directions,
        strip_poses,
    )
    from tasks.sim.sensors import make_rig

    data, rig = Path(root) / "data", make_rig()
    half = max((n + 1) // 2 for n in frames)
    poses = strip_poses(half, STEP_M, float(rig.T_base_from_lidar[2, 3]))
    pool = Path(root) / "pool"
    t0 = time.perf_counter()
    missing = [k for k in range(half) if not (pool / f"{k}.bin").exists()]
    if missing:
        scene, dirs = build_scene(campus_strip(half * STEP_M, seed)), os1_directions(128, 1024)
        zeros = np.zeros(128 * 1024, np.float32)
        for k in missing:
            path = W.write_lidar(
                pool, 0, k, organised_sweep(scene, poses[k], dirs, SWEEP_RANGE_M), zeros, zeros
            )
            move_into_place(path, pool / f"{k}.bin")
    sim_s = time.perf_counter() - t0
    cam = rig.camera("cam0")
    image = pool / "image.jpg"
    if not image.exists():  # the reader wants each frame's camera files; nothing here reads them
        move_into_place(
            W.write_image(pool, 0, "cam0", 0, np.full((cam.height, cam.width, 3), 128, np.uint8)),
            image,
        )
    out = {}
    for n in frames:
        seq = SEQ_BASE + n
        order = [
            k if k < (n + 1) // 2 else n - 1 - k for k in range(n)
        ]  # out, then back the same way
        for k, src in enumerate(order):
            target = W.lidar_path(data, seq, 2 * k)
            if not target.exists():
                target.parent.mkdir(parents=True, exist_ok=True)
                os.link(pool / f"{src}.bin", target)
            for name in ("cam0", "cam1"):
                if not W.image_path(data, seq, name, 2 * k).exists():
                    W.image_path(data, seq, name, 2 * k).parent.mkdir(parents=True, exist_ok=True)
                    os.link(image, W.image_path(data, seq, name, 2 * k))
        stamps = 1_673_884_185_000_000_000 + 100_000_000 * np.arange(2 * n, dtype=np.int64)
        W.write_calibration(data, seq, _calibration(rig))
        W.write_timestamps(data, seq, stamps)
        W.write_poses(data, seq, stamps, np.repeat(poses[order], 2, axis=0))
        W.write_metadata(
            data, seq, {"synthetic": True, "lighting": "day", "generator": "flows.bench.memory"}
        )
        detect = Path(root) / "detect" / str(seq)
        _write_detections(detect, [2 * k for k in range(n)], cam.K, cam.height, cam.width)
        out[n] = {
            "sequence": str(seq),
            "detect_dir": str(detect),
            "distinct_sweeps": (n + 1) // 2,
            "path_m": round(((n + 1) // 2 - 1) * STEP_M, 1),
        }
    out["simulate_s"] = sim_s
    return out


def _unit(cfg, sequence: str, stage: str):
    """The stage's unit without hashing the inputs (the key only names the output folder)."""
    from flows.pipeline.inputs import sequence_ref, stage_inputs
    from flows.pipeline.plan import UnitPlan

    return UnitPlan(
        sequence,
        stage,
        f"bench-{stage}-{sequence}",
        {},
        False,
        "bench",
        stage_inputs(cfg)[stage],
        sequence_ref(cfg, sequence),
    )


def _made(sequence: str, stage: str, location: str):
    """The outcome of a unit whose product the bench made itself at ``location``."""
    from flows.pipeline.outcome import Status, UnitOutcome

    return UnitOutcome(sequence, stage, "", {}, Status.DONE, location=location)


def _stage_process(
    data_root: str, out_root: str, sequence: str, stage: str, upstream: dict, overrides: dict
) -> dict:
    """In a fresh process: one stage of one sequence; its peak RSS and its baseline."""
    import flows.stages  # noqa: F401  (every stage and kernel imported before the baseline)
    from flows.pipeline.inputs import runtime, source
    from flows.pipeline.outcome import Status
    from flows.pipeline.units import execute_unit

    cfg = make_config(Path(data_root), Path(out_root), overrides)
    frames = len(source(cfg).open(_unit(cfg, sequence, stage).ref))
    base, c0, t0 = _peak_mb(), time.process_time(), time.perf_counter()
    outcome = execute_unit(
        _unit(cfg, sequence, stage), Path(out_root), upstream, "bench", runtime(cfg)
    )
    if outcome.status != Status.DONE:
        raise RuntimeError(f"{stage} of sequence {sequence}: {outcome.error}\n{outcome.traceback}")
    return {
        "frames": frames,
        "peak_rss_mb": _peak_mb(),
        "baseline_rss_mb": base,
        "stage_rss_mb": _peak_mb() - base,
        "wall_s": time.perf_counter() - t0,
        "cpu_s": time.process_time() - c0,
        "outcome": outcome,
    }


def _untiled_process(data_root: str, sequence: str, detect_dir: str, overrides: dict) -> dict:
    """In a fresh process: the whole-sequence SequenceMapper over the sequence (the design before
    tiles: both maps whole in memory), peak RSS as :func:`_stage_process`."""
    import flows.stages  # noqa: F401
    from flows.pipeline.inputs import map_inputs, sequence_ref, source
    from storage.products import Detections
    from tasks.conventions import UNLABELED
    from tasks.occupancy.mapping import SequenceMapper

    cfg = make_config(Path(data_root), Path(data_root) / "unused", overrides)
    inp, seq = map_inputs(cfg), source(cfg).open(sequence_ref(cfg, sequence))
    cam = seq.info.calibration.cameras[inp.source.camera]
    lut = np.full(256, UNLABELED, np.uint8)
    lut[[k for k, _ in inp.class_lut]] = [v for _, v in inp.class_lut]
    base, t0 = _peak_mb(), time.perf_counter()
    mapper = SequenceMapper(
        inp.settings,
        inp.freespace,
        lut,
        cam.K,
        cam.T_cam_from_lidar,
        cam.width,
        cam.height,
        inp.assoc_min_iou,
        point_classes=inp.point_classes,
        geometry=inp.geometry,
    )
    for i in range(len(seq)):
        f = seq.frame(i)
        d = Detections.read(Path(detect_dir), Detections.file_name(f.index))
        mapper.add_sweep(
            f.points_lidar,
            f.T_world_from_lidar,
            d.semantic,
            d.mask_labels,
            d.boxes_xyxy,
            d.lidar_centers,
            d.lidar_sizes,
            d.lidar_yaws,
            d.lidar_scores,
            f.intensity if f.intensity_present else None,
        )
    final, _ = mapper.finish(inp.ground_class_ids)
    keys, _ = mapper.occupancy.to_arrays()
    return {
        "frames": len(seq),
        "peak_rss_mb": _peak_mb(),
        "baseline_rss_mb": base,
        "stage_rss_mb": _peak_mb() - base,
        "wall_s": time.perf_counter() - t0,
        "static_voxels": len(final.keys),
        "occupancy_voxels": len(keys),
    }


def bench_memory(
    frames: list[int],
    work_dir: Path,
    untiled: bool = False,
    overrides: dict | None = None,
    stages: tuple[str, ...] = ("map", "fuse"),
) -> dict:
    """Peak RSS (MB) of the map and fuse stages per sequence length (5 Hz frames), each stage run
    in a fresh spawned process on a synthetic sequence of that length (module docstring).

    Returns {"frames": [...], "map": {n: {...}}, "fuse": {n: {...}}, "untiled_map": {n: {...}}
    (with ``untiled``), "ratio": {stage: peak(longest) / peak(shortest)}, "sequences": {...},
    "machine": {...}}. work_dir keeps the data between calls (sweeps are made once)."""

    work = Path(work_dir)
    frames = sorted(int(n) for n in frames)
    overrides = dict(overrides or {})
    made = make_sequences(work, frames)
    out: dict = {"frames": frames, "sequences": made, "overrides": overrides, "machine": machine()}
    for n in frames:
        seq, detect = made[n]["sequence"], made[n]["detect_dir"]
        outroot = work / "out" / str(n)
        if "map" in stages or "fuse" in stages:
            m = spawned(
                _stage_process,
                str(work / "data"),
                str(outroot),
                seq,
                "map",
                {"detect": _made(seq, "detect", detect)},
                overrides,
            )
            out.setdefault("map", {})[n] = {k: v for k, v in m.items() if k != "outcome"} | {
                "summary": m["outcome"].summary
            }
        if "fuse" in stages:
            f = spawned(
                _stage_process,
                str(work / "data"),
                str(outroot),
                seq,
                "fuse",
                {"map": m["outcome"], "detect": _made(seq, "detect", detect)},
                overrides,
            )
            out.setdefault("fuse", {})[n] = {k: v for k, v in f.items() if k != "outcome"}
        if untiled:
            out.setdefault("untiled_map", {})[n] = spawned(
                _untiled_process, str(work / "data"), seq, detect, overrides
            )
    lo, hi = frames[0], frames[-1]
    out["ratio"] = {
        k: out[k][hi]["peak_rss_mb"] / out[k][lo]["peak_rss_mb"]
        for k in ("map", "fuse", "untiled_map")
        if k in out
    }
    out["stage_ratio"] = {
        k: out[k][hi]["stage_rss_mb"] / max(out[k][lo]["stage_rss_mb"], 1e-9)
        for k in ("map", "fuse", "untiled_map")
        if k in out
    }
    return out


def format_table(r: dict) -> str:
    """The RSS table of :func:`bench_memory`."""
    kinds = [k for k in ("map", "fuse", "untiled_map") if k in r]
    lines = [f"{'frames':>7}" + "".join(f"{k + ' peak / +stage MB':>30}" for k in kinds)]
    for n in r["frames"]:
        lines.append(
            f"{n:>7}"
            + "".join(
                f"{r[k][n]['peak_rss_mb']:>20.0f} / {r[k][n]['stage_rss_mb']:>+7.0f}" for k in kinds
            )
        )
    lines.append(
        f"{'ratio':>7}"
        + "".join(f"{r['ratio'][k]:>20.2f} / {r['stage_ratio'][k]:>7.2f}" for k in kinds)
    )
    m = r["machine"]
    lines.append(
        f"machine: {m['cpu_count']} cpus, load {m['load_avg_1m']:.1f}; ratio = peak({r['frames'][-1]}) / "
        f"peak({r['frames'][0]})"
    )
    return "\n".join(lines)
