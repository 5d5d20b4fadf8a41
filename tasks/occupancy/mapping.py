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
from dataclasses import dataclass, replace

import numpy as np

from tasks.conventions import PEDESTRIAN, ROAD, TERRAIN, UNLABELED
from tasks.geometry import transform_points
from tasks.occupancy.freespace import OccupancyMap
from tasks.occupancy.geometric_classes import (
    GeometricClassSettings,
    geometric_classes,
    gravity_aligned,
)
from tasks.occupancy.settings import FreeSpaceParams, MapParams
from tasks.occupancy.static_map import (
    NUM_OCCUPIED_CLASSES,
    StaticMap,
    StaticSemanticMap,
    lift_image_semantics,
    merge_static_maps,
    pack_keys,
    pedestrian_boxes_for_masking,
    pedestrian_point_mask,
    project_points,
    small_fragments,
    sum_votes,
    unpack_keys,
    vote,
)
from tasks.occupancy.surface import NUM_MOMENTS, group_sum, surface_fit
from tasks.occupancy.tiles import BLOCK_VOXELS, ground_halo_tiles, tiles_of_keys, voxels_per_tile

#: the label sources of ``map.point_classes`` (:class:`SweepLabeller`)
POINT_CLASSES = ("camera", "geometry", "camera+geometry")


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
    assoc_min_iou: see :func:`pedestrian_boxes_for_masking`; threads: nearest-neighbour search;
    ground_class_ids: the classes of the ground people stand on (``map.ground_classes``).

    point_classes (``map.point_classes``): where the labels come from. "camera": the image
    semantics lifted to the points, ``params.outside_image_fallback`` beyond the image;
    "geometry": :func:`tasks.occupancy.geometric_classes.geometric_classes` with ``geometry``
    (no segmenter needed; the image still removes people); "camera+geometry": the camera's label
    where a point is in the image and its pixel has a class, the geometry's everywhere else (it
    replaces the outside-image fallback: a point the geometry cannot tell stays UNLABELED)."""

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
        ground_class_ids: tuple[int, ...] = (ROAD, TERRAIN),
        *,
        point_classes: str = "camera",
        geometry: GeometricClassSettings | None = None,
    ):
        if point_classes not in POINT_CLASSES:
            raise ValueError(f"point_classes must be one of {POINT_CLASSES}, got {point_classes!r}")
        self.params, self.lut, self.K, self.T_cam = params, class_lut, K, T_cam_from_lidar
        self.size, self.min_iou, self.threads = (width, height), assoc_min_iou, threads
        self.ground = tuple(ground_class_ids)
        self.point_classes = point_classes
        self.geometry = geometry if geometry is not None else GeometricClassSettings()

    def __call__(
        self,
        points_lidar: np.ndarray,
        semantic: np.ndarray,
        mask_labels: np.ndarray,
        boxes_xyxy: np.ndarray,
        lidar_centers: np.ndarray,
        lidar_sizes: np.ndarray,
        lidar_yaws: np.ndarray,
        lidar_scores: np.ndarray | None = None,
        intensity: np.ndarray | None = None,
        T_world_from_lidar: np.ndarray | None = None,
    ) -> SweepLabels:
        """points_lidar (N, 3) float32 LiDAR frame; semantic (H, W) Cityscapes train ids,
        mask_labels (H, W) instance labels (> 0: a person), image boxes (D, 4), LiDAR pedestrian
        boxes (M, 3) / (M,) and their scores (M,) (None: every box out of view counts). For
        point_classes with geometry: intensity (N,) (None: not measured), T_world_from_lidar
        (4, 4) whose rotation turns the points z up (None: the LiDAR is level)."""
        p, (width, height) = self.params, self.size
        projection = project_points(
            points_lidar, self.K, self.T_cam, width, height
        )  # once per sweep
        if self.point_classes == "geometry":
            labels = self._geometry(points_lidar, intensity, T_world_from_lidar)
        else:
            labels = lift_image_semantics(
                points_lidar,
                semantic,
                self.K,
                self.T_cam,
                self.lut,
                p
                if self.point_classes == "camera"
                else replace(p, outside_image_fallback="unknown"),
                projection=projection,
                threads=self.threads,
            )
            if self.point_classes == "camera+geometry":
                fill = labels == UNLABELED
                if fill.any():
                    labels[fill] = self._geometry(points_lidar, intensity, T_world_from_lidar)[fill]
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
            lidar_scores,
            p.lidar_person_min_score,
        )
        people = pedestrian_point_mask(
            points_lidar,
            instance_image=mask_labels,
            boxes_lidar=boxes,
            box_margin_m=p.pedestrian_box_margin_m,
            projection=projection,
        )
        people |= labels == PEDESTRIAN
        if p.person_edge_m > 0 and people.any():
            people = person_edges(points_lidar, people, p.person_edge_m, self.threads)
        if p.person_ground_keep_m > 0 and people.any():
            labels, ground_back = _ground_under_people(
                points_lidar,
                labels,
                people,
                self.ground,
                p.person_ground_keep_m,
                p.ground_cell_m,
                self.threads,
            )
            # only the ground under a person goes back to the map: every other point of the
            # person stays removed whatever its label (a point out of the image takes the label of
            # the nearest in-view point, a mask's edge the background's)
            people &= ~ground_back
        return SweepLabels(labels, ~people, projection[1])

    def _geometry(self, points_lidar, intensity, T_world_from_lidar) -> np.ndarray:
        up = (
            np.asarray(points_lidar, np.float32)
            if T_world_from_lidar is None
            else gravity_aligned(T_world_from_lidar, points_lidar)
        )
        return geometric_classes(up, intensity, self.geometry)


def person_edges(
    points_lidar: np.ndarray, people: np.ndarray, edge_m: float, threads: int | None = None
) -> np.ndarray:
    """``people`` (N,) bool grown by one step: every point within edge_m (m) of a person's point
    is a person's point too. points_lidar: (N, 3) float, LiDAR frame, m.

    A body's outline as the LiDAR sees it projects partly just outside the person's image mask
    (pixel edges, the LiDAR-to-camera parallax); where no confirmed LiDAR box holds the person,
    those returns took the label of what lies behind the outline in the image and stayed in the
    static map (issue 30: a trail of pole and wall voxels along a walking person's path). Points
    of the person lie within the LiDAR's point spacing of the masked ones. One step, not a flood:
    a static surface touching a person loses only its returns within edge_m of the person in
    that sweep (the ground under the feet goes back with ``person_ground_keep_m``)."""
    from tasks.occupancy.nearest import nearest_indices

    p = np.asarray(points_lidar, dtype=np.float64).reshape(-1, 3)
    out = np.asarray(people, dtype=bool).copy()
    src = p[out]
    if not len(src) or edge_m <= 0:
        return out
    # only points in a cell next to a person's cell can be within edge_m of one
    cell = np.floor(p / edge_m).astype(np.int64)
    offsets = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), -1).reshape(-1, 3)
    grown = np.unique(pack_keys((np.unique(cell[out], axis=0)[:, None] + offsets).reshape(-1, 3)))
    ask = np.flatnonzero(~out)
    ask = ask[np.isin(pack_keys(cell[ask]), grown)]
    near = np.zeros(len(p), dtype=bool)
    if len(ask):
        nearest = nearest_indices(src, p[ask], threads)
        d2 = np.sum((p[ask] - src[nearest]) ** 2, axis=1)
        near[ask[d2 <= edge_m**2]] = True
    return out | near


def _ground_under_people(
    points_lidar: np.ndarray,
    labels: np.ndarray,
    people: np.ndarray,
    ground: tuple[int, ...],
    keep_m: float,
    cell_m: float,
    threads: int | None,
) -> tuple[np.ndarray, np.ndarray]:
    """(labels (N,) uint8, given back (N,) bool) where the points of ``people`` (N,) bool at
    most keep_m above the local
    ground (the lowest point of their cell_m cell and its neighbours, LiDAR frame) are ground (a
    class of ``ground``), not person: the ground a person stands on (a box with its margin, the person's image mask or
    label seen from the camera's other viewpoint holds it). Such a point keeps its label when the
    image says ground, else takes the label of the nearest ground-level point outside the people
    (PEDESTRIAN where none). Soles within keep_m of the ground are taken too: they lie within
    the range noise of the ground plane, which the surface fit assigns to the ground's voxel.
    given back: the points of people that now carry a ground label (the only ones to keep)."""
    from tasks.occupancy.nearest import nearest_indices
    from tasks.perception.lidar_clusters import ground_height

    p = np.asarray(points_lidar, dtype=np.float64).reshape(-1, 3)
    low = p[:, 2] - ground_height(p, cell_m) <= keep_m
    out = labels.copy()
    under = people & low
    out[under & ~np.isin(labels, ground)] = PEDESTRIAN
    ask = np.flatnonzero(under & (out == PEDESTRIAN))
    src = np.flatnonzero(low & ~people & np.isin(labels, ground))
    if len(ask) and len(src):
        out[ask] = labels[src][nearest_indices(p[src], p[ask], threads)]
    return out, under & np.isin(out, ground)


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
        ground_class_ids: tuple[int, ...] = (ROAD, TERRAIN),
        *,
        point_classes: str = "camera",
        geometry: GeometricClassSettings | None = None,
    ):
        self.params, self.freespace = params, freespace
        self.labeller = SweepLabeller(
            params,
            class_lut,
            K,
            T_cam_from_lidar,
            width,
            height,
            assoc_min_iou,
            threads,
            ground_class_ids,
            point_classes=point_classes,
            geometry=geometry,
        )
        self.seen = StaticSemanticMap(params.voxel_size_m, moments=True)
        self.unseen = StaticSemanticMap(params.voxel_size_m, moments=True)
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
        lidar_scores: np.ndarray | None = None,
        intensity: np.ndarray | None = None,
    ) -> None:
        """One sweep (N, 3) float32 LiDAR frame with its pose (4, 4), its detections and
        intensities (as :meth:`SweepLabeller.__call__`)."""
        s = self.labeller(
            points_lidar,
            semantic,
            mask_labels,
            boxes_xyxy,
            lidar_centers,
            lidar_sizes,
            lidar_yaws,
            lidar_scores,
            intensity,
            T_world_from_lidar,
        )
        world = world_points(T_world_from_lidar, points_lidar)
        origin = T_world_from_lidar[:3, 3]
        self.seen.add_sweep(world, s.labels, keep=s.keep & s.in_image, origin_world=origin)
        self.unseen.add_sweep(world, s.labels, keep=s.keep & ~s.in_image, origin_world=origin)
        self.occupancy.insert_scan(
            world[s.keep],
            T_world_from_lidar[:3, 3],
            max_range_m=self.freespace.max_range_m,
            discretize=self.freespace.discretize,
        )
        self.removed += int((~s.keep).sum())
        self.kept += int(s.keep.sum())

    def finish(self, ground_class_ids: tuple[int, ...]) -> tuple[StaticMap, StaticMap]:
        """(the final static map, the camera-labelled part of it) after the surface fit, the
        ground check and max voting; the occupancy map is ``self.occupancy``."""
        sides = [(*m.packed_counts(), m.packed_moments()) for m in (self.seen, self.unseen)]
        return final_maps(sides, self.params, ground_class_ids)


def final_maps(
    sides: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    params: MapParams,
    ground_class_ids: tuple[int, ...],
    select=None,
) -> tuple[StaticMap, StaticMap]:
    """(the static map, its camera-labelled part) from the raw votes of the camera-seen and the
    unseen points: sides = [(packed keys (K,) ascending, counts (K, 10) uint16, moments (K, 13)
    int64)] * 2. The surface fit (:func:`tasks.occupancy.surface.surface_fit`) runs on both sides'
    points together (one geometry) and drops the voxels that only hold noise in front of a
    neighbour's surface; each side is then voted (ground check, max voting) and the camera's side
    wins where both have a voxel; the voxels of fragments of that map smaller than
    ``params.min_fragment_voxels`` (:func:`tasks.occupancy.static_map.small_fragments`, over all
    the voxels given: give a halo of :func:`tasks.occupancy.tiles.ground_halo_tiles`) are dropped
    before the final vote. select(packed keys) -> bool: the voxels to return (all: None)."""
    vs, ground = params.voxel_size_m, tuple(ground_class_ids)
    keys, moments = group_sum(
        np.concatenate([k for k, _, _ in sides]), np.concatenate([m for _, _, m in sides])
    )
    fit = surface_fit(keys, moments, vs, params.surface_noise_m, params.surface_min_points)
    keeps = [
        fit.keep[np.searchsorted(keys, k)] if len(k) else np.zeros(0, bool) for k, _, _ in sides
    ]
    if params.min_fragment_voxels > 1:  # fragments of the voted map (all voxels given) go
        voted = [vote(k, c, params, ground, select=kp) for (k, c, _), kp in zip(sides, keeps)]
        whole = merge_static_maps(voted[0], voted[1])
        small = pack_keys(
            whole.keys[small_fragments(whole.keys, whole.labels, params.min_fragment_voxels)]
        )
        keeps = [kp & ~np.isin(k, small) for (k, _, _), kp in zip(sides, keeps)]
    maps = []
    for (k, counts, _), keep in zip(sides, keeps):
        if select is not None:
            keep &= select(k)
        maps.append(vote(k, counts, params, ground, select=keep))
    merged = merge_static_maps(maps[0], maps[1])
    surface = fit.surface[np.searchsorted(keys, pack_keys(merged.keys))]
    return replace(merged, surface=surface), maps[0]


def world_points(T_world_from_lidar: np.ndarray, points_lidar: np.ndarray) -> np.ndarray:
    """(N, 3) float32 world frame: the points that vote and are inserted (one rounding, shared by
    every way of running the map)."""
    return transform_points(T_world_from_lidar, points_lidar).astype(np.float32)


# ---- by tiles ------------------------------------------------------------------------------------


#: a tile's raw votes: (camera-seen packed keys (A,), counts (A, 10), moments (A, 13), unseen packed
#: keys (B,), counts (B, 10), moments (B, 13))
TileVotes = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


class WindowVotes:
    """Static-map votes of a window of consecutive sweeps, split by tile (seen by the camera and
    not, as :class:`SequenceMapper`) of ``params.voxel_size_m`` by tiles of ``params.tile_m``.
    State lives on the instance."""

    def __init__(self, params: MapParams):
        self.n = voxels_per_tile(params.tile_m, params.voxel_size_m)
        self.seen = StaticSemanticMap(params.voxel_size_m, moments=True)
        self.unseen = StaticSemanticMap(params.voxel_size_m, moments=True)
        self.kept = self.removed = 0

    def add(self, world: np.ndarray, sweep: SweepLabels, origin_world: np.ndarray) -> None:
        """world: (N, 3) float32 the sweep's points in the world frame (:func:`world_points`);
        origin_world: (3,) the LiDAR's position."""
        self.seen.add_sweep(
            world, sweep.labels, keep=sweep.keep & sweep.in_image, origin_world=origin_world
        )
        self.unseen.add_sweep(
            world, sweep.labels, keep=sweep.keep & ~sweep.in_image, origin_world=origin_world
        )
        self.removed += int((~sweep.keep).sum())
        self.kept += int(sweep.keep.sum())

    def by_tile(self) -> Iterator[tuple[tuple[int, int], TileVotes]]:
        """(tile, its votes) for every tile with votes, tiles ascending; keys ascending in each."""
        parts = [
            _split_by_tile(*m.packed_counts(), self.n, m.packed_moments())
            for m in (self.seen, self.unseen)
        ]
        empty = (
            np.empty(0, np.int64),
            np.empty((0, NUM_OCCUPIED_CLASSES), np.uint16),
            np.empty((0, NUM_MOMENTS), np.int64),
        )
        for tile in sorted(set(parts[0]) | set(parts[1])):
            yield tile, (*parts[0].get(tile, empty), *parts[1].get(tile, empty))


def _split_by_tile(
    packed: np.ndarray, counts: np.ndarray, n: int, *more: np.ndarray
) -> dict[tuple[int, int], tuple]:
    """Rows of a sorted vote table (and of the arrays ``more`` on the same rows) grouped by tile
    (each group keeps the ascending key order)."""
    if not len(packed):
        return {}
    tiles = tiles_of_keys(unpack_keys(packed), n)
    order = np.lexsort((packed, tiles[:, 1], tiles[:, 0]))
    t = tiles[order]
    cut = np.flatnonzero(np.any(t[1:] != t[:-1], axis=1)) + 1
    return {
        (int(t[a, 0]), int(t[a, 1])): tuple(x[order[a:b]] for x in (packed, counts, *more))
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
    p = params
    n = voxels_per_tile(p.tile_m, p.voxel_size_m)
    h = ground_halo_tiles(p)
    cache: dict[tuple[int, int], TileVotes | None] = {}
    for tile in sorted(tiles):
        near = [(tile[0] + dx, tile[1] + dy) for dx in range(-h, h + 1) for dy in range(-h, h + 1)]
        for t in [t for t in cache if t[0] < tile[0] - h]:
            del cache[t]
        votes = [cache[t] if t in cache else cache.setdefault(t, load(t)) for t in near]
        sides = [
            _sum_side([(v[side], v[side + 1], v[side + 2]) for v in votes if v is not None])
            for side in (0, 3)  # camera-seen, then unseen
        ]
        smap, camera = final_maps(
            sides,
            p,
            ground_class_ids,
            lambda keys, tile=tile: np.all(tiles_of_keys(unpack_keys(keys), n) == tile, axis=1),
        )
        yield tile, smap, len(camera.keys)


def _sum_side(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]]):
    """(packed keys, counts, moments) of one side summed over parts (windows or tiles)."""
    keys, counts = sum_votes([(k, c) for k, c, _ in parts])
    if not parts:
        return keys, counts, np.zeros((0, NUM_MOMENTS), np.int64)
    mk, mm = group_sum(
        np.concatenate([k for k, _, _ in parts]), np.concatenate([m for _, _, m in parts])
    )
    assert np.array_equal(mk, keys), "moments and votes cover the same voxels"
    return keys, counts, mm


def sum_tile_votes(parts: list[TileVotes]) -> TileVotes | None:
    """One tile's votes of several windows added (:func:`tasks.occupancy.static_map.sum_votes`,
    moments exactly)."""
    if not parts:
        return None
    seen = _sum_side([(p[0], p[1], p[2]) for p in parts])
    unseen = _sum_side([(p[3], p[4], p[5]) for p in parts])
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


def join_static_tiles(voxel_size_m: float, parts: list[tuple[np.ndarray, ...]]) -> StaticMap:
    """The static map of several tiles: parts of (keys (K, 3) int64, labels (K,) uint8, counts
    (K, 10) uint16[, surface (K, 6) float32]); keys ascending over the whole (packed order), as the
    whole-sequence map. The map has a surface when every part has one (no part: an empty one)."""
    if not parts:
        return StaticMap(
            voxel_size_m,
            np.empty((0, 3), np.int64),
            np.empty(0, np.uint8),
            np.empty((0, NUM_OCCUPIED_CLASSES), np.uint16),
            0,
            np.empty((0, 6), np.float32),
        )
    keys = np.concatenate([p[0] for p in parts])
    order = np.argsort(pack_keys(keys), kind="stable")
    surface = (
        np.concatenate([p[3] for p in parts])[order] if all(len(p) > 3 for p in parts) else None
    )
    return StaticMap(
        voxel_size_m,
        keys[order],
        np.concatenate([p[1] for p in parts])[order],
        np.concatenate([p[2] for p in parts])[order],
        0,
        surface,
    )
