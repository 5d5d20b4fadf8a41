"""The map by spatial tiles (tasks/occupancy/tiles.py, mapping.py): windows of sweeps, regions,
tiles with a ground-check halo give the whole-sequence maps voxel for voxel, on a drive that
comes back over its own path; the map and fuse stages on tiles give the untiled grids byte for
byte and a fuse chunk reads only the tiles near its frames."""

from __future__ import annotations

import numpy as np
import pytest

from configs.schema import ConfigError, load_config
from storage.products import KeepMasks
from tasks.conventions import OTHER_STRUCTURE, ROAD, TERRAIN, VEGETATION
from tasks.occupancy.freespace import OccupancyMap
from tasks.occupancy.mapping import (
    SweepLabels,
    WindowVotes,
    final_maps,
    finalize_tiles,
    occupancy_tiles,
    region_occupancy,
    sum_tile_votes,
    world_points,
)
from tasks.occupancy.settings import FreeSpaceParams, MapParams
from tasks.occupancy.static_map import (
    StaticSemanticMap,
    pack_keys,
    sum_votes,
    unpack_keys,
    vote,
)
from tasks.occupancy.synthetic import (
    build_scene,
    campus_strip,
    organised_sweep,
    os1_directions,
    strip_poses,
)
from tasks.occupancy.tiles import (
    TileError,
    check_tiling,
    ground_halo_tiles,
    plan_map,
    static_groups,
    tiles_near_grids,
    tiles_of_keys,
    voxels_per_tile,
)

GROUND = (ROAD, TERRAIN)
#: small tiles, so the drive crosses many borders; 3-sweep windows; one-tile regions
PARAMS = MapParams(
    tile_m=3.2, window_frames=3, region_tiles=1, ground_cell_m=1.0, ground_neighbourhood_cells=1
)
FREESPACE = FreeSpaceParams(max_range_m=8.0)


@pytest.fixture(scope="module")
def drive():
    """Sweeps of a walk out along a campus strip and back over the same places (poses repeat,
    reversed): (points (N, 3) float32 LiDAR frame, T_world_from_lidar, labels) per sweep. Labels:
    ground road / terrain by position, raised points mostly structure with some spurious road votes
    (the ground check rejects those), high points vegetation."""
    scene = build_scene(campus_strip(10.0, seed=3, reach_m=30.0))
    poses = strip_poses(6, step_m=1.5, lidar_height_m=0.9)
    out = []
    for k in [0, 1, 2, 3, 4, 5, 4, 3, 2, 1]:
        pts = organised_sweep(scene, poses[k], os1_directions(64, 256), max_range_m=25.0)
        pts = pts[np.any(pts != 0, axis=1)]
        w = world_points(poses[k], pts)
        rng = np.random.default_rng(k)
        labels = np.where(
            w[:, 2] < 0.05,
            np.where(np.floor(w[:, 1] / 2.0) % 2 == 0, ROAD, TERRAIN),
            np.where(
                w[:, 2] > 2.0,
                VEGETATION,
                np.where(rng.random(len(w)) < 0.15, ROAD, OTHER_STRUCTURE),
            ),
        ).astype(np.uint8)
        out.append((pts, poses[k], labels))
    return out


def _sweep(pts, labels):
    """Keep all but a pretend person (points within 0.4 m of LiDAR (3, 2)); in view: x > 0."""
    person = np.hypot(pts[:, 0] - 3.0, pts[:, 1] - 2.0) < 0.4
    return SweepLabels(labels, ~person, pts[:, 0] > 0)


def _whole(drive):
    """The sequential maps (SequenceMapper's arithmetic): two vote tables, one occupancy map."""
    seen, unseen, occ = (
        StaticSemanticMap(PARAMS.voxel_size_m, moments=True),
        StaticSemanticMap(PARAMS.voxel_size_m, moments=True),
        OccupancyMap(FREESPACE),
    )
    for pts, T, labels in drive:
        s, w = _sweep(pts, labels), world_points(T, pts)
        seen.add_sweep(w, s.labels, keep=s.keep & s.in_image, origin_world=T[:3, 3])
        unseen.add_sweep(w, s.labels, keep=s.keep & ~s.in_image, origin_world=T[:3, 3])
        occ.insert_scan(
            w[s.keep],
            T[:3, 3],
            max_range_m=FREESPACE.max_range_m,
            discretize=FREESPACE.discretize,
        )
    final, camera = final_maps(
        [(*m.packed_counts(), m.packed_moments()) for m in (seen, unseen)], PARAMS, GROUND
    )
    return final, camera, occ


def _tiled(drive):
    """The same drive by windows, regions and tiles."""
    plan = plan_map(np.array([T[:3, 3] for _, T, _ in drive]), PARAMS, FREESPACE)
    votes: dict = {}
    for w, (a, b) in enumerate(plan.windows):
        wv = WindowVotes(PARAMS)
        for pts, T, labels in drive[a:b]:
            wv.add(world_points(T, pts), _sweep(pts, labels), T[:3, 3])
        for tile, arrays in wv.by_tile():
            votes[(w, tile)] = arrays
    groups = static_groups(
        plan,
        [(w, [t for (ww, t) in votes if ww == w]) for w in range(len(plan.windows))],
        ground_halo_tiles(PARAMS),
    )
    static = []
    for tiles, where in groups:
        load = lambda t, where=where: sum_tile_votes([votes[(w, t)] for w in where.get(t, [])])
        static += list(finalize_tiles(tiles, load, PARAMS, GROUND))
    n = voxels_per_tile(PARAMS.tile_m, FREESPACE.voxel_size_m, 8)
    occ = {}
    for region, frames in plan.regions:
        scans = [
            (
                world_points(drive[i][1], drive[i][0])[_sweep(drive[i][0], drive[i][2]).keep],
                drive[i][1][:3, 3],
            )
            for i in frames
        ]
        for tile, keys, logodds in occupancy_tiles(
            region_occupancy(FREESPACE, plan.region_keys(region, n), scans), PARAMS.tile_m
        ):
            assert tile not in occ  # each tile comes from one region
            occ[tile] = (keys, logodds)
    return plan, static, occ


def test_tiles_windows_and_regions_equal_the_whole_sequence_maps(drive):
    final, camera, whole_occ = _whole(drive)
    plan, static, occ = _tiled(drive)
    assert len(plan.windows) == 4 and len(plan.regions) > 4 and len({t for t, _, _ in static}) > 20
    keys = np.concatenate([m.keys for _, m, _ in static])
    order = np.argsort(pack_keys(keys))
    for name in ("keys", "labels", "counts", "surface"):
        got = np.concatenate([getattr(m, name) for _, m, _ in static])[order]
        np.testing.assert_array_equal(got, getattr(final, name), err_msg=name)
    for tile, m, _ in static:  # every voxel in its own tile, ascending in it
        assert np.all(tiles_of_keys(m.keys, 16) == tile) and np.all(np.diff(pack_keys(m.keys)) > 0)
    assert sum(c for _, _, c in static) == len(camera.keys)
    assert sum(m.ground_rejected for _, m, _ in static) == final.ground_rejected > 0
    ok, ov = whole_occ.to_arrays()
    tk = np.concatenate([k for k, _ in occ.values()])
    tv = np.concatenate([v for _, v in occ.values()])
    a, b = np.argsort(pack_keys(ok)), np.argsort(pack_keys(tk))
    np.testing.assert_array_equal(tk[b], ok[a])
    assert tv[b].tobytes() == ov[a].tobytes()


def test_the_ground_check_needs_the_halo(drive):
    """Voted tile by tile without the neighbouring tiles' votes, some border voxels come out
    differently (so the test above would catch a halo that is too small)."""
    seen = StaticSemanticMap(PARAMS.voxel_size_m)
    for pts, T, labels in drive:
        s = _sweep(pts, labels)
        seen.add_sweep(world_points(T, pts), s.labels, keep=s.keep & s.in_image)
    keys, counts = seen.packed_counts()
    tiles = tiles_of_keys(unpack_keys(keys), 16)
    whole = vote(keys, counts, PARAMS, GROUND)
    alone = [
        vote(keys[inside], counts[inside], PARAMS, GROUND)
        for inside in (np.all(tiles == t, axis=1) for t in np.unique(tiles, axis=0))
    ]
    order = np.argsort(pack_keys(np.concatenate([m.keys for m in alone])))
    assert not np.array_equal(np.concatenate([m.counts for m in alone])[order], whole.counts)


def test_votes_of_windows_add_with_saturation():
    """uint16 counts saturate once, whatever the windows: 3 x 30,000 votes -> 65,535."""
    one = StaticSemanticMap(1.0, flush_points=1)
    parts = []
    for _ in range(3):
        pts, lab = np.full((30_000, 3), 0.5, np.float32), np.full(30_000, ROAD, np.uint8)
        one.add_sweep(pts, lab)
        w = StaticSemanticMap(1.0)
        w.add_sweep(pts, lab)
        parts.append(w.packed_counts())
    keys, counts = sum_votes(parts)
    np.testing.assert_array_equal(keys, one.packed_counts()[0])
    np.testing.assert_array_equal(counts, one.packed_counts()[1])
    assert counts[0, ROAD] == 65535


def test_plan_regions_hold_every_frame_that_reaches_them():
    rng = np.random.default_rng(0)
    origins = np.column_stack(
        [np.cumsum(rng.normal(0, 3, 200)), np.cumsum(rng.normal(0, 3, 200)), np.ones(200)]
    )
    plan = plan_map(
        origins,
        MapParams(window_frames=50, tile_m=25.6, region_tiles=2),
        FreeSpaceParams(voxel_size_m=0.2, max_range_m=20.0),
    )
    assert plan.windows == [(0, 50), (50, 100), (100, 150), (150, 200)]
    n = voxels_per_tile(25.6, 0.2, 8)
    for region, frames in plan.regions:
        kx0, kx1, ky0, ky1 = plan.region_keys(region, n)
        box_lo, box_hi = (
            np.floor((origins[:, :2] - 20.0) / 0.2) - 8,
            np.floor((origins[:, :2] + 20.0) / 0.2) + 8,
        )
        reach = (
            (box_hi[:, 0] >= kx0)
            & (box_lo[:, 0] < kx1)
            & (box_hi[:, 1] >= ky0)
            & (box_lo[:, 1] < ky1)
        )
        assert set(np.flatnonzero(reach)) == set(frames.tolist())
    first_tile = np.floor(origins[0, :2] / 25.6).astype(int)
    assert plan.region_of_tile(first_tile) == (
        0,
        0,
    )  # the start is inside a region, not at a corner
    assert plan.region_of_tile(first_tile - 1) == (0, 0)


def test_tile_sizes_that_do_not_cut_whole_voxels_fail():
    check_tiling(25.6, 0.2, 0.2)
    check_tiling(25.6, 0.05, 0.1)
    with pytest.raises(TileError, match="8-voxel blocks"):
        check_tiling(10.0, 0.2, 0.2)
    with pytest.raises(TileError, match="static map"):
        check_tiling(25.6, 0.15, 0.2)
    with pytest.raises(ConfigError, match="map.tile_m"):
        load_config(overrides={"map.tile_m": 10.0})
    with pytest.raises(ValueError, match="finite max_range_m"):
        plan_map(
            np.zeros((3, 3)),
            MapParams(window_frames=10, tile_m=25.6, region_tiles=4),
            FreeSpaceParams(voxel_size_m=0.2, max_range_m=-1.0),
        )


def test_tiles_near_grids_cover_the_reach():
    T = np.eye(4)
    T[:2, 3] = (25.0, -0.5)
    assert tiles_near_grids(25.6, 11.0, T[None], 0.2) == [
        (tx, ty) for tx in (0, 1) for ty in (-1, 0)
    ]
    T[:2, 3] = (24.0, 5.0)
    assert tiles_near_grids(25.6, 1.0, T[None], 0.2) == [(0, 0)]
    assert tiles_near_grids(25.6, 1.0, T[None], 1.0) == [(0, 0), (1, 0)]


def test_keep_masks_round_trip(tmp_path):
    masks = [np.array([1, 0, 1], bool), np.zeros(0, bool), np.arange(13) % 3 == 0]
    KeepMasks.of([4, 6, 8], masks).write(tmp_path, KeepMasks.file_name(2))
    back = KeepMasks.read(tmp_path, KeepMasks.file_name(2))
    for r, m in enumerate(masks):
        np.testing.assert_array_equal(back.mask(r), m)
    assert back.frame.tolist() == [4, 6, 8]


def test_region_pieces_of_an_occupancy_map_on_every_path(monkeypatch):
    """Regions of one block up to many tiles, dense and sparse marking, discretize: the pieces of
    the map of the whole plane."""
    import tasks.occupancy.freespace as fs

    scene = build_scene(campus_strip(4.0, seed=1, reach_m=20.0))
    scans = []
    for T in strip_poses(3, step_m=2.0, lidar_height_m=0.9):
        pts = organised_sweep(scene, T, os1_directions(32, 256), max_range_m=15.0)
        scans.append((world_points(T, pts[np.any(pts != 0, axis=1)]), T[:3, 3]))
    for dense_max, discretize in (
        (fs._DENSE_MAX_BLOCKS, False),
        (0, False),
        (fs._DENSE_MAX_BLOCKS, True),
    ):
        monkeypatch.setattr(fs, "_DENSE_MAX_BLOCKS", dense_max)
        whole = OccupancyMap(FreeSpaceParams(voxel_size_m=0.2), threads=2)
        for p, o in scans:
            whole.insert_scan(p, o, max_range_m=10.0, discretize=discretize)
        keys, vals = whole.to_arrays()
        got = {}
        for x0 in range(-64, 96, 16):
            for y0 in range(-64, 64, 24):
                m = OccupancyMap(FreeSpaceParams(voxel_size_m=0.2), threads=2)
                for p, o in scans:
                    m.insert_scan(
                        p,
                        o,
                        max_range_m=10.0,
                        discretize=discretize,
                        region=(x0, x0 + 16, y0, y0 + 24),
                    )
                k, v = m.to_arrays()
                assert np.all(
                    (k[:, 0] >= x0) & (k[:, 0] < x0 + 16) & (k[:, 1] >= y0) & (k[:, 1] < y0 + 24)
                )
                got.update(zip(map(tuple, k.tolist()), v.tolist()))
        assert got == dict(zip(map(tuple, keys.tolist()), vals.tolist())), (dense_max, discretize)


def test_a_region_must_be_whole_blocks():
    m = OccupancyMap(FreeSpaceParams(voxel_size_m=0.2))
    with pytest.raises(ValueError, match="multiples of 8"):
        m.insert_scan(
            np.ones((2, 3)), np.zeros(3), max_range_m=-1.0, discretize=False, region=(0, 12, 0, 8)
        )


def _grids(out, outcome) -> dict[str, bytes]:
    import zarr

    g = zarr.open_group(str(out / outcome.location / "occupancy.zarr"), mode="r")
    return {
        name: g[name][:].tobytes()
        for name in ("semantics", "instances", "mask_lidar", "mask_camera", "velocity")
    }


def test_map_and_fuse_stages_by_tile_equal_the_whole_maps(synthetic_root, tmp_path, monkeypatch):
    """Stage level, small tiles, one-frame windows, one-tile regions: the tiles are the
    whole-sequence maps of SequenceMapper; a fuse chunk reads only tiles near its frames; its grids
    equal those fused from maps in four huge tiles (the whole maps, every tile read)."""
    from flows.bench.common import make_config, run_stages
    from flows.pipeline.inputs import map_inputs, open_sequence
    from storage.products import (
        TILES,
        Detections,
        MapTiles,
        OccupancyMapProduct,
        Product,
        StaticMapProduct,
    )
    from tasks.conventions import UNLABELED
    from tasks.occupancy.mapping import SequenceMapper
    from tasks.occupancy.resample import grid_reach_m

    reads, read = [], Product.read.__func__
    monkeypatch.setattr(
        Product,
        "read",
        classmethod(
            lambda cls, folder, name=None: (
                reads.append((cls.__name__, name)),
                read(cls, folder, name),
            )[1]
        ),
    )
    out = tmp_path / "out"
    base = {
        "fuse.body_source": "ground-truth",
        "dataset.sequences": ["0"],
        "dataset.max_range_m": 30.0,
    }
    small_cfg = make_config(
        synthetic_root,
        out,
        {**base, "map.tile_m": 6.4, "map.window_frames": 1, "map.region_tiles": 1},
    )
    small = run_stages(small_cfg, ("detect", "map", "fuse")).outcomes
    fuse_reads = {name for kind, name in reads if kind.endswith("MapProduct")}
    map_dir = out / small[("0", "map")].location
    index = MapTiles.read(map_dir)
    assert small[("0", "map")].summary["windows"] == 2 and len(index.static_tiles) > 10
    # the tiles are the sequential maps
    inp, seq = map_inputs(small_cfg), open_sequence(small_cfg, "0")
    cam = seq.info.calibration.cameras[inp.source.camera]
    lut = np.full(256, UNLABELED, np.uint8)
    lut[[k for k, _ in inp.class_lut]] = [v for _, v in inp.class_lut]
    mapper = SequenceMapper(
        inp.settings,
        inp.freespace,
        lut,
        cam.K,
        cam.T_cam_from_lidar,
        cam.width,
        cam.height,
        inp.assoc_min_iou,
    )
    for i in range(len(seq)):
        f = seq.frame(i)
        d = Detections.read(out / small[("0", "detect")].location, Detections.file_name(f.index))
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
        )
    final, _ = mapper.finish(inp.ground_class_ids)
    tiles = [
        StaticMapProduct.read(map_dir / TILES, StaticMapProduct.file_name(t))
        for t in index.static_tiles
    ]
    keys = np.concatenate([t.keys for t in tiles])
    order = np.argsort(pack_keys(keys))
    np.testing.assert_array_equal(keys[order], final.keys)
    np.testing.assert_array_equal(np.concatenate([t.labels for t in tiles])[order], final.labels)
    occ = [
        OccupancyMapProduct.read(map_dir / TILES, OccupancyMapProduct.file_name(t))
        for t in index.occupancy_tiles
    ]
    ok, ov = mapper.occupancy.to_arrays()
    tk, tv = np.concatenate([o.keys for o in occ]), np.concatenate([o.logodds for o in occ])
    a, b = np.argsort(pack_keys(ok)), np.argsort(pack_keys(tk))
    assert np.array_equal(tk[b], ok[a]) and tv[b].tobytes() == ov[a].tobytes()
    # the fuse read the tiles near its frames, not the others
    T_base = np.linalg.inv(seq.info.calibration.T_base_from_lidar)
    near = tiles_near_grids(
        6.4, grid_reach_m(small_cfg.fuse.grid.spec()), seq.info.poses @ T_base, 0.2
    )
    assert fuse_reads == {
        f(t)
        for t in near
        for f, tt in (
            (StaticMapProduct.file_name, index.static_tiles),
            (OccupancyMapProduct.file_name, index.occupancy_tiles),
        )
        if np.any(np.all(tt == t, axis=1))
    }
    assert len(fuse_reads) < len(index.static_tiles) + len(index.occupancy_tiles)
    # whole maps (four tiles of 819.2 m around the origin, all read): the same grids
    small_grids, _ = (
        _grids(out, small[("0", "fuse")]),
        reads.clear(),
    )  # (a new run removes older versions)
    whole = run_stages(
        make_config(synthetic_root, out, {**base, "map.tile_m": 819.2}), ("detect", "map", "fuse")
    ).outcomes
    whole_index = MapTiles.read(out / whole[("0", "map")].location)
    assert len([n for k, n in reads if k.endswith("MapProduct")]) == len(
        whole_index.static_tiles
    ) + len(whole_index.occupancy_tiles)
    assert _grids(out, whole[("0", "fuse")]) == small_grids
