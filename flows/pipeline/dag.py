"""The DAG of a sequence's stages and their code versions."""

from __future__ import annotations

#: stage -> the stages whose products it reads. Order is a topological order.
STAGES: dict[str, tuple[str, ...]] = {
    "detect": (),
    "track": ("detect",),
    "fit": ("detect", "track"),  # detect: the frames it produced (the gap filler reads no other)
    "map": ("detect",),
    "fuse": ("detect", "track", "fit", "map"),  # detect: the frames it produced are the store's
    #                                            frame axis; track: a person's returns with no body
    "export": ("fuse", "track", "fit"),  # tables take tracks and body fits too
}

#: Explicit code versions: bump a stage's version when its output for the same input changes.
#: (A key from code versions, not from source hashes: refactors do not invalidate datasets.)
CODE_VERSIONS: dict[str, str] = {
    "detect": "4",  # 2: the oracle's miss curve calibrated on the paper's detection table; 3: a frame
    #               with bad input is left out (failed_frames in the summary) instead of failing the
    #               sequence, images decoded and size-checked, a sweep's channels from its sequence's
    #               first sweep (every later stage's key follows through its upstream keys)
    #               4: lidar-clusters: a robust ground (low percentile, multipath rejected) and a
    #               person score from shape (detect.lidar_clusters.min_score gates the boxes)
    "track": "6",  # 2: offline back-fill and stitching; 3: world-position check; 4: person points past the
    #               image side; 5: 2d_rect cameras read as the rectified pinhole (real CODa calibration)
    #               6: tracklets confirmed by one detection's evidence (track.confirm: image score,
    #               a matched LiDAR candidate's person score, keypoints): a person seen once is tracked
    "fit": "8",  # 2: L_3D caps the vertex -> point distances (fit.chamfer_vertex_max_m); 100 iterations;
    #             3: detections with fewer than fit.min_points LiDAR points are not fitted, fits
    #                that moved more than fit.max_shift_m from their estimate are dropped;
    #             4: bodies carry chamfer_m and reproj_px (typed products); the rectified camera;
    #                the kernel rewritten for speed (batched ICP, vertex subset, grid pairs); torch on 1 thread
    #             5: along tracks (tasks/fit/track_fit.py): left / right swaps decided, one shape
    #                per track, the temporal refinement, gap-filled bodies (Bodies.mirrored,
    #                .gap_filled); fit.init_provider lidar-keypoints
    #             6: default preset 3dpw (was ut_campus); torch really on 1 thread in a unit of
    #                several (flows/pipeline/parallel.limit_threads sized it after threadpoolctl)
    #             7: fit.flips.follow_start (off by default): with a provider's start, undecided
    #                rows' face / arms / legs relabelled towards it and keypoints far from it
    #                dropped (.start_max_distance; summary flips_chains_to_start,
    #                flips_keypoints_dropped); the refinement starts from each track's Whittaker-smoothed root,
    #                orientation and pose (fit.refine.*_cutoff_hz)
    #             8: ICP and L_3D read 1,500 of the visible vertices spread over the surface
    #                (fit.data_vertices; 2.9x the person-fits per CPU-second, MPJPE +0.06 mm)
    "map": "8",  # 2: the out-of-view fallback keeps ground and raised points apart, strips along the path;
    #             3: 2d_rect cameras read as the rectified pinhole (real CODa calibration);
    #             4: both maps written by spatial tile (map_tiles.npz + tiles/*.npz, map.tile_m), built in
    #                parallel windows / regions; the voxels are the same, the product files are not.
    #             (fuse not bumped: it reads the tiles near its frames and writes the same bytes; its key
    #             follows the map's key)
    #             5: voxels holding only the range noise of a neighbour's surface dropped, each voxel's
    #                surface kept (tasks/occupancy/surface.py; window votes carry point moments); the
    #                ground under a person kept; a person's other points removed whatever their label
    #             6: points within map.person_edge_m of a person's removed points removed too (a
    #                body's outline projecting just outside its image mask stayed in the map); a
    #                voxel without a plane of its own whose points crowd the face of a better-sampled
    #                voxel behind it is that surface's noise (a pole's arc just behind a face filled
    #                the voxel in front)
    #             7: a voxel that the own plane (flat, voxel-wide) of the voxel behind it reaches
    #                into is kept: a tree's crown bulging across a voxel face is no tail
    #                (tasks/occupancy/surface.py, WIDE_SPREAD)
    #                and fragments of fewer than map.min_fragment_voxels voxels of one class dropped
    #                (a missed passer-by's returns, single noisy labels in vegetation)
    #             8: map.point_classes: labels from the sweep's geometry where no camera label
    #                (tasks/occupancy/geometric_classes.py; auto: when detect gives no semantics)
    #                and out of the camera's view a LiDAR pedestrian box removes points only with a
    #                score of at least map.lidar_person_min_score (a false box deleted a real post)
    #                and returns with no class vote UNCLASSIFIED (class 9), rejected ground votes too;
    #                a voxel with no semantic vote is UNCLASSIFIED, not dropped (issue 38); counts
    #                (K, 10)
    "fuse": "5",  # 2: mask_camera is inside mask_lidar (Occ3D); class_counts among voxels with
    #               mask_lidar = 1 (as documented); store attrs carry the stage key, not a config hash;
    #               the rectified camera; 3: pedestrian voxel velocity from each vertex's motion along
    #               the track (fuse.velocity "vertex"), the mean over the body surface in the voxel;
    #               4: static voxels from points on each map voxel's surface (right at any offset of
    #               the grid, e.g. 10 Hz); every occupied voxel in mask_lidar; 5: no return is
    #               left free (one with nothing occupied among its 26 neighbours occupies its voxel:
    #               PEDESTRIAN for a tracked person's, else UNCLASSIFIED; fuse reads track too)
    "export": "6",  # 2: instances carry the fitted bodies, 3D boxes and velocities; 3: source paths
    #                 relative to the dataset root, box yaw from the body's forward axis, no NaN
    #                 velocity, chamfer_m / reproj_px written, config_hash of the stage inputs; the
    #                 rectified camera's K and T in the sequences table; 4: the Occ3D metadata says
    #                 semantics is free where mask_lidar is 0 and keeps hidden occupied voxels' class;
    #                 5: instances carry keypoints_mirrored and gap_filled, and a row per gap-filled
    #                 body (no 2D box or keypoints); 6: frames table 2 (11 class_counts,
    #                 unclassified_voxels)
}
#: Version of the dataset-level Occ3D / nuScenes exports (OUT/exports/, made after the sequences
#: are published; part of their key in the manifest): bump when their files change for the same
#: dataset. 2: labels.npz carries OpenOcc's flow; annotations.json and the training infos in time
#: order, the infos with the occupancy challenge's prev / next / frame_idx / can_bus / occ_gt_path;
#: the metadata's FlashOcc settings (depth, BEV flips, input sizes and their frustum coverage);
#: 3: the metadata says semantics is free where mask_lidar is 0 and keeps the class of occupied
#: voxels hidden from the camera (issue 30); 4: a robot log's scene is the log's own name (no
#: ``<scene_prefix>-``), the Occ3D img_path of a log's image has its extension (issue 38)
#: class 9 unclassified (Occ3D "others"), free 10, 11 classes (issue 38)
DATASET_EXPORTS_VERSION = "4"
