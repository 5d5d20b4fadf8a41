"""Occupancy kernels: grid spec, free/unknown space (OctoMap semantics), the static semantic map,
visibility masks and the per-frame fusion into robot-local grids.

Conventions (frames, array dtypes, class ids) are those of :mod:`tasks.conventions`.

- :mod:`.grid`: ``GridSpec`` (box, voxel size, indices, centres).
- :mod:`.freespace`: ``OccupancyMap`` (insert_scan / query / query_grid / to_arrays / from_arrays).
- :mod:`.static_map`: ``StaticSemanticMap`` (add_sweep / finalize -> ``StaticMap``),
  ``project_points`` (once per sweep), ``lift_image_semantics``, ``pedestrian_point_mask``,
  ``pedestrian_boxes_for_masking``, ``lookup_labels`` (points in boxes: :mod:`tasks.geometry`).
- :mod:`.nearest`: ``nearest_indices`` (exact 3D nearest neighbours, the out-of-view fallback).
- :mod:`.tiles`: spatial tiles of the sequence maps and the map stage's split (``plan_map``:
  windows of frames, regions of tiles; ``tiles_near_grids``: what a fuse chunk reads).
- :mod:`.mapping`: ``SweepLabeller`` (labels, person removal), ``SequenceMapper`` (whole maps,
  the reference), ``WindowVotes`` / ``region_occupancy`` / ``finalize_tiles`` (the same maps by tile).
- :mod:`.resample`: ``static_in_grid`` / ``static_labels_at_cells`` (the static map in a local grid).
- :mod:`.visibility`: ``lidar_mask``, ``camera_mask``.
- :mod:`.fuse`: ``fuse_frame`` -> ``FrameGrids``; ``voxelize_mesh``, ``voxelize_labels``.
- :mod:`.threads`: the kernels' thread pools (an explicit count per call; None: one per core).
- :mod:`.synthetic`: OS1-128-like ray casting into box scenes (tests, benchmarks).
"""
