"""Perception kernels: the provider interface, the oracle provider, LiDAR clusters, person points.

See :mod:`tasks.perception.types` for the arrays every provider returns.
"""
