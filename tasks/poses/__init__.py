"""Rigid poses over time: quaternions, interpolation, a TF tree as data, LiDAR odometry.

Conventions of :mod:`tasks.conventions`: poses (4, 4) float64 ``T_target_from_source``,
quaternions (w, x, y, z), stamps integer nanoseconds. Kernels only: nothing here reads a file.
"""
