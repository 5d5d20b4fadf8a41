"""Synthetic LiDAR shapes for the detector tests: a person-shaped column, posts, bushes, a
ground plane and multipath returns below it (points (n, 3) float64, LiDAR frame, sensor at the
origin, z up)."""

from __future__ import annotations

import numpy as np


def visible_side(rng, n, cx, cy, rx, ry, z0, z1):
    """n points on the sensor-facing half of an elliptic column (radii rx along x, ry along y)."""
    facing = np.arctan2(-cy, -cx)
    angle = facing + rng.uniform(-np.pi / 2, np.pi / 2, n)
    return np.stack(
        [cx + rx * np.cos(angle), cy + ry * np.sin(angle), rng.uniform(z0, z1, n)], axis=1
    )


def person(rng, cx, cy, ground_z, height_m=1.75, density=300.0):
    """A standing person: two legs, a torso with arms, a neck and a head (the head narrower than
    the shoulders), density points per m^2 of the visible side."""
    h = height_m
    parts = [  # (dx, dy, rx, ry, z0, z1) as fractions of the height for z
        (0.0, 0.1, 0.07, 0.07, 0.0, 0.47),  # legs
        (0.0, -0.1, 0.07, 0.07, 0.0, 0.47),
        (0.0, 0.0, 0.13, 0.24, 0.47, 0.82),  # torso and arms
        (0.0, 0.0, 0.06, 0.06, 0.82, 0.87),  # neck
        (0.0, 0.0, 0.1, 0.09, 0.87, 1.0),  # head
    ]
    out = []
    for dx, dy, rx, ry, z0, z1 in parts:
        area = np.pi * (rx + ry) / 2 * (z1 - z0) * h
        count = max(3, int(density * area))
        out.append(
            visible_side(rng, count, cx + dx, cy + dy, rx, ry, ground_z + z0 * h, ground_z + z1 * h)
        )
    return np.concatenate(out)


def column(rng, cx, cy, radius, ground_z, height_m, density=300.0):
    """A round post or pole of one radius."""
    count = max(3, int(density * np.pi * radius * height_m))
    return visible_side(rng, count, cx, cy, radius, radius, ground_z, ground_z + height_m)


def bush(rng, cx, cy, ground_z, radius=0.6, height_m=1.2, density=300.0):
    """A squat scattered blob: points through an ellipsoid's volume (returns from leaves)."""
    count = int(density * 2 * radius * height_m)
    direction = rng.normal(size=(count, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    r = rng.uniform(0, 1, count) ** (1 / 3)
    centre = np.array([cx, cy, ground_z + height_m / 2])
    pts = centre + direction * r[:, None] * np.array([radius, radius, height_m / 2])
    return pts


def ground(rng, n, x, y, z, noise_m=0.02):
    """n points on the plane z (+ noise) over the x, y ranges."""
    return np.stack([rng.uniform(*x, n), rng.uniform(*y, n), z + rng.normal(0, noise_m, n)], axis=1)


def multipath(rng, n, x, y, z, depth_m=(1.0, 6.0)):
    """n returns 1-6 m below the road at z (reflections off wet asphalt, glass)."""
    return np.stack([rng.uniform(*x, n), rng.uniform(*y, n), z - rng.uniform(*depth_m, n)], axis=1)
