"""fuse: per frame, the robot-local grid: pedestrians over static, free / unknown, masks, velocity.

Frames fan out in chunks aligned to the Zarr store's write units (one writer per chunk). Output:
``occupancy.zarr`` (storage/occupancy_store.py, documented in storage/SCHEMA.md) and
:class:`storage.products.FusedFrames`. mask_lidar is the union of this frame's LiDAR rays
(traversed or hit voxels) and the voxels the sequence's occupancy map has observed (known free or
occupied), so "unknown" means never observed.
mask_camera is cam0's visibility restricted to mask_lidar, as in Occ3D (storage/SCHEMA.md, "Masks").
No return of a frame is left free: a return with nothing occupied at or next to its voxel occupies
it, PEDESTRIAN where it is a tracked person's point (the track's points: a person whose body was
not fitted), else UNCLASSIFIED.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flows.pipeline.inputs import FuseInputs, SequenceRef
from flows.pipeline.parallel import fan_out
from flows.stages.common import StageContext, body_model, detected_positions
from storage.gt import frame_path, read_frame_gt, read_sequence_gt
from storage.occupancy_store import create_store, write_frames
from storage.products import (
    TILES,
    Bodies,
    FusedFrames,
    MapTiles,
    OccupancyMapProduct,
    PersonVoxels,
    StaticMapProduct,
    Tracks,
)
from tasks.body.motion import TrackedBodies
from tasks.conventions import FREE, NUM_CLASSES, PEDESTRIAN, UNCLASSIFIED
from tasks.geometry import transform_points
from tasks.occupancy.frame import local_grids, relative_pose
from tasks.occupancy.freespace import OccupancyMap
from tasks.occupancy.fuse import CameraView, PedestrianMesh, returns_without_class
from tasks.occupancy.mapping import join_static_tiles
from tasks.occupancy.resample import grid_reach_m
from tasks.occupancy.static_map import StaticMap
from tasks.occupancy.tiles import tiles_near_grids


class _People:
    """The pedestrians of a frame as meshes in the base frame: fitted bodies, or the simulator's;
    with ``fusion.velocity`` "vertex" each vertex carries its own velocity (tasks/body/motion.py
    for fits, the ground truth's ``vertex_velocity_base`` for the simulator's bodies)."""

    def __init__(self, inputs: FuseInputs, seq, out_root: Path, fit_dir: Path | None):
        self.inputs, self.seq, self.per_vertex = inputs, seq, inputs.fusion.velocity != "person"
        self.T = seq.info.calibration.T_base_from_lidar
        if inputs.body_source == "ground-truth":
            self.faces = read_sequence_gt(seq.root, seq.sequence).person_faces
            return
        self.model = body_model(inputs.body, out_root)
        self.faces = np.asarray(self.model.faces)
        b = Bodies.read(fit_dir) if fit_dir is not None else Bodies.empty()
        pos = {raw: k for k, raw in enumerate(seq.info.frame_indices)}
        gap = (
            inputs.fusion.velocity_max_gap_s if self.per_vertex else 0.0
        )  # per person: no neighbour posed
        self.bodies = TrackedBodies(
            self.model,
            b.betas,
            b.global_orient,
            b.body_pose,
            b.transl,
            b.track_id,
            np.array([pos[int(f)] for f in b.frame], np.int64),
            b.velocity_base,
            seq.info.stamps_ns * 1e-9,
            seq.info.poses,
            self.T,
            gap,
            relative=inputs.fusion.velocity == "articulated",
            neighbours=inputs.fusion.velocity_neighbours,
        )

    def __call__(self, position: int, frame: int) -> list[PedestrianMesh]:
        if self.inputs.body_source == "ground-truth":
            ids, verts, vel, vertex_vel = self._ground_truth(frame)
        else:
            rows, verts, vertex_vel = self.bodies.frame(position)
            ids, vel = self.bodies.track_id[rows], self.bodies.velocity_base[rows]
        return [
            PedestrianMesh(
                int(t),
                transform_points(self.T, v),
                self.faces,
                w,
                vertex_vel[k, :, :2] if self.per_vertex else None,
            )
            for k, (t, v, w) in enumerate(zip(ids, verts, vel))
        ]

    def _ground_truth(self, frame: int):
        """(track ids, vertices LiDAR frame, person velocities, vertex velocities base axes) of
        the observed simulated people."""
        gt = read_frame_gt(self.seq.root, self.seq.sequence, frame)
        returns = np.array([(gt.point_instance == t).sum() for t in gt.track_id], np.int64)
        n = self.inputs.gt_min_points
        observed = (returns >= n) & (gt.visible_fraction > 0) if n else returns >= 0
        if self.per_vertex and gt.vertex_velocity_base is None:
            raise ValueError(
                f"{frame_path(self.seq.root, self.seq.sequence, frame)}: no vertex_velocity_base "
                "(ground truth simulated before it existed): simulate again, or set "
                "fuse.velocity: person"
            )
        vertex_vel = gt.vertex_velocity_base[observed] if self.per_vertex else None
        return gt.track_id[observed], gt.vertices[observed], gt.velocity_base[observed], vertex_vel


def maps_near(
    map_dir: Path, inputs: FuseInputs, T_world_from_base: np.ndarray
) -> tuple[StaticMap, OccupancyMap]:
    """The static and occupancy maps of the tiles that a grid at these poses ((F, 4, 4)) can touch:
    a chunk reads a bounded part of the sequence's maps, and its grids equal those of whole maps."""
    index = MapTiles.read(map_dir)
    sv, ov = float(index.static_voxel_size_m), float(index.occupancy_voxel_size_m)
    tiles = tiles_near_grids(
        float(index.tile_m), grid_reach_m(inputs.grid), T_world_from_base, max(sv, ov)
    )
    static = [
        StaticMapProduct.read(map_dir / TILES, StaticMapProduct.file_name(t))
        for t in tiles
        if index.has("static", t)
    ]
    occ = [
        OccupancyMapProduct.read(map_dir / TILES, OccupancyMapProduct.file_name(t))
        for t in tiles
        if index.has("occupancy", t)
    ]
    keys = np.concatenate([o.keys for o in occ]) if occ else np.empty((0, 3), np.int64)
    logodds = np.concatenate([o.logodds for o in occ]) if occ else np.empty(0, np.float32)
    return (
        join_static_tiles(sv, [(p.keys, p.labels, p.counts, p.surface) for p in static]),
        OccupancyMap.from_arrays(inputs.freespace, keys, logodds),
    )


def _return_labels(tracks: Tracks | None, frame: int, num_points: int) -> np.ndarray:
    """(N,) uint8 per point of a frame's sweep: PEDESTRIAN for the points of a tracked person
    (the track stage's confirmed persons), else UNCLASSIFIED: the class of a return's voxel where
    nothing occupied is at or next to it."""
    out = np.full(num_points, UNCLASSIFIED, np.uint8)
    if tracks is None:
        return out
    for row in np.flatnonzero(tracks.frame == frame):
        idx = tracks.points_of(int(row))
        out[idx[(idx >= 0) & (idx < num_points)]] = PEDESTRIAN
    return out


def _person_voxels(tracks: Tracks | None, frame: int, points_base, spec, grids) -> list[tuple]:
    """(frame, det_index, unclassified voxels, pedestrian voxels without body) per Tracks row of
    the frame: the voxels of the person's points (:class:`storage.products.PersonVoxels`)."""
    if tracks is None:
        return []
    idx = spec.index_of(points_base)
    return [
        (
            frame,
            int(tracks.det_index[r]),
            *returns_without_class(
                grids["semantics"], grids["instances"], idx[tracks.points_of(int(r))]
            ),
        )
        for r in np.flatnonzero(tracks.frame == frame)
    ]


def fuse_chunk(
    ref: SequenceRef,
    inputs: FuseInputs,
    out_root: Path,
    positions: list[int],
    store: Path,
    map_dir: Path,
    fit_dir: Path | None,
    start: int,
    threads: int,
    track_dir: Path | None = None,
) -> list[dict]:
    """Fuse some frames (positions in the sequence) and write them as one write unit of the store,
    from index ``start`` of its frame axis (the frames detect produced, in order)."""
    seq = inputs.source.open(ref)
    calib = seq.info.calibration
    cam, T_base_from_lidar = calib.cameras[inputs.source.camera], calib.T_base_from_lidar
    smap, occupancy = maps_near(
        map_dir, inputs, relative_pose(seq.info.poses[positions], T_base_from_lidar)
    )
    people = _People(inputs, seq, out_root, fit_dir)
    tracks = Tracks.read(track_dir) if track_dir is not None else None
    camera = (
        CameraView(
            cam.K, cam.width, cam.height, relative_pose(T_base_from_lidar, cam.T_cam_from_lidar)
        )
        if inputs.fusion.camera_mask
        else None
    )
    stacks, rows = {}, []
    for i in positions:
        frame = seq.frame(i)
        T_world_from_base = relative_pose(frame.T_world_from_lidar, T_base_from_lidar)
        persons = people(i, frame.index)
        grids, counts = local_grids(
            inputs.grid,
            T_world_from_base,
            smap,
            occupancy,
            persons,
            frame.points_lidar,
            T_base_from_lidar,
            camera,
            inputs.fusion,
            threads,
            _return_labels(tracks, frame.index, len(frame.points_lidar)),
        )
        for name, value in grids.items():
            stacks.setdefault(name, []).append(value)
        points_base = transform_points(T_base_from_lidar, frame.points_lidar)
        persons_voxels = _person_voxels(tracks, frame.index, points_base, inputs.grid, grids)
        rows.append(
            {
                "frame": frame.index,
                "stamp_ns": frame.stamp_ns,
                "people": len(persons),
                "counts": counts,
                "T_world_from_base": T_world_from_base,
                "person_voxels": persons_voxels,
            }
        )
    write_frames(store, start, {k: np.stack(v) for k, v in stacks.items()})
    return rows


def run_fuse(ctx: StageContext[FuseInputs]) -> dict:
    inp, spec = ctx.inputs, ctx.inputs.grid
    fit_dir = ctx.upstream.get("fit") if inp.body_source == "fit" else None
    store, at = ctx.out_dir / "occupancy.zarr", detected_positions(ctx, ctx.open())
    layout = create_store(
        store,
        len(at),
        spec.shape,
        inp.frames_per_chunk,
        {
            "range_min": list(spec.range_min),
            "range_max": list(spec.range_max),
            "voxel_size_m": spec.voxel_size_m,
            "stage_key": ctx.key,
            "sequence": ctx.sequence,
            "body_source": inp.body_source,
        },
    )
    parts = fan_out(
        fuse_chunk,
        [
            (
                ctx.ref,
                inp,
                ctx.out_root,
                at[a:b],
                store,
                ctx.upstream["map"],
                fit_dir,
                a,
                ctx.runtime.threads,
                ctx.upstream.get("track"),  # absent in a stage-level run without track
            )
            for a, b in layout.write_units()
        ],
        threads=ctx.runtime.threads,
    )
    rows = [r for part in parts for r in part]
    counts = np.array([r["counts"] for r in rows], np.int64).reshape(-1, NUM_CLASSES)
    FusedFrames(
        np.array([r["frame"] for r in rows], np.int64),
        np.array([r["stamp_ns"] for r in rows], np.int64),
        counts,
        np.array([r["T_world_from_base"] for r in rows], np.float64).reshape(-1, 4, 4),
    ).write(ctx.out_dir)
    person = [p for r in rows for p in r["person_voxels"]]
    PersonVoxels(*(np.array([p[k] for p in person], np.int64).reshape(-1) for k in range(4))).write(
        ctx.out_dir
    )
    return {
        "implemented": True,
        "frames": len(rows),
        "grid_shape": list(spec.shape),
        "voxel_size_m": spec.voxel_size_m,
        "body_source": inp.body_source,
        "pedestrian_meshes": sum(r["people"] for r in rows),
        # among voxels with mask_lidar = 1: the labels' honesty at a glance (status, end of run)
        "occupied_voxels": int(counts[:, :FREE].sum()),
        "unclassified_voxels": int(counts[:, UNCLASSIFIED].sum()),
    }
