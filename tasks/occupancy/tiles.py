"""Square spatial tiles of the sequence maps, and how the map stage splits its work over them.

A tile is a column of space ``[tx, tx + 1) x [ty, ty + 1) * tile_m`` (world x / y, any z). A map
of voxel size ``v`` has ``n = tile_m / v`` voxels per tile edge (a whole number; a multiple of 8
for the occupancy map, whose 8 x 8 x 8 blocks never straddle a tile), and voxel key
``(kx, ky, kz)`` lies in tile ``(kx // n, ky // n)`` (floor division): tiles are exact in integer
keys, so two maps of different voxel sizes cut space at the same lines.

The map stage (tasks/occupancy/mapping.py) works in three parallel passes whose union equals the
sequential map exactly:

1. frame *windows* (``window_frames`` consecutive sweeps): per sweep the labels and the points
   kept, and static-map votes per tile (votes add, so windows merge by a sum);
2. *regions* (``region_tiles`` x ``region_tiles`` tiles): the occupancy map of a region from every
   sweep that can reach it, in frame order (each voxel sees the same updates in the same order
   as in one sequential map: :meth:`tasks.occupancy.freespace.OccupancyMap.insert_scan`, region);
3. static tiles: votes summed over windows, then the ground check (it pools ground cells within
   ``(ground_neighbourhood_cells + 1) * ground_cell_m``: a tile reads that halo of neighbouring
   tiles, :func:`ground_halo_tiles`) and max voting.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tasks.occupancy.settings import FreeSpaceParams, MapParams

#: voxels per occupancy-map block edge (tasks/occupancy/freespace.py): occupancy tiles hold whole blocks
BLOCK_VOXELS = 8
#: margin (voxels) around a ray's origin and end voxels holding every voxel it crosses (as in
#: tasks/occupancy/freespace.py)
RAY_MARGIN_VOXELS = 8


class TileError(ValueError):
    """A tile size that does not cut a map's voxels into whole tiles."""


def voxels_per_tile(
    tile_m: float, voxel_size_m: float, multiple: int = 1, what: str = "map"
) -> int:
    """Tile edge in voxels of size voxel_size_m; TileError unless it is a whole multiple of ``multiple``."""
    n = tile_m / voxel_size_m
    whole = int(round(n))
    if whole < multiple or abs(n - whole) > 1e-6 * max(1.0, n) or whole % multiple:
        raise TileError(
            f"map.tile_m = {tile_m} m is not a whole number of {multiple} x {voxel_size_m} m "
            f"voxels of the {what} (got {n:.6g} voxels; e.g. {multiple * voxel_size_m * 16:g} m)"
        )
    return whole


def check_tiling(tile_m: float, map_voxel_m: float, occupancy_voxel_m: float) -> None:
    """Raise TileError unless tile_m cuts both maps into whole tiles (occupancy: whole blocks)."""
    voxels_per_tile(tile_m, map_voxel_m, 1, "static map (map.voxel_size_m)")
    voxels_per_tile(
        tile_m,
        occupancy_voxel_m,
        BLOCK_VOXELS,
        "occupancy map (map.freespace.voxel_size_m; 8-voxel blocks)",
    )


def tiles_of_keys(keys: np.ndarray, n: int) -> np.ndarray:
    """(N, 3) int voxel keys -> (N, 2) int64 tiles, n voxels per tile edge."""
    return np.floor_divide(np.asarray(keys, dtype=np.int64).reshape(-1, 3)[:, :2], n)


def tiles_in_box(tile_m: float, lo_xy, hi_xy, pad_m: float = 0.0) -> list[tuple[int, int]]:
    """Tiles (sorted) meeting the world box [lo_xy, hi_xy] (m) grown by pad_m."""
    t0 = [math.floor((lo_xy[a] - pad_m) / tile_m) for a in range(2)]
    t1 = [math.floor((hi_xy[a] + pad_m) / tile_m) for a in range(2)]
    return [(tx, ty) for tx in range(t0[0], t1[0] + 1) for ty in range(t0[1], t1[1] + 1)]


def ground_halo_tiles(params: MapParams) -> int:
    """Tiles of halo a tile's ground check and fragment check read on each side: the ground check
    pools the ground votes of cells up to ``ground_neighbourhood_cells`` away, i.e. voxel centres
    less than ``(ground_neighbourhood_cells + 1) * ground_cell_m`` away (one voxel more for the
    centres' rounding); a fragment of fewer than ``min_fragment_voxels`` voxels reaches less than
    that many voxels from any of its voxels, so a halo that wide sees whether it is one."""
    p = params
    reach_m = max(
        (p.ground_neighbourhood_cells + 1) * p.ground_cell_m + p.voxel_size_m,
        p.min_fragment_voxels * p.voxel_size_m,
    )
    return max(1, math.ceil(reach_m / p.tile_m))


@dataclass(frozen=True)
class MapPlan:
    """How the map stage splits a sequence. windows: (start, stop) frame positions; regions:
    (region (rx, ry), frame positions ascending of the sweeps that can reach it); region (rx, ry)
    holds tiles ``offset + (rx, ry) * region_tiles`` up to ``region_tiles`` more on each axis (the
    first robot position sits in the middle of a region: sequences start at the world origin, which
    would otherwise be a corner of four)."""

    windows: list[tuple[int, int]]
    regions: list[tuple[tuple[int, int], np.ndarray]]
    offset: tuple[int, int]
    region_tiles: int

    def region_of_tile(self, tile) -> tuple[int, int]:
        return (
            (int(tile[0]) - self.offset[0]) // self.region_tiles,
            (int(tile[1]) - self.offset[1]) // self.region_tiles,
        )

    def region_keys(self, region, n: int) -> tuple[int, int, int, int]:
        """Voxel keys (kx0, kx1, ky0, ky1) of a region, n voxels per tile edge."""
        x0 = (self.offset[0] + int(region[0]) * self.region_tiles) * n
        y0 = (self.offset[1] + int(region[1]) * self.region_tiles) * n
        return x0, x0 + self.region_tiles * n, y0, y0 + self.region_tiles * n


def static_groups(
    plan: MapPlan, windows: list[tuple[int, list[tuple[int, int]]]], halo: int
) -> list[tuple[list[tuple[int, int]], dict[tuple[int, int], list[int]]]]:
    """The static tiles' final pass, one group per region: (its tiles with votes, ascending; for
    those tiles and their halo, the windows that voted there). windows: (window, its tiles)."""
    where: dict[tuple[int, int], list[int]] = {}
    for w, tiles in windows:
        for tile in tiles:
            where.setdefault((int(tile[0]), int(tile[1])), []).append(int(w))
    groups: dict[tuple[int, int], list[tuple[int, int]]] = {}
    for tile in sorted(where):
        groups.setdefault(plan.region_of_tile(tile), []).append(tile)
    out = []
    for _, tiles in sorted(groups.items()):
        near = {
            (tx + dx, ty + dy)
            for tx, ty in tiles
            for dx in range(-halo, halo + 1)
            for dy in range(-halo, halo + 1)
        }
        out.append((tiles, {t: where[t] for t in sorted(near) if t in where}))
    return out


def plan_map(origins_world: np.ndarray, params: MapParams, freespace: FreeSpaceParams) -> MapPlan:
    """Windows of ``params.window_frames`` frames, and per region of region_tiles x region_tiles
    tiles of ``params.tile_m`` the frames whose rays can reach it.

    origins_world: (F, 3) float64 LiDAR origins, world frame, m. The occupancy map's
    ``freespace.max_range_m`` is how far a ray reaches: a frame reaches a region when the voxel box
    of its origin +- that (grown by RAY_MARGIN_VOXELS, in occupancy voxel keys) meets the
    region's keys.
    """
    window_frames, tile_m, region_tiles = params.window_frames, params.tile_m, params.region_tiles
    occupancy_voxel_m, reach_m = freespace.voxel_size_m, freespace.max_range_m
    if not reach_m > 0 or not math.isfinite(reach_m):
        raise TileError(
            f"the occupancy map needs a finite max_range_m > 0 to be split by region, got {reach_m}"
        )
    o = np.asarray(origins_world, dtype=np.float64).reshape(-1, 3)
    n = len(o)
    windows = [(a, min(a + window_frames, n)) for a in range(0, n, window_frames)]
    offset = (
        (0, 0)
        if not n
        else tuple(int(math.floor(o[0, a] / tile_m)) - region_tiles // 2 for a in range(2))
    )
    per_tile = voxels_per_tile(tile_m, occupancy_voxel_m, BLOCK_VOXELS)
    regions = []
    for sign, margin in ((-1, -RAY_MARGIN_VOXELS), (1, RAY_MARGIN_VOXELS)):
        keys = np.floor((o[:, :2] + sign * reach_m) / occupancy_voxel_m).astype(np.int64) + margin
        regions.append(
            np.floor_divide(np.floor_divide(keys, per_tile) - np.asarray(offset), region_tiles)
        )
    lo, hi = regions
    members: dict[tuple[int, int], list[int]] = {}
    for i in range(n):
        for rx in range(lo[i, 0], hi[i, 0] + 1):
            for ry in range(lo[i, 1], hi[i, 1] + 1):
                members.setdefault((int(rx), int(ry)), []).append(i)
    return MapPlan(
        windows,
        [(r, np.asarray(members[r], dtype=np.int64)) for r in sorted(members)],
        offset,
        region_tiles,
    )


def tiles_near_grids(
    tile_m: float, reach_m: float, T_world_from_base: np.ndarray, pad_m: float
) -> list[tuple[int, int]]:
    """Tiles (sorted) a robot-local grid can touch at any of the poses: those meeting the square
    of half side reach_m + pad_m around each robot position. T_world_from_base: (F, 4, 4) float64.
    reach_m: :func:`tasks.occupancy.resample.grid_reach_m` (every cell centre and the fine-map
    crop lie within it); pad_m: the largest map voxel (a voxel holding such a point)."""
    out: set[tuple[int, int]] = set()
    for T in np.asarray(T_world_from_base, dtype=np.float64).reshape(-1, 4, 4):
        xy = T[:2, 3]
        out.update(tiles_in_box(tile_m, xy - reach_m, xy + reach_m, pad_m))
    return sorted(out)
