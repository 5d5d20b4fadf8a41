"""The map stage's work on a sequence, sweep by sweep (paper, "Static Map Generation").

Per sweep: image semantics lifted to the points; points in pedestrian instance masks, in LiDAR
pedestrian boxes, or labelled pedestrian removed; the rest, in the world frame, vote in the static
map and are inserted into the occupancy map (OctoMap semantics) from the sensor origin. Points the
camera sees vote in one count table, points outside the image (labelled by the fallback) in
another; the camera's table decides every voxel it has votes for and the fallback only fills the
rest (with a 360 deg LiDAR and one camera, out-of-view points are ~80 % of a sweep and would
otherwise outvote the camera).

Two ways to run it, with the same result voxel for voxel:

- :class:`SequenceMapper`: one pass, whole-sequence maps in memory (memory grows with the mapped
  area: the reference, and small sequences);
- by tiles (tasks/occupancy/tiles.py): :class:`WindowVotes` per window of sweeps (votes by tile),
  :func:`region_occupancy` per region (the occupancy map of one region from every sweep that
  reaches it, in frame order), :func:`finalize_tiles` (votes summed, ground check with a halo of
  tiles, max voting). Each piece holds a bounded part of space, so memory does not grow with the
  sequence, and the pieces run in parallel.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from tasks.conventions import PEDESTRIAN
from tasks.geometry import transform_points
from tasks.occupancy.freespace import OccupancyMap
from tasks.occupancy.settings import FreeSpaceParams, MapParams
from tasks.occupancy.static_map import (
    StaticMap,
    StaticSemanticMap,
    lift_image_semantics,
    merge_static_maps,
    pack_keys,
    pedestrian_boxes_for_masking,
    pedestrian_point_mask,
    project_points,
    sum_votes,
    unpack_keys,
    vote,
)
from tasks.occupancy.tiles import BLOCK_VOXELS, ground_halo_tiles, tiles_of_keys, voxels_per_tile


@dataclass(frozen=True)
class SweepLabels:
    """One sweep's points: labels (N,) uint8 class ids (lifted, fallback outside the image),
    keep (N,) bool (not a person: what votes and is inserted), in_image (N,) bool."""

    labels: np.ndarray
    keep: np.ndarray
    in_image: np.ndarray


class SweepLabeller:
    """Labels and person removal of single sweeps: class_lut (256,) uint8 Cityscapes train id ->
    class id (UNLABELED: none); K (3, 3), T_cam_from_lidar (4, 4), width / height: the camera;
    assoc_min_iou: see :func:`pedestrian_boxes_for_masking`; threads: nearest-neighbour search."""

    def __init__(
        self,
        params: MapParams,
        class_lut: np.ndarray,
        K: np.ndarray,
        T_cam_from_lidar: np.ndarray,
        width: int,
        height: int,
        assoc_min_iou: float,
        threads: int | None = None,
    ):
        self.params, self.lut, self.K, self.T_cam = params, class_lut, K, T_cam_from_lidar
        self.size, self.min_iou, self.threads = (width, height), assoc_min_iou, threads

    def __call__(
        self,
        points_lidar: np.ndarray,
        semantic: np.ndarray,
        mask_labels: np.ndarray,
        boxes_xyxy: np.ndarray,
        lidar_centers: np.ndarray,
        lidar_sizes: np.ndarray,
        lidar_yaws: np.ndarray,
    ) -> SweepLabels:
        """points_lidar (N, 3) float32 LiDAR frame; semantic (H, W) Cityscapes train ids,
        mask_labels (H, W) instance labels (> 0: a person), image boxes (D, 4), LiDAR pedestrian
        boxes (M, 3) / (M,)."""
        p, (width, height) = self.params, self.size
        projection = project_points(
            points_lidar, self.K, self.T_cam, width, height
        )  # once per sweep
        labels = lift_image_semantics(
            points_lidar,
            semantic,
            self.K,
            self.T_cam,
            self.lut,
            p,
            projection=projection,
            threads=self.threads,
        )
        boxes = pedestrian_boxes_for_masking(
            boxes_xyxy,
            lidar_centers,
            lidar_sizes,
            lidar_yaws,
            self.K,
            self.T_cam,
            width,
            height,
            self.min_iou,
        )
        people = pedestrian_point_mask(
            points_lidar,
            instance_image=mask_labels,
            boxes_lidar=boxes,
            box_margin_m=p.pedestrian_box_margin_m,
            projection=projection,
        )
        return SweepLabels(labels, ~people & (labels != PEDESTRIAN), projection[1])


class SequenceMapper:
    """The static semantic map and the occupancy map of one sequence, fed sweep by sweep, whole
    maps in memory (the tiled pipeline's reference). Arguments as :class:`SweepLabeller`. State
    lives on the instance; ``add_sweep`` advances it."""

    def __init__(
        self,
        params: MapParams,
        freespace: FreeSpaceParams,
        class_lut: np.ndarray,
        K: np.ndarray,
        T_cam_from_lidar: np.ndarray,
        width: int,
        height: int,
        assoc_min_iou: float,
        threads: int | None = None,
    ):
        self.params, self.freespace = params, freespace
        self.labeller = SweepLabeller(
            params, class_lut, K, T_cam_from_lidar, width, height, assoc_min_iou, threads
        )
        self.seen = StaticSemanticMap(params.voxel_size_m)
        self.unseen = StaticSemanticMap(params.voxel_size_m)
        self.occupancy = OccupancyMap(freespace, threads=threads)
        self.kept = self.removed = 0

    def add_sweep(
        self,
        points_lidar: np.ndarray,
        T_world_from_lidar: np.ndarray,
        semantic: np.ndarray,
        mask_labels: np.ndarray,
        boxes_xyxy: np.ndarray,
        lidar_centers: np.ndarray,
        lidar_sizes: np.ndarray,
        lidar_yaws: np.ndarray,
    ) -> None:
        """One sweep (N, 3) float32 LiDAR frame with its pose (4, 4) and its detections (as
        :meth:`SweepLabeller.__call__`)."""
        s = self.labeller(
            points_lidar, semantic, mask_labels, boxes_xyxy, lidar_centers, lidar_sizes, lidar_yaws
        )
        world = world_points(T_world_from_lidar, points_lidar)
        self.seen.add_sweep(world, s.labels, keep=s.keep & s.in_image)
        self.unseen.add_sweep(world, s.labels, keep=s.keep & ~s.in_image)
        self.occupancy.insert_scan(
            world[s.keep],
            T_world_from_lidar[:3, 3],
            max_range_m=self.freespace.max_range_m,
            discretize=self.freespace.discretize,
        )
        self.removed += int((~s.keep).sum())
        self.kept += int(s.keep.sum())

    def finish(self, ground_class_ids: tuple[int, ...]) -> tuple[StaticMap, StaticMap]:
        """(the final static map, the camera-labelled part of it) after the ground check and max
        voting; the occupancy map is ``self.occupancy``."""
        p, ground = self.params, tuple(ground_class_ids)
        camera = self.seen.finalize(p, ground)
        return merge_static_maps(camera, self.unseen.finalize(p, ground)), camera


def world_points(T_world_from_lidar: np.ndarray, points_lidar: np.ndarray) -> np.ndarray:
    """(N, 3) float32 world frame: the points that vote and are inserted (one rounding, shared by
    every way of running the map)."""
    return transform_points(T_world_from_lidar, points_lidar).astype(np.float32)


# ---- by tiles ------------------------------------------------------------------------------------


#: a tile's raw votes: (camera-seen packed keys (A,), counts (A, 9), unseen packed keys (B,), counts (B, 9))
TileVotes = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


class WindowVotes:
    """Static-map votes of a window of consecutive sweeps, split by tile (seen by the camera and
    not, as :class:`SequenceMapper`) of ``params.voxel_size_m`` by tiles of ``params.tile_m``.
    State lives on the instance."""

    def __init__(self, params: MapParams):
        self.n = voxels_per_tile(params.tile_m, params.voxel_size_m)
        self.seen = StaticSemanticMap(params.voxel_size_m)
        self.unseen = StaticSemanticMap(params.voxel_size_m)
        self.kept = self.removed = 0

    def add(self, world: np.ndarray, sweep: SweepLabels) -> None:
        """world: (N, 3) float32 the sweep's points in the world frame (:func:`world_points`)."""
        self.seen.add_sweep(world, sweep.labels, keep=sweep.keep & sweep.in_image)
        self.unseen.add_sweep(world, sweep.labels, keep=sweep.keep & ~sweep.in_image)
        self.removed += int((~sweep.keep).sum())
        self.kept += int(sweep.keep.sum())

    def by_tile(self) -> Iterator[tuple[tuple[int, int], TileVotes]]:
        """(tile, its votes) for every tile with votes, tiles ascending; keys ascending in each."""
        parts = [_split_by_tile(*m.packed_counts(), self.n) for m in (self.seen, self.unseen)]
        empty = (np.empty(0, np.int64), np.empty((0, 9), np.uint16))
        for tile in sorted(set(parts[0]) | set(parts[1])):
            yield tile, (*parts[0].get(tile, empty), *parts[1].get(tile, empty))


def _split_by_tile(packed: np.ndarray, counts: np.ndarray, n: int) -> dict[tuple[int, int], tuple]:
    """Rows of a sorted vote table grouped by tile (each group keeps the ascending key order)."""
    if not len(packed):
        return {}
    tiles = tiles_of_keys(unpack_keys(packed), n)
    order = np.lexsort((packed, tiles[:, 1], tiles[:, 0]))
    t = tiles[order]
    cut = np.flatnonzero(np.any(t[1:] != t[:-1], axis=1)) + 1
    return {
        (int(t[a, 0]), int(t[a, 1])): (packed[order[a:b]], counts[order[a:b]])
        for a, b in zip(np.r_[0, cut], np.r_[cut, len(t)])
    }


def finalize_tiles(
    tiles: Iterable[tuple[int, int]],
    load: Callable[[tuple[int, int]], TileVotes | None],
    params: MapParams,
    ground_class_ids: tuple[int, ...],
) -> Iterator[tuple[tuple[int, int], StaticMap, int]]:
    """The final static map of each tile: (tile, map, camera-labelled voxels).

    load(tile): the tile's votes summed over the whole sequence (:func:`sum_tile_votes`), None
    where it has none. The ground check of a tile reads the votes of its halo
    (:func:`tasks.occupancy.tiles.ground_halo_tiles`): the result equals the whole-sequence
    :meth:`SequenceMapper.finish` restricted to the tile. Tiles are loaded once per call while
    they are within the halo of the tiles still to come (give tiles in ascending order).
    """
    p, ground = params, tuple(ground_class_ids)
    n = voxels_per_tile(p.tile_m, p.voxel_size_m)
    h = ground_halo_tiles(p)
    cache: dict[tuple[int, int], TileVotes | None] = {}
    for tile in sorted(tiles):
        near = [(tile[0] + dx, tile[1] + dy) for dx in range(-h, h + 1) for dy in range(-h, h + 1)]
        for t in [t for t in cache if t[0] < tile[0] - h]:
            del cache[t]
        votes = [cache[t] if t in cache else cache.setdefault(t, load(t)) for t in near]
        maps = []
        for side in (0, 2):  # camera-seen, then unseen
            keys, counts = sum_votes([(v[side], v[side + 1]) for v in votes if v is not None])
            inside = np.all(tiles_of_keys(unpack_keys(keys), n) == tile, axis=1)
            maps.append(vote(keys, counts, p, ground, select=inside))
        yield tile, merge_static_maps(maps[0], maps[1]), len(maps[0].keys)


def sum_tile_votes(parts: list[TileVotes]) -> TileVotes | None:
    """One tile's votes of several windows added (:func:`tasks.occupancy.static_map.sum_votes`)."""
    if not parts:
        return None
    seen = sum_votes([(p[0], p[1]) for p in parts])
    unseen = sum_votes([(p[2], p[3]) for p in parts])
    return (*seen, *unseen)


def region_occupancy(
    freespace: FreeSpaceParams,
    region_keys: tuple[int, int, int, int],
    scans: Iterable[tuple[np.ndarray, np.ndarray]],
    threads: int | None = None,
) -> OccupancyMap:
    """The occupancy map of one region (voxel keys (kx0, kx1, ky0, ky1), whole blocks:
    :meth:`tasks.occupancy.tiles.MapPlan.region_keys`) from scans (points (N, 3) float32 world
    frame, origin (3,)) given in frame order: every scan that can reach the region
    (:func:`tasks.occupancy.tiles.plan_map`). Its voxels equal those of the whole-sequence map."""
    m = OccupancyMap(freespace, threads=threads)
    for points, origin in scans:
        m.insert_scan(
            points,
            origin,
            max_range_m=freespace.max_range_m,
            discretize=freespace.discretize,
            region=region_keys,
        )
    return m


def occupancy_tiles(
    m: OccupancyMap, tile_m: float
) -> Iterator[tuple[tuple[int, int], np.ndarray, np.ndarray]]:
    """(tile, keys (K, 3) int64, log-odds (K,) float32) of a map's known voxels by tile, tiles
    ascending, keys ascending (x, then y, then z) in each."""
    keys, vals = m.to_arrays()
    n = voxels_per_tile(tile_m, m.voxel_size_m, BLOCK_VOXELS)
    packed = pack_keys(keys)
    for tile, (pk, v) in _split_by_tile(packed, vals, n).items():
        yield tile, unpack_keys(pk), v


def join_static_tiles(
    voxel_size_m: float, parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]]
) -> StaticMap:
    """The static map of several tiles: parts of (keys (K, 3) int64, labels (K,) uint8, counts
    (K, 9) uint16); keys ascending over the whole (packed order), as the whole-sequence map."""
    if not parts:
        return StaticMap(
            voxel_size_m,
            np.empty((0, 3), np.int64),
            np.empty(0, np.uint8),
            np.empty((0, 9), np.uint16),
            0,
        )
    keys = np.concatenate([p[0] for p in parts])
    order = np.argsort(pack_keys(keys), kind="stable")
    return StaticMap(
        voxel_size_m,
        keys[order],
        np.concatenate([p[1] for p in parts])[order],
        np.concatenate([p[2] for p in parts])[order],
        0,
    )
