"""map: the human-free static semantic map and the free / unknown occupancy map of a sequence, by tile.

Three passes, each fanned out (tasks/occupancy/tiles.py explains the split; the maps equal the
sequential :class:`tasks.occupancy.mapping.SequenceMapper`'s voxel for voxel):

1. ``map_window`` per window of frames: labels and person removal per sweep; static votes by tile
   and the kept points' masks go to a scratch folder (``work/``);
2. ``map_region`` per region: the occupancy map of the region from every sweep that reaches it,
   written as :class:`storage.products.OccupancyMapProduct` tiles;
3. ``map_static`` per region: votes summed over windows, ground check with a halo of tiles, max
   voting, written as :class:`storage.products.StaticMapProduct` tiles.

Then the index (:class:`storage.products.MapTiles`); the scratch folder is deleted. Every task
holds a bounded part of the sequence: memory does not grow with its length.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flows.pipeline.inputs import MapInputs, SequenceRef
from flows.pipeline.parallel import fan_out
from flows.stages.common import StageContext, detected_positions
from storage.products import (
    TILES,
    Detections,
    KeepMasks,
    MapTiles,
    OccupancyMapProduct,
    StaticMapProduct,
    WindowVotesProduct,
    remove_scratch,
)
from tasks.conventions import UNLABELED
from tasks.occupancy.mapping import (
    SweepLabeller,
    WindowVotes,
    finalize_tiles,
    occupancy_tiles,
    region_occupancy,
    sum_tile_votes,
    world_points,
)
from tasks.occupancy.tiles import (
    BLOCK_VOXELS,
    ground_halo_tiles,
    plan_map,
    static_groups,
    voxels_per_tile,
)


def _labeller(inp: MapInputs, seq, threads: int) -> SweepLabeller:
    cam = seq.info.calibration.cameras[inp.source.camera]
    lut = np.full(256, UNLABELED, np.uint8)
    lut[[k for k, _ in inp.class_lut]] = [v for _, v in inp.class_lut]
    return SweepLabeller(
        inp.settings,
        lut,
        cam.K,
        cam.T_cam_from_lidar,
        cam.width,
        cam.height,
        inp.assoc_min_iou,
        threads,
        inp.ground_class_ids,
        point_classes=inp.point_classes,
        geometry=inp.geometry,
    )


def map_window(
    ref: SequenceRef,
    inp: MapInputs,
    detect_dir: Path,
    work: Path,
    window: int,
    positions: list[int],
    threads: int,
) -> dict:
    """One window of frames (positions in the sequence): static votes by tile and keep masks into
    ``work``."""
    seq = inp.source.open(ref)
    labeller, votes = (
        _labeller(inp, seq, threads),
        WindowVotes(inp.settings),
    )
    frames, masks = [], []
    for i in positions:
        frame = seq.frame(i)
        d = Detections.read(detect_dir, Detections.file_name(frame.index))
        sweep = labeller(
            frame.points_lidar,
            d.semantic,
            d.mask_labels,
            d.boxes_xyxy,
            d.lidar_centers,
            d.lidar_sizes,
            d.lidar_yaws,
            d.lidar_scores,
            frame.intensity if frame.intensity_present else None,
            frame.T_world_from_lidar,
        )
        votes.add(
            world_points(frame.T_world_from_lidar, frame.points_lidar),
            sweep,
            frame.T_world_from_lidar[:3, 3],
        )
        frames.append(frame.index)
        masks.append(sweep.keep)
    KeepMasks.of(frames, masks).write(work, KeepMasks.file_name(window))
    tiles = []
    for tile, arrays in votes.by_tile():
        WindowVotesProduct(*arrays).write(work, WindowVotesProduct.file_name(window, tile))
        tiles.append(tile)
    return {"window": window, "tiles": tiles, "kept": votes.kept, "removed": votes.removed}


def _kept_scans(seq, work: Path, frames: np.ndarray, positions: np.ndarray, window_frames: int):
    """(kept points (N, 3) float32 world frame, LiDAR origin (3,)) of each frame, in order; frames
    count the mapped frames (window = frame // window_frames), positions[frame] is its position in
    the sequence."""
    masks: tuple[int, KeepMasks] | None = None
    for i in frames:
        if masks is None or masks[0] != i // window_frames:
            masks = (
                i // window_frames,
                KeepMasks.read(work, KeepMasks.file_name(i // window_frames)),
            )
        frame = seq.frame(int(positions[i]))
        keep = masks[1].mask(int(i) % window_frames)
        yield (
            world_points(frame.T_world_from_lidar, frame.points_lidar)[keep],
            frame.T_world_from_lidar[:3, 3],
        )


def map_region(
    ref: SequenceRef,
    inp: MapInputs,
    work: Path,
    out_dir: Path,
    region_keys: tuple[int, int, int, int],
    frames: np.ndarray,
    positions: np.ndarray,
    threads: int,
) -> list[tuple[tuple[int, int], int]]:
    """The occupancy map of one region (its voxel keys), written by tile: [(tile, voxels)]."""
    s, fs = inp.settings, inp.freespace
    scans = _kept_scans(inp.source.open(ref), work, frames, positions, s.window_frames)
    m = region_occupancy(fs, region_keys, scans, threads)
    written = []
    for tile, keys, logodds in occupancy_tiles(m, s.tile_m):
        OccupancyMapProduct(np.array(fs.voxel_size_m, np.float64), keys, logodds).write(
            out_dir / TILES, OccupancyMapProduct.file_name(tile)
        )
        written.append((tile, len(keys)))
    return written


def map_static(
    inp: MapInputs,
    work: Path,
    out_dir: Path,
    tiles: list[tuple[int, int]],
    windows: dict[tuple[int, int], list[int]],
) -> list[dict]:
    """The final static map of some tiles (windows: tile -> the windows with votes there, for the
    tiles and their halo), written by tile."""

    def load(tile):
        return sum_tile_votes(
            [
                tuple(
                    WindowVotesProduct.read(work, WindowVotesProduct.file_name(w, tile))
                    .arrays()
                    .values()
                )
                for w in windows.get(tile, [])
            ]
        )

    out = []
    for tile, smap, camera in finalize_tiles(tiles, load, inp.settings, inp.ground_class_ids):
        if len(smap.keys):
            StaticMapProduct(
                np.array(smap.voxel_size_m, np.float64),
                smap.keys,
                smap.labels,
                smap.counts,
                smap.surface,
            ).write(out_dir / TILES, StaticMapProduct.file_name(tile))
        out.append(
            {
                "tile": tile,
                "voxels": len(smap.keys),
                "camera": camera,
                "rejected": smap.ground_rejected,
            }
        )
    return out


def run_map(ctx: StageContext[MapInputs]) -> dict:
    inp, seq, work, threads = ctx.inputs, ctx.open(), ctx.out_dir / "work", ctx.runtime.threads
    s, fs, at = inp.settings, inp.freespace, np.asarray(detected_positions(ctx, seq), np.int64)
    plan = plan_map(seq.info.poses[at, :3, 3], s, fs)
    windows = fan_out(
        map_window,
        [
            (ctx.ref, inp, ctx.upstream["detect"], work, w, at[a:b].tolist(), threads)
            for w, (a, b) in enumerate(plan.windows)
        ],
        threads=threads,
    )
    n = voxels_per_tile(s.tile_m, fs.voxel_size_m, BLOCK_VOXELS)
    occupancy = [
        t
        for part in fan_out(
            map_region,
            [
                (ctx.ref, inp, work, ctx.out_dir, plan.region_keys(r, n), frames, at, threads)
                for r, frames in plan.regions
            ],
            threads=threads,
        )
        for t in part
    ]
    groups = static_groups(plan, [(w["window"], w["tiles"]) for w in windows], ground_halo_tiles(s))
    static = [
        t
        for part in fan_out(
            map_static,
            [(inp, work, ctx.out_dir, tiles, where) for tiles, where in groups],
            threads=threads,
        )
        for t in part
    ]
    remove_scratch(work)
    MapTiles.of(
        s.tile_m,
        s.voxel_size_m,
        fs.voxel_size_m,
        [(t["tile"], t["voxels"]) for t in static],
        occupancy,
    ).write(ctx.out_dir)
    return {
        "implemented": True,
        "static_voxels": sum(t["voxels"] for t in static),
        "static_tiles": sum(t["voxels"] > 0 for t in static),
        "camera_labelled_voxels": sum(t["camera"] for t in static),
        "occupancy_voxels": sum(n for _, n in occupancy),
        "occupancy_tiles": len(occupancy),
        "points_kept": sum(w["kept"] for w in windows),
        "points_removed": sum(w["removed"] for w in windows),
        "ground_votes_rejected": sum(t["rejected"] for t in static),
        "windows": len(plan.windows),
        "regions": len(plan.regions),
    }
