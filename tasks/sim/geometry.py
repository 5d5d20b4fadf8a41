"""Mesh primitives for the synthetic campus (world frame, metres; rigid transforms in
:mod:`tasks.geometry`).

A :class:`Solid` is one closed convex triangle mesh with its half-space planes (for exact
inside tests of the ground-truth occupancy), a class id (:mod:`tasks.conventions`) and an
instance id. A :class:`Surface` is an open mesh (the ground) with no interior.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull

from tasks.geometry import rot_z


@dataclass(frozen=True)
class Solid:
    """A convex closed mesh in the world frame.

    vertices: (V, 3) float64 metres. faces: (F, 3) int32, outward winding.
    planes: (P, 4) float64, a point p is inside when ``planes[:, :3] @ p + planes[:, 3] <= 0``.
    """

    vertices: np.ndarray
    faces: np.ndarray
    planes: np.ndarray
    class_id: int
    instance_id: int


@dataclass(frozen=True)
class Surface:
    """An open mesh (no inside) in the world frame: vertices (V, 3) float64, faces (F, 3) int32."""

    vertices: np.ndarray
    faces: np.ndarray
    class_id: int
    instance_id: int


def convex_solid(points: np.ndarray, class_id: int, instance_id: int) -> Solid:
    """The convex hull of ``points`` (N, 3) float64 (world, m) as a :class:`Solid`."""
    hull = ConvexHull(points)
    faces = hull.simplices.astype(np.int32).copy()
    verts = hull.points
    # ConvexHull does not orient simplices: flip those whose normal points inward.
    centroid = verts[hull.vertices].mean(axis=0)
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    n = np.cross(b - a, c - a)
    flip = np.einsum("ij,ij->i", n, a - centroid) < 0
    faces[flip] = faces[flip][:, ::-1]
    used = np.unique(faces)
    remap = np.full(len(verts), -1, dtype=np.int32)
    remap[used] = np.arange(len(used), dtype=np.int32)
    return Solid(
        vertices=verts[used].astype(np.float64),
        faces=remap[faces],
        planes=np.unique(np.round(hull.equations, 12), axis=0),
        class_id=int(class_id),
        instance_id=int(instance_id),
    )


def box_solid(center, size, yaw: float, class_id: int, instance_id: int) -> Solid:
    """A box: center (3,) m, size (l, w, h) m along its own x, y, z, rotated by yaw about z."""
    l, w, h = (float(v) for v in size)
    corners = np.array(
        [[sx * l / 2, sy * w / 2, sz * h / 2] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
    )
    return convex_solid(corners @ rot_z(yaw).T + np.asarray(center, float), class_id, instance_id)


def cylinder_solid(
    base, radius: float, height: float, class_id: int, instance_id: int, segments: int = 12
) -> Solid:
    """A vertical prism approximating a cylinder standing on ``base`` (3,) m."""
    ang = np.arange(segments) * 2 * np.pi / segments
    ring = np.stack([radius * np.cos(ang), radius * np.sin(ang), np.zeros(segments)], axis=1)
    pts = np.concatenate([ring, ring + [0.0, 0.0, height]]) + np.asarray(base, float)
    return convex_solid(pts, class_id, instance_id)


def ellipsoid_solid(
    center, radii, class_id: int, instance_id: int, rings: int = 6, segments: int = 10
) -> Solid:
    """A convex polyhedron approximating an axis-aligned ellipsoid (tree crowns)."""
    pts = [[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]
    for i in range(1, rings):
        th = np.pi * i / rings
        for j in range(segments):
            ph = 2 * np.pi * (j + 0.5 * (i % 2)) / segments
            pts.append([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])
    return convex_solid(
        np.asarray(pts) * np.asarray(radii, float) + np.asarray(center, float),
        class_id,
        instance_id,
    )


def ground_tile(
    x0: float, x1: float, y0: float, y1: float, z: float, class_id: int, instance_id: int = 0
) -> Surface:
    """A flat rectangle at height z (two triangles facing up)."""
    v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], dtype=np.float64)
    f = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)
    return Surface(v, f, int(class_id), int(instance_id))


def rotation_to_axis_angle(R: np.ndarray) -> np.ndarray:
    """(3,) axis-angle (rad) of a (3, 3) rotation matrix."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()


def sample_triangles(vertices: np.ndarray, faces: np.ndarray, spacing_m: float) -> np.ndarray:
    """Points covering every triangle with gaps below ``spacing_m``.

    vertices (V, 3) float, faces (F, 3) int -> (N, 3) float64 on the surface (vertices, edge and
    interior points of a regular barycentric subdivision of each triangle), same frame.
    """
    if len(faces) == 0:
        return np.zeros((0, 3))
    a = vertices[faces[:, 0]].astype(np.float64)
    b = vertices[faces[:, 1]].astype(np.float64)
    c = vertices[faces[:, 2]].astype(np.float64)
    longest = np.max(
        np.stack(
            [
                np.linalg.norm(b - a, axis=1),
                np.linalg.norm(c - b, axis=1),
                np.linalg.norm(a - c, axis=1),
            ]
        ),
        axis=0,
    )
    levels = np.maximum(1, np.ceil(longest / spacing_m).astype(np.int64))
    out = []
    for n in np.unique(levels):
        sel = levels == n
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        keep = i + j <= n
        u = (i[keep] / n)[None, :, None]
        v = (j[keep] / n)[None, :, None]
        pts = a[sel, None] + u * (b[sel, None] - a[sel, None]) + v * (c[sel, None] - a[sel, None])
        out.append(pts.reshape(-1, 3))
    return np.concatenate(out)
