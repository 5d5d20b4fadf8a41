"""Storage benchmark: zarr store write throughput vs raw numpy, bytes per frame, export time.

``bench_store(quick)`` returns a dict of figures (no prefect; the CLI ``mobileocc bench`` calls it).
Content is realistic for the pipeline's output: mostly free / unknown, a ground plane of road and
terrain, a few boxes (a car, people, a pole, a wall), masks observed in a forward wedge, a few
pedestrian voxels with velocity. Every figure is measured against writing the same dense bytes
with ``ndarray.tofile`` to the same disk in the same run.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from storage import occupancy_store as occ
from storage import publish as pub
from tasks.conventions import (
    CAR,
    FREE,
    OTHER_STRUCTURE,
    PEDESTRIAN,
    POLE,
    ROAD,
    TERRAIN,
)

RANGE_MIN = np.array([0.4, -4.8, -1.0])
RANGE_MAX = np.array([10.0, 4.8, 3.8])


def synthetic_frames(n: int, voxel_size_m: float, seed: int = 0) -> dict[str, np.ndarray]:
    """n frames of realistic-looking output on the benchmark range at ``voxel_size_m``."""
    rng = np.random.default_rng(seed)
    shape = tuple(int(round(v)) for v in (RANGE_MAX - RANGE_MIN) / voxel_size_m)
    X, Y, Z = shape

    def idx(p, axis):  # metres -> voxel index along axis
        return int(np.clip((p - RANGE_MIN[axis]) / voxel_size_m, 0, shape[axis]))

    sem = np.full((n, *shape), FREE, np.uint8)
    inst = np.zeros((n, *shape), np.uint16)
    vel = np.zeros((n, *shape, 2), np.float16)
    ground = idx(0.0, 2)
    sem[:, :, : idx(0.0, 1), ground] = ROAD
    sem[:, :, idx(0.0, 1) :, ground] = TERRAIN
    for f in range(n):
        dx = 0.1 * f
        sem[
            f,
            idx(6 + dx, 0) : idx(9.5 + dx, 0),
            idx(-3.5, 1) : idx(-1.8, 1),
            ground + 1 : idx(1.5, 2),
        ] = CAR
        sem[f, idx(2, 0) : idx(9, 0), idx(4.2, 1) : idx(4.6, 1), ground + 1 : idx(3, 2)] = (
            OTHER_STRUCTURE
        )
        sem[f, idx(5, 0) : idx(5.2, 0), idx(2, 1) : idx(2.2, 1), ground + 1 : idx(3.5, 2)] = POLE
        for k in range(3):
            x0, y0 = 2.5 + 2 * k + dx, -1.0 + k
            box = (
                f,
                slice(idx(x0, 0), idx(x0 + 0.5, 0)),
                slice(idx(y0, 1), idx(y0 + 0.5, 1)),
                slice(ground + 1, idx(1.8, 2)),
            )
            sem[box] = PEDESTRIAN
            inst[box] = k + 1
            vel[box] = (1.2, 0.3 * k)
    # a little label noise on surfaces, as real fused output has
    noise = rng.random((n, X, Y)) < 0.02
    sem[:, :, :, ground][noise] = TERRAIN
    # observed: a forward wedge of +-40 deg up to the first obstacle height
    xs = RANGE_MIN[0] + (np.arange(X) + 0.5) * voxel_size_m
    ys = RANGE_MIN[1] + (np.arange(Y) + 0.5) * voxel_size_m
    wedge = np.abs(np.arctan2(ys[None, :], xs[:, None])) < np.deg2rad(40)
    mask_lidar = np.zeros((n, *shape), np.uint8)
    mask_lidar[:, wedge, : idx(2.5, 2)] = 1
    mask_camera = mask_lidar.copy()
    mask_camera[:, :, :, idx(1.5, 2) :] = 0
    return {
        "semantics": sem,
        "instances": inst,
        "mask_lidar": mask_lidar,
        "mask_camera": mask_camera,
        "velocity": vel,
    }


def _dir_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def _bench_grid(
    work: Path, voxel_size_m: float, n: int, fpc: int, repeats: int, skip_empty: bool | None = None
) -> dict:
    frames = synthetic_frames(fpc, voxel_size_m)
    grid = frames["semantics"].shape[1:]
    raw_bytes_per_frame = sum(a[0].nbytes for a in frames.values())
    t_store, t_raw = [], []
    for r in range(repeats):
        path = work / f"store-{voxel_size_m}-{r}.zarr"
        layout = occ.create_store(
            path, n, grid, fpc, {"voxel_size_m": voxel_size_m}, skip_empty_chunks=skip_empty
        )
        t0 = time.perf_counter()
        for start, stop in layout.write_units():
            occ.write_frames(path, start, {k: v[: stop - start] for k, v in frames.items()})
        t_store.append(time.perf_counter() - t0)
        stored = _dir_bytes(path)
        shutil.rmtree(path) if r + 1 < repeats else None
        raw_dir = work / f"raw-{r}"
        raw_dir.mkdir()
        t0 = time.perf_counter()
        for start in range(0, n, fpc):
            for k, v in frames.items():
                v[: min(fpc, n - start)].tofile(raw_dir / f"{k}-{start}.bin")
        t_raw.append(time.perf_counter() - t0)
        shutil.rmtree(raw_dir)
    ts, tr = min(t_store), min(t_raw)
    t0 = time.perf_counter()
    occ.read_frames(path, slice(0, min(fpc, n)))
    t_read = time.perf_counter() - t0
    return {
        "voxel_size_m": voxel_size_m,
        "grid": list(grid),
        "frames": n,
        "frames_per_chunk": layout.frames_per_chunk,
        "chunk_shape": list(layout.chunk_shape),
        "sharded": layout.sharded,
        "skip_empty_chunks": bool(occ.read_attrs(path)["skip_empty_chunks"]),
        "store_frames_per_s": n / ts,
        "store_raw_MB_per_s": n * raw_bytes_per_frame / ts / 1e6,
        "numpy_tofile_frames_per_s": n / tr,
        "store_vs_numpy_speed": tr / ts,
        "dense_bytes_per_frame": raw_bytes_per_frame,
        "stored_bytes_per_frame": stored / n,
        "compression_ratio": raw_bytes_per_frame * n / stored,
        "read_frames_per_s": min(fpc, n) / t_read,
    }


def _bench_export(work: Path, n: int) -> dict:
    from PIL import Image

    from storage.export import export_nuscenes, export_occ3d

    root = work / "ds"
    frames = synthetic_frames(n, 0.2)
    eye = np.eye(4)
    with pub.sequence_writer(root, "s0", "k") as staged:
        layout = occ.create_store(
            staged.store_path,
            n,
            frames["semantics"].shape[1:],
            50,
            {"voxel_size_m": 0.2, "range_min": RANGE_MIN.tolist(), "range_max": RANGE_MAX.tolist()},
        )
        for start, stop in layout.write_units():
            occ.write_frames(
                staged.store_path, start, {k: v[start:stop] for k, v in frames.items()}
            )
        rows = []
        for f in range(n):
            raw = np.zeros((131072, 5), np.float32)
            raw[:60000, :3] = np.random.default_rng(f).normal(0, 5, (60000, 3))
            (root / "src").mkdir(parents=True, exist_ok=True)
            raw.tofile(root / "src" / f"{f}.bin")
            Image.fromarray(np.zeros((1024, 1224, 3), np.uint8)).save(root / "src" / f"{f}.png")
            rows.append(
                {
                    "frame": f,
                    "raw_frame": 2 * f,
                    "stamp_ns": 10**18 + f * 2 * 10**8,
                    "T_world_from_lidar": eye.ravel(),
                    "T_world_from_base": eye.ravel(),
                    "lidar_path": f"src/{f}.bin",
                    "cam0_path": f"src/{f}.png",
                }
            )
        pub.stage_table(staged, "frames", rows)
        pub.stage_table(
            staged,
            "instances",
            [
                {
                    "track_id": 1,
                    "frame": f,
                    "box3d_center": [3, 0, 0.9],
                    "box3d_size": [0.6, 0.5, 1.8],
                    "box3d_yaw": 0.0,
                }
                for f in range(n)
            ],
        )
        pub.stage_table(
            staged,
            "sequences",
            [
                {
                    "fingerprint": "x",
                    "config_hash": "c",
                    "code_version": "0",
                    "status": "ok",
                    "num_frames": n,
                    "K": np.eye(3).ravel(),
                    "T_cam0_from_lidar": eye.ravel(),
                    "T_base_from_lidar": eye.ravel(),
                    "image_width": 1224,
                    "image_height": 1024,
                }
            ],
        )
    t0 = time.perf_counter()
    export_occ3d(root, work / "occ3d")
    t_occ = time.perf_counter() - t0
    t0 = time.perf_counter()
    export_nuscenes(root, work / "nusc")
    t_nus = time.perf_counter() - t0
    return {"export_frames": n, "occ3d_s_per_frame": t_occ / n, "nuscenes_s_per_frame": t_nus / n}


def bench_store(quick: bool = True, work_dir: str | Path | None = None) -> dict:
    """Measure the store and the exports; ``quick`` uses fewer frames (about a minute on 2 cores)."""
    work = Path(tempfile.mkdtemp(prefix="mobileocc-bench-", dir=work_dir))
    try:
        coarse = _bench_grid(work, 0.2, 200 if quick else 2000, 50, 2 if quick else 3)
        fine = _bench_grid(work, 0.02, 2 if quick else 4, 1, 1 if quick else 2)
        fine_noskip = _bench_grid(work, 0.02, 2 if quick else 4, 1, 1, skip_empty=False)
        export = _bench_export(work, 4 if quick else 20)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return {
        "coarse_0.2m": coarse,
        "fine_0.02m": fine,
        "fine_0.02m_no_skip": fine_noskip,
        "export": export,
    }
