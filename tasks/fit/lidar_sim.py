"""Synthetic Ouster-style LiDAR sweeps on body meshes (paper appendix C).

The virtual sensor sits at the camera centre; its frame is the project's ``lidar`` convention
(x forward = camera z, y left = -camera x, z up = -camera y), so ``T_cam_from_lidar`` is a pure
rotation (:data:`R_CAM_FROM_LIDAR`). Beams are spread uniformly over the vertical field of view,
columns uniformly over 360 deg; only rays whose direction projects inside the image are cast
(open3d RaycastingScene). Each return gets Gaussian range noise, Gaussian angular noise on the
measured direction, and random dropout; returns outside [min_range_m, max_range_m] are dropped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from tasks.body.params import BodyParams

#: Rotation taking lidar-frame vectors to the cam frame for a sensor at the camera centre.
R_CAM_FROM_LIDAR = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


@dataclass(frozen=True)
class LidarSpec:
    """Spinning LiDAR model. beams over vfov_deg (centred on the horizon), columns over 360 deg;
    range_noise_std_m, angle_noise_std_deg, dropout probability, valid range in metres."""

    beams: int
    columns: int
    vfov_deg: float = 45.0
    range_noise_std_m: float = 0.010
    angle_noise_std_deg: float = 0.01
    dropout: float = 0.10
    min_range_m: float = 0.5
    max_range_m: float = 90.0


SENSORS: dict[str, LidarSpec] = {
    "ouster-32": LidarSpec(32, 512),
    "ouster-64": LidarSpec(64, 1024),
    "ouster-128": LidarSpec(128, 2048),
}


def frustum_ray_directions(spec: LidarSpec, K, image_size: tuple[int, int]) -> np.ndarray:
    """Unit ray directions (R, 3) float64 in the cam frame of the sensor's rays inside the image.

    K (3, 3) intrinsics; image_size (width, height) pixels.
    """
    half = np.radians(spec.vfov_deg) / 2.0
    elev = np.linspace(-half, half, spec.beams)
    azim = np.arange(spec.columns) * (2.0 * np.pi / spec.columns)
    e, a = np.meshgrid(elev, azim, indexing="ij")
    d_lidar = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
    d = d_lidar @ R_CAM_FROM_LIDAR.T
    K = np.asarray(K, dtype=np.float64)
    front = d[:, 2] > 1e-6
    uv = (d[front] / d[front, 2:3]) @ K.T
    w, h = image_size
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    return d[front][inside]


def simulate_sweep(
    vertices, faces, directions, spec: LidarSpec, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Cast rays from the cam-frame origin at one mesh and return noisy hits.

    vertices (V, 3) cam frame (m); faces (F, 3) int; directions (R, 3) unit rays in the cam frame
    (from :func:`frustum_ray_directions`). Returns points_cam (N, 3) float32 and the hit face id
    per point (N,) int64.
    """
    scene = o3d.t.geometry.RaycastingScene()
    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(np.asarray(vertices, dtype=np.float32))
    mesh.triangle.indices = o3d.core.Tensor(np.asarray(faces, dtype=np.int32))
    scene.add_triangles(mesh)
    d = np.asarray(directions, dtype=np.float32)
    rays = np.concatenate([np.zeros_like(d), d], axis=1)
    ans = scene.cast_rays(o3d.core.Tensor(rays))
    t = ans["t_hit"].numpy().astype(np.float64)
    fid = ans["primitive_ids"].numpy().astype(np.int64)
    hit = np.isfinite(t)
    t, fid, dh = t[hit], fid[hit], d[hit].astype(np.float64)
    t = t + rng.normal(0.0, spec.range_noise_std_m, size=t.shape)
    # angular noise: small rotation of the measured direction, std per tangent axis
    sigma = np.radians(spec.angle_noise_std_deg)
    dn = dh + rng.normal(0.0, sigma, size=dh.shape)
    dn /= np.linalg.norm(dn, axis=1, keepdims=True)
    keep = (rng.random(t.shape) >= spec.dropout) & (t >= spec.min_range_m) & (t <= spec.max_range_m)
    pts = dn[keep] * t[keep, None]
    return pts.astype(np.float32), fid[keep]


# Limbs whose occlusion the benchmark simulates: COCO keypoints hidden and SMPL parts whose
# LiDAR returns an occluder blocks.
_LIMBS: tuple[tuple[tuple[int, ...], tuple[int, ...]], ...] = (
    ((7, 9), (18, 20, 22)),  # left forearm + hand
    ((8, 10), (19, 21, 23)),  # right forearm + hand
    ((13, 15), (4, 7, 10)),  # left shin + foot
    ((14, 16), (5, 8, 11)),  # right shin + foot
)


@dataclass(frozen=True)
class SyntheticPersons:
    """B simulated persons seen by one camera + co-located LiDAR. truth, truth_*: ground truth in
    the cam frame (body parameters, vertices (B, V, 3), joints (B, 24, 3)); keypoints (B, 17, 3) (u, v, conf) pixels; K (3, 3);
    points_lidar (B, P, 3) float32 padded, point_mask (B, P) bool; T_cam_from_lidar (4, 4);
    occluded_limb (B,) int (-1 none, else index into the limb table)."""

    truth: BodyParams
    truth_vertices: np.ndarray
    truth_joints: np.ndarray
    keypoints: np.ndarray
    K: np.ndarray
    points_lidar: np.ndarray
    point_mask: np.ndarray
    T_cam_from_lidar: np.ndarray
    occluded_limb: np.ndarray


def _yaw_upright(yaw: np.ndarray) -> np.ndarray:
    """Cam-frame global orientation of an upright person turned by yaw about the vertical."""
    c, s = np.cos(yaw), np.sin(yaw)
    Ry = np.zeros((len(yaw), 3, 3))
    Ry[:, 0, 0], Ry[:, 0, 2], Ry[:, 1, 1], Ry[:, 2, 0], Ry[:, 2, 2] = c, s, 1.0, -s, c
    return Ry @ np.diag([1.0, -1.0, -1.0])  # SMPL y-up template -> OpenCV y-down, facing camera


def synthesize_persons(
    model,
    body_pose: np.ndarray,
    spec: LidarSpec,
    rng: np.random.Generator,
    K=None,
    image_size: tuple[int, int] = (1920, 1080),
    distance_m: tuple[float, float] = (3.0, 12.0),
    camera_height_m: tuple[float, float] = (1.0, 1.6),
    betas_std: float = 1.0,
    keypoint_noise_px: float = 3.0,
    occlusion_prob: float = 0.2,
    max_points: int = 1024,
) -> SyntheticPersons:
    """Ground-truth bodies on a ground plane in front of the camera, their LiDAR sweeps and
    COCO-17 keypoints (paper appendix C). body_pose (B, 69) axis-angle poses to use; distances
    uniform in distance_m, random heading, random shape N(0, betas_std). With occlusion_prob one
    limb is occluded: its keypoints get low confidence and large noise, its LiDAR returns vanish.
    Sweeps with more than max_points returns are subsampled at random.
    """
    import torch

    from tasks.body.rotations import matrix_to_axis_angle
    from tasks.fit.optimize import model_keypoints  # noqa: PLC0415 (avoid a cycle at import)
    from tasks.fit.visibility import vertex_parts

    B = body_pose.shape[0]
    K = (
        np.array([[1000.0, 0, image_size[0] / 2], [0, 1000.0, image_size[1] / 2], [0, 0, 1]])
        if K is None
        else np.asarray(K, float)
    )
    betas = rng.normal(0.0, betas_std, (B, 10))
    yaw = rng.uniform(0.0, 2 * np.pi, B)
    Rg = _yaw_upright(yaw)
    go = matrix_to_axis_angle(torch.as_tensor(Rg)).numpy()
    with torch.no_grad():
        o = model(
            torch.as_tensor(betas, dtype=torch.float32),
            torch.as_tensor(go, dtype=torch.float32),
            torch.as_tensor(body_pose, dtype=torch.float32),
            torch.zeros(B, 3),
        )
    v0 = o.vertices.double().numpy()
    dist = rng.uniform(*distance_m, B)
    half_fov = np.arctan(image_size[0] / 2 / K[0, 0])
    az = rng.uniform(-0.7, 0.7, B) * half_fov
    h = rng.uniform(*camera_height_m, B)
    root = o.joints[:, 0].double().numpy()
    transl = np.stack(
        [dist * np.sin(az) - root[:, 0], h - v0[:, :, 1].max(1), dist * np.cos(az) - root[:, 2]], 1
    )
    verts = v0 + transl[:, None]
    joints = o.joints.double().numpy() + transl[:, None]
    kp3 = model_keypoints(
        torch.as_tensor(joints), torch.as_tensor(verts), model.keypoint_vertex_ids
    ).numpy()
    uvw = kp3 @ K.T
    uv = uvw[..., :2] / uvw[..., 2:3] + rng.normal(0.0, keypoint_noise_px, (B, 17, 2))
    conf = rng.uniform(0.75, 1.0, (B, 17))
    parts = vertex_parts(model.lbs_weights)
    faces = np.asarray(model.faces)
    face_part = parts[faces[:, 0]]
    dirs = frustum_ray_directions(spec, K, image_size)
    occluded = np.where(rng.random(B) < occlusion_prob, rng.integers(0, len(_LIMBS), B), -1)
    pts = np.zeros((B, max_points, 3), np.float32)
    mask = np.zeros((B, max_points), bool)
    for b in range(B):
        p, fid = simulate_sweep(verts[b], faces, dirs, spec, rng)
        if occluded[b] >= 0:
            kps, limb_parts = _LIMBS[occluded[b]]
            conf[b, list(kps)] = rng.uniform(0.05, 0.4, len(kps))
            uv[b, list(kps)] += rng.normal(0.0, 30.0, (len(kps), 2))
            p = p[~np.isin(face_part[fid], limb_parts)]
        if len(p) > max_points:
            p = p[rng.choice(len(p), max_points, replace=False)]
        p_lidar = p.astype(np.float64) @ R_CAM_FROM_LIDAR  # R^T p: cam -> lidar
        pts[b, : len(p)] = p_lidar
        mask[b, : len(p)] = True
    T = np.eye(4)
    T[:3, :3] = R_CAM_FROM_LIDAR
    f32 = np.float32
    return SyntheticPersons(
        BodyParams(
            betas.astype(f32), go.astype(f32), np.asarray(body_pose, f32), transl.astype(f32)
        ),
        verts.astype(f32),
        joints.astype(f32),
        np.concatenate([uv, conf[..., None]], -1).astype(f32),
        K,
        pts,
        mask,
        T,
        occluded,
    )
