"""Synthetic LiDAR scans for tests and benchmarks: an OS1-128-like beam pattern ray cast into
triangle meshes with open3d. All geometry in metres; frames as named."""

from __future__ import annotations

import numpy as np
import open3d as o3d


def os1_directions(n_beams: int = 128, n_columns: int = 1024, vfov_deg: float = 45.0) -> np.ndarray:
    """Unit ray directions (n_beams * n_columns, 3) float32 in the LiDAR frame (x forward, y left,
    z up): beams evenly spaced over +-vfov/2 elevation, columns over 360 deg azimuth."""
    elev = np.deg2rad(np.linspace(vfov_deg / 2, -vfov_deg / 2, n_beams))
    azim = np.linspace(0.0, 2 * np.pi, n_columns, endpoint=False)
    e, a = np.meshgrid(elev, azim, indexing="ij")
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=-1)
    return d.reshape(-1, 3).astype(np.float32)


def box_mesh(center, size, yaw: float = 0.0) -> o3d.geometry.TriangleMesh:
    """A closed box mesh: center (3,) m, size (3,) m (x, y, z extents), yaw rad about z."""
    m = o3d.geometry.TriangleMesh.create_box(*[float(s) for s in size])
    m.translate(-np.asarray(size, dtype=np.float64) / 2)
    c, s = np.cos(yaw), np.sin(yaw)
    m.rotate(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]), center=np.zeros(3))
    m.translate(np.asarray(center, dtype=np.float64))
    return m


def build_scene(meshes: list) -> o3d.t.geometry.RaycastingScene:
    """An open3d ray-casting scene of the meshes (to cast many scans into one scene)."""
    scene = o3d.t.geometry.RaycastingScene()
    for m in meshes:
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m))
    return scene


def raycast(
    meshes, origin: np.ndarray, directions: np.ndarray, sensor_range_m: float = np.inf
) -> tuple[np.ndarray, np.ndarray]:
    """Cast rays from ``origin`` (3,) along ``directions`` (N, 3) into the meshes (same frame; a
    list of meshes or a :func:`build_scene`).

    Returns (points (M, 3) float32 hit points, ray_index (M,) int64) for the rays that hit within
    ``sensor_range_m``.
    """
    scene = build_scene(meshes) if isinstance(meshes, (list, tuple)) else meshes
    d = np.asarray(directions, dtype=np.float32)
    rays = np.concatenate([np.broadcast_to(np.asarray(origin, np.float32), d.shape), d], axis=1)
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    ok = np.isfinite(t) & (t <= sensor_range_m)
    idx = np.nonzero(ok)[0]
    return (rays[idx, :3] + d[idx] * t[idx, None]).astype(np.float32), idx


def room_scene(seed: int = 0, n_boxes: int = 6) -> list:
    """A 24 x 16 x 4 m closed room (floor at z = 0) with ``n_boxes`` seeded boxes on the floor."""
    rng = np.random.default_rng(seed)
    meshes = [
        box_mesh((0.0, 0.0, -0.1), (24.0, 16.0, 0.2)),  # floor
        box_mesh((0.0, 0.0, 4.1), (24.0, 16.0, 0.2)),  # ceiling
        box_mesh((12.1, 0.0, 2.0), (0.2, 16.0, 4.0)),
        box_mesh((-12.1, 0.0, 2.0), (0.2, 16.0, 4.0)),
        box_mesh((0.0, 8.1, 2.0), (24.0, 0.2, 4.0)),
        box_mesh((0.0, -8.1, 2.0), (24.0, 0.2, 4.0)),
    ]
    for _ in range(n_boxes):
        size = rng.uniform([0.4, 0.4, 0.5], [2.0, 2.0, 2.5])
        c = rng.uniform([-10, -6.5], [10, 6.5])
        meshes.append(box_mesh((c[0], c[1], size[2] / 2), size, rng.uniform(0, np.pi)))
    return meshes


def campus_scene(seed: int = 0, n_boxes: int = 40) -> list:
    """An open campus-like scene: a 120 x 120 m ground plane (top at z = 0), buildings 15-40 m away
    and ``n_boxes`` seeded boxes / poles (0.2-3 m) within 25 m of the origin."""
    rng = np.random.default_rng(seed)
    meshes = [box_mesh((0.0, 0.0, -0.1), (120.0, 120.0, 0.2))]
    for ang in np.linspace(0, 2 * np.pi, 9, endpoint=False):
        r = rng.uniform(15, 40)
        size = rng.uniform([8, 8, 6], [25, 25, 20])
        c = r * np.array([np.cos(ang), np.sin(ang)]) * (1 + size[:2].max() / (2 * r))
        meshes.append(box_mesh((c[0], c[1], size[2] / 2), size, ang))
    for _ in range(n_boxes):
        size = rng.uniform([0.2, 0.2, 0.5], [3.0, 3.0, 3.0])
        r, a = rng.uniform(2.5, 25), rng.uniform(0, 2 * np.pi)
        meshes.append(
            box_mesh((r * np.cos(a), r * np.sin(a), size[2] / 2), size, rng.uniform(0, np.pi))
        )
    return meshes


def campus_strip(length_m: float, seed: int = 0, reach_m: float = 140.0) -> list:
    """A campus-like scene along a straight walk of ``length_m`` along +x from the origin, with the
    same density everywhere (long drives for memory benchmarks): a ground plane (top at z = 0)
    reaching ``reach_m`` beyond the walk, buildings (6-20 m high) every ~35 m on both sides 12-45 m
    from the path, and boxes / poles (0.2-3 m) every ~1.5 m within 2.5-30 m of it. Seeded by
    position, so a longer strip is a shorter one extended."""
    meshes = [box_mesh(((length_m) / 2, 0.0, -0.1), (length_m + 2 * reach_m, 2 * reach_m, 0.2))]
    for k in range(int(np.floor(-reach_m / 35.0)), int(np.ceil((length_m + reach_m) / 35.0)) + 1):
        rng = np.random.default_rng([seed, 1, k + 1_000_000])
        for side in (-1, 1):
            size = rng.uniform([8, 8, 6], [25, 25, 20])
            y = side * (rng.uniform(12, 45) + size[1] / 2)
            meshes.append(
                box_mesh(
                    (35.0 * k + rng.uniform(-5, 5), y, size[2] / 2), size, rng.uniform(-0.3, 0.3)
                )
            )
    for k in range(int(np.floor(-30 / 1.5)), int(np.ceil((length_m + 30) / 1.5)) + 1):
        rng = np.random.default_rng([seed, 2, k + 1_000_000])
        size = rng.uniform([0.2, 0.2, 0.5], [3.0, 3.0, 3.0])
        y = rng.choice([-1, 1]) * rng.uniform(2.5, 30)
        meshes.append(
            box_mesh(
                (1.5 * k + rng.uniform(-0.7, 0.7), y, size[2] / 2), size, rng.uniform(0, np.pi)
            )
        )
    return meshes


def strip_poses(frames: int, step_m: float, lidar_height_m: float) -> np.ndarray:
    """(frames, 4, 4) float64 T_world_from_lidar of a walk along +x at step_m per frame (1 m/s at
    5 Hz), weaving +-0.5 m sideways with a matching small heading, LiDAR lidar_height_m up."""
    s = np.arange(frames) * step_m
    y = 0.5 * np.sin(s / 15.0)
    yaw = np.arctan2(0.5 / 15.0 * np.cos(s / 15.0), 1.0)
    T = np.tile(np.eye(4), (frames, 1, 1))
    T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = (
        np.cos(yaw),
        -np.sin(yaw),
        np.sin(yaw),
        np.cos(yaw),
    )
    T[:, 0, 3], T[:, 1, 3], T[:, 2, 3] = s, y, lidar_height_m
    return T


def organised_sweep(
    scene, T_world_from_lidar: np.ndarray, directions: np.ndarray, max_range_m: float
) -> np.ndarray:
    """(len(directions), 3) float32 LiDAR-frame returns of a scene (meshes or :func:`build_scene`)
    seen from a pose, in beam order, zeros where a ray hits nothing within max_range_m (an
    organised OS1 sweep)."""
    R, t = T_world_from_lidar[:3, :3], T_world_from_lidar[:3, 3]
    d_world = (np.asarray(directions, np.float64) @ R.T).astype(np.float32)
    pts, idx = raycast(scene, t, d_world, max_range_m)
    out = np.zeros((len(directions), 3), np.float32)
    out[idx] = ((pts.astype(np.float64) - t) @ R).astype(np.float32)
    return out
