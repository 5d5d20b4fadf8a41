"""Human mesh fitting (paper Sec. "Human Mesh Optimization", appendices A-C).

Frame: every fit works in the OpenCV camera frame (``cam``: x right, y down, z forward, metres),
where the 2D reprojection term is natural; LiDAR points are moved into it with
``T_cam_from_lidar`` before fitting. Pipeline per chunk of persons: visibility filter
(:mod:`.visibility`) -> rigid ICP (:mod:`.icp`) -> batched Adam on the six-term objective
(:mod:`.losses`, :mod:`.optimize`).
"""
