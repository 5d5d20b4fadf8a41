"""Occupancy kernels: grid spec, free/unknown space (OctoMap semantics), the static semantic map,
visibility masks and the per-frame fusion into robot-local grids.

Conventions (frames, array dtypes, class ids) are those of :mod:`tasks.conventions`.

- :mod:`.grid`: ``GridSpec`` (box, voxel size, indices, centres).
- :mod:`.freespace`: ``OccupancyMap`` (insert_scan / query / query_grid / to_arrays / from_arrays).
- :mod:`.static_map`: ``StaticSemanticMap`` (add_sweep / finalize -> ``StaticMap``),
  ``lift_image_semantics``, ``pedestrian_point_mask``, ``points_in_boxes``.
- :mod:`.visibility`: ``lidar_mask``, ``camera_mask``.
- :mod:`.fuse`: ``fuse_frame`` -> ``FrameGrids``; ``voxelize_mesh``, ``voxelize_labels``.
- :mod:`.synthetic`: OS1-128-like ray casting into box scenes (tests, benchmarks).
"""
