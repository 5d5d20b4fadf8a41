"""Ray-cast sensors of the simulator: an Ouster OS1 LiDAR and a rectified stereo pair.

LiDAR noise follows the paper's appendix table (simulated Ouster sensors): range noise std
10 mm, angular noise std 0.01 deg, 10 % dropout, valid range [0.5, 90] m. The organised layout
is always 128 rows x 1024 columns (row 0 the top beam, column c at azimuth
pi - 2 pi (c + 0.5) / 1024, so column 512 looks forward); the os1-64 / os1-32 variants fire every
2nd / 4th row over the same 45 deg field and leave the other rows as no-return zeros.
The sweep is simulated from the frame's pose (no motion skew); the time channel holds each
column's firing offset within the 0.1 s sweep.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import open3d as o3d
import open3d.core as o3c

from tasks import conventions as C
from tasks.geometry import make_transform

ROWS, COLUMNS = 128, 1024
NUM_POINTS = ROWS * COLUMNS
VERTICAL_FOV_DEG = 45.0
ROW_STRIDE = {"os1-128": 1, "os1-64": 2, "os1-32": 4}

#: Per-class reflectivity in [0, 1] for the intensity channel (pedestrian .. vegetation).
REFLECTIVITY = np.array([0.35, 0.6, 0.45, 0.7, 0.2, 0.3, 0.6, 0.5, 0.4], dtype=np.float32)
#: Base albedo (RGB 0-1) per class for the shaded images.
ALBEDO = np.array(
    [
        [0.75, 0.35, 0.3],
        [0.5, 0.1, 0.1],
        [0.78, 0.74, 0.66],
        [0.5, 0.5, 0.52],
        [0.36, 0.36, 0.38],
        [0.35, 0.55, 0.25],
        [0.85, 0.85, 0.82],
        [0.15, 0.2, 0.45],
        [0.22, 0.45, 0.15],
    ],
    dtype=np.float32,
)
_SUN = np.array([0.45, 0.3, 0.84]) / np.linalg.norm([0.45, 0.3, 0.84])


@dataclass(frozen=True)
class LidarNoise:
    """range_std_m, angle_std_deg, dropout probability, min/max valid range (m)."""

    range_std_m: float = 0.010
    angle_std_deg: float = 0.01
    dropout: float = 0.10
    min_range_m: float = 0.5
    max_range_m: float = 90.0


@dataclass(frozen=True)
class CameraModel:
    """A rectified pinhole camera: K (3, 3) float64 px, width, height, T_cam_from_lidar (4, 4) of
    the rectified frame; images are rendered with these.

    The physical (raw) camera behind it, as a stereo calibration describes it: K_raw (3, 3) px,
    distortion (5,) plumb-bob, R_rect (3, 3) raw camera frame -> rectified frame. The raw camera's
    extrinsic is ``[[R_rect^T, 0], [0, 1]] @ T_cam_from_lidar`` and the projection matrix
    ``[K | p4]`` (p4 = -fx * baseline on the right camera). None: the camera is its own raw camera.
    """

    name: str
    K: np.ndarray
    width: int
    height: int
    T_cam_from_lidar: np.ndarray
    K_raw: np.ndarray | None = None
    distortion: np.ndarray | None = None
    R_rect: np.ndarray | None = None


@dataclass(frozen=True)
class SensorRig:
    """The robot's sensors. T_base_from_lidar (4, 4) float64; cameras cam0 (left), cam1 (right)."""

    sensor: str
    T_base_from_lidar: np.ndarray
    cameras: tuple[CameraModel, ...]
    noise: LidarNoise

    def camera(self, name: str) -> CameraModel:
        return next(c for c in self.cameras if c.name == name)


#: The raw cameras behind the rectified pair, CODa-like (its documented cam0 intrinsics are
#: fx 730.3, fy 729.7, cx 610.9, cy 537.7, k1..k3 -0.056 0.124 .. -0.064, a rectification of ~1
#: deg): raw intrinsics (fx, fy, cx, cy), plumb-bob distortion, and the rectification rotation
#: as a rotation vector (rad) per camera. They only reach the calibration files: the images are
#: rendered with the rectified pinhole, as a rectified download holds them.
RAW_CAMERAS = {
    "cam0": (
        (730.27, 729.71, 610.90, 537.72),
        (-0.0560, 0.1238, 0.00115, -0.00367, -0.0636),
        (0.0122, 0.0148, 0.0151),
    ),
    "cam1": (
        (731.64, 731.02, 614.21, 530.35),
        (-0.0532, 0.1181, 0.00092, 0.00121, -0.0597),
        (0.0105, 0.0137, 0.0083),
    ),
}


def make_rig(
    sensor: str = "os1-128",
    lidar_height_m: float = 0.9,
    width: int = 1224,
    height: int = 1024,
    focal_px: float = 730.0,
    baseline_m: float = 0.12,
    noise: LidarNoise = LidarNoise(),
    raw_cameras: bool = True,
    image_scale: float = 1.0,
) -> SensorRig:
    """The default rig: LiDAR ``lidar_height_m`` above the base origin, cameras 0.15 m below and
    0.08 m ahead of it, cam0 left of centre by half the baseline, cam1 right, both looking forward
    (these are the rectified frames). raw_cameras: attach the raw cameras of ``RAW_CAMERAS``
    (distorted, rotated by their rectification), else each camera is its own raw camera.
    image_scale: both cameras' images scaled by this factor (width, height rounded; focal
    lengths and the raw cameras' intrinsics scaled with them, pixel centres kept: a pixel (u, v)
    at scale 1 is at s (u + 0.5) - 0.5 after): the same field of view on fewer pixels."""
    from scipy.spatial.transform import Rotation

    if sensor not in ROW_STRIDE:
        raise ValueError(f"sensor must be one of {tuple(ROW_STRIDE)}, got {sensor!r}")
    if not 0.0 < image_scale <= 1.0:
        raise ValueError(f"image_scale must be in (0, 1], got {image_scale}")
    if image_scale != 1.0:
        width, height = int(round(width * image_scale)), int(round(height * image_scale))
        focal_px = focal_px * image_scale
    T_base_from_lidar = make_transform(np.eye(3), [0.0, 0.0, lidar_height_m])
    K = np.array([[focal_px, 0.0, (width - 1) / 2], [0.0, focal_px, (height - 1) / 2], [0, 0, 1.0]])
    R_cam_from_lidar = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    cams = []
    for name, y in (("cam0", baseline_m / 2), ("cam1", -baseline_m / 2)):
        centre_lidar = np.array([0.08, y, -0.15])
        raw = {}
        if raw_cameras:
            (fx, fy, cx, cy), dist, rotvec = RAW_CAMERAS[name]
            if image_scale != 1.0:
                fx, fy = fx * image_scale, fy * image_scale
                cx, cy = image_scale * (cx + 0.5) - 0.5, image_scale * (cy + 0.5) - 0.5
            raw = {
                "K_raw": np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]),
                "distortion": np.array(dist, dtype=np.float64),
                "R_rect": Rotation.from_rotvec(rotvec).as_matrix(),
            }
        cams.append(
            CameraModel(
                name,
                K,
                width,
                height,
                make_transform(R_cam_from_lidar, -R_cam_from_lidar @ centre_lidar),
                **raw,
            )
        )
    return SensorRig(sensor, T_base_from_lidar, tuple(cams), noise)


def coda_semantic_ids(point_class: np.ndarray) -> np.ndarray:
    """(N,) uint8 our class ids of a sweep -> (N,) uint8 CODa 3d_semantic ids, as CODa annotates:
    terrain only (the walkway Concrete, the lawn Grass), every other point Unlabeled (0)."""
    from tasks.metrics.coda_labels import CODA_SEMANTIC_IDS

    table = np.zeros(256, dtype=np.uint8)
    table[C.ROAD] = CODA_SEMANTIC_IDS["Concrete"]
    table[C.TERRAIN] = CODA_SEMANTIC_IDS["Grass"]
    return table[np.asarray(point_class, dtype=np.uint8)]


@functools.lru_cache(maxsize=1)
def lidar_directions() -> np.ndarray:
    """Unit beam directions (128, 1024, 3) float64 in the LiDAR frame (row 0 = top beam); one
    read-only array per process."""
    half = np.deg2rad(VERTICAL_FOV_DEG / 2)
    elev = np.linspace(half, -half, ROWS)
    az = np.pi - 2 * np.pi * (np.arange(COLUMNS) + 0.5) / COLUMNS
    ce, se = np.cos(elev)[:, None], np.sin(elev)[:, None]
    dirs = np.stack(
        [ce * np.cos(az)[None], ce * np.sin(az)[None], np.broadcast_to(se, (ROWS, COLUMNS))], -1
    )
    dirs.setflags(write=False)
    return dirs


@dataclass(frozen=True)
class MeshSet:
    """All triangles of one frame in the world frame, with per-triangle labels.

    vertices (V, 3) float32 world m; faces (F, 3) uint32; tri_class (F,) uint8; tri_instance (F,)
    uint16; tri_albedo (F, 3) float32 RGB 0-1.
    """

    vertices: np.ndarray
    faces: np.ndarray
    tri_class: np.ndarray
    tri_instance: np.ndarray
    tri_albedo: np.ndarray

    def raycasting_scene(self) -> o3d.t.geometry.RaycastingScene:
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3c.Tensor(self.vertices), o3c.Tensor(self.faces))
        return scene


@dataclass(frozen=True)
class LidarSweep:
    """An organised sweep (131072 points, row-major 128 x 1024), LiDAR frame.

    points (N, 3) float32 m (zeros for no return); intensity (N,) float32 in [0, 255];
    time_s (N,) float32 offset within the sweep; point_class (N,) uint8 (255 no return);
    point_instance (N,) uint16 (0 none).
    """

    points: np.ndarray
    intensity: np.ndarray
    time_s: np.ndarray
    point_class: np.ndarray
    point_instance: np.ndarray


def cast_lidar(
    scene: o3d.t.geometry.RaycastingScene,
    meshes: MeshSet,
    T_world_from_lidar: np.ndarray,
    sensor: str,
    noise: LidarNoise,
    rng: np.random.Generator,
) -> LidarSweep:
    """Ray-cast one sweep from ``T_world_from_lidar`` (4, 4) with the given noise (see module doc)."""
    dirs = lidar_directions().reshape(-1, 3)
    fired = np.zeros((ROWS, COLUMNS), dtype=bool)
    fired[:: ROW_STRIDE[sensor]] = True
    fired = fired.reshape(-1)
    # Angular noise: small random rotation of each beam (two orthogonal perturbations).
    sigma = np.deg2rad(noise.angle_std_deg)
    perturb = rng.normal(0.0, sigma, (NUM_POINTS, 3))
    dirs = dirs + np.cross(perturb, dirs)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    R, t = T_world_from_lidar[:3, :3], T_world_from_lidar[:3, 3]
    rays = np.concatenate([np.broadcast_to(t, dirs.shape), dirs @ R.T], axis=1).astype(np.float32)
    hit = scene.cast_rays(o3c.Tensor(rays))
    t_hit = hit["t_hit"].numpy().astype(np.float64)
    prim = hit["primitive_ids"].numpy().astype(np.int64)
    normals = hit["primitive_normals"].numpy().astype(np.float64)
    keep_prob = rng.random(NUM_POINTS)
    range_noise = rng.normal(0.0, noise.range_std_m, NUM_POINTS)
    ok = fired & np.isfinite(t_hit) & (t_hit >= noise.min_range_m) & (t_hit <= noise.max_range_m)
    ok &= keep_prob >= noise.dropout
    rng_m = np.where(ok, t_hit + range_noise, 0.0)
    points = (dirs * rng_m[:, None]).astype(np.float32)
    cls = np.full(NUM_POINTS, C.UNLABELED, dtype=np.uint8)
    inst = np.zeros(NUM_POINTS, dtype=np.uint16)
    cls[ok] = meshes.tri_class[prim[ok]]
    inst[ok] = meshes.tri_instance[prim[ok]]
    cos_inc = np.abs(np.einsum("ij,ij->i", normals, dirs @ R.T))
    intensity = np.zeros(NUM_POINTS, dtype=np.float32)
    intensity[ok] = 255.0 * REFLECTIVITY[cls[ok]] * (0.2 + 0.8 * cos_inc[ok])
    col = np.tile(np.arange(COLUMNS), ROWS)
    time_s = (col * (0.1 / COLUMNS)).astype(np.float32)
    return LidarSweep(points, intensity, time_s, cls, inst)


@dataclass(frozen=True)
class CameraRender:
    """One rendered rectified image (H, W): rgb uint8 (H, W, 3); class_id uint8 (our ids, 255 sky);
    instance uint16 (pedestrian track id, 0 none); depth float32 metres along the optical axis
    (inf for sky)."""

    rgb: np.ndarray
    class_id: np.ndarray
    instance: np.ndarray
    depth: np.ndarray

    @property
    def cityscapes(self) -> np.ndarray:
        """(H, W) uint8 Cityscapes train ids (255 sky / ignore)."""
        table = np.full(256, C.CITYSCAPES_IGNORE, dtype=np.uint8)
        table[: len(C.CLASS_TO_CITYSCAPES)] = C.CLASS_TO_CITYSCAPES
        return table[self.class_id]


def camera_rays(cam: CameraModel) -> np.ndarray:
    """(H * W, 3) float32 ray directions in the camera frame with unit z (pixel centres at integer
    (u, v), OpenCV convention), row-major over (v, u)."""
    u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    x = (u - cam.K[0, 2]) / cam.K[0, 0]
    y = (v - cam.K[1, 2]) / cam.K[1, 1]
    return np.stack([x, y, np.ones_like(x)], axis=-1).reshape(-1, 3).astype(np.float32)


class CameraRays:
    """One camera's rays, reused from frame to frame: the camera-frame directions, and the
    world-frame ray array (H * W, 6) float32 with each pixel's sky-gradient factor (H * W,)
    float32 for the last camera orientation seen. The simulated robot only translates, so the
    rotation, and with it everything but the ray origins, is computed once per sequence."""

    def __init__(self, cam: CameraModel):
        self.rays_cam = camera_rays(cam)
        self._R: bytes | None = None
        self._rays = np.empty((len(self.rays_cam), 6), dtype=np.float32)
        self._sky = np.empty(len(self.rays_cam), dtype=np.float32)

    def world(
        self, R_world_from_cam: np.ndarray, t_world_from_cam: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(rays (H * W, 6) float32 origin + direction, sky factor (H * W,)) in the world frame.
        The arrays are this object's buffers: valid until the next call."""
        key = np.asarray(R_world_from_cam, np.float64).tobytes()
        if key != self._R:
            d = self.rays_cam @ R_world_from_cam.T.astype(np.float32)
            self._rays[:, 3:] = d
            self._sky[:] = np.clip(d[:, 2] / np.linalg.norm(d, axis=1), 0.0, 1.0)
            self._R = key
        self._rays[:, :3] = t_world_from_cam
        return self._rays, self._sky


def render_camera(
    scene: o3d.t.geometry.RaycastingScene,
    meshes: MeshSet,
    cam: CameraModel,
    T_world_from_lidar: np.ndarray,
    night: bool,
    rays: CameraRays | None = None,
) -> CameraRender:
    """Render one rectified image: per-class albedo x Lambert shading, a sky gradient."""
    if rays is None:
        rays = CameraRays(cam)
    T_world_from_cam = T_world_from_lidar @ np.linalg.inv(cam.T_cam_from_lidar)
    H, W = cam.height, cam.width
    ray_array, sky_s = rays.world(T_world_from_cam[:3, :3], T_world_from_cam[:3, 3])
    hit = scene.cast_rays(o3c.Tensor(ray_array))
    t_hit = hit["t_hit"].numpy()
    ok = np.isfinite(t_hit)
    okn = np.flatnonzero(ok)
    prim = hit["primitive_ids"].numpy()[okn].astype(np.int64)
    n = hit["primitive_normals"].numpy()[okn]
    t_ok = t_hit[okn]
    d_ok = ray_array[okn, 3:]
    cls = np.full(H * W, C.UNLABELED, dtype=np.uint8)
    inst = np.zeros(H * W, dtype=np.uint16)
    cls_ok = meshes.tri_class[prim]
    cls[okn] = cls_ok
    inst[okn] = np.where(cls_ok == C.PEDESTRIAN, meshes.tri_instance[prim], 0)
    depth = np.full(H * W, np.inf, dtype=np.float32)
    depth[okn] = t_ok  # rays have unit z in the camera frame: t is the depth
    facing = np.einsum("ij,ij->i", n, d_ok) > 0
    lambert = np.abs(
        np.clip(
            np.where(facing, -1.0, 1.0).astype(np.float32) * (n @ _SUN.astype(np.float32)), 0, 1
        )
    )
    albedo = meshes.tri_albedo[prim]
    rgb = np.empty((H * W, 3), dtype=np.float32)
    sky_idx = np.flatnonzero(~ok)
    s = sky_s[sky_idx][:, None]
    if night:
        sky = (1 - s) * np.array([0.06, 0.07, 0.12], np.float32) + s * np.array(
            [0.01, 0.01, 0.04], np.float32
        )
        rgb[okn] = albedo * (0.12 + 0.2 * lambert[:, None]) * np.exp(-t_ok / 25.0)[:, None]
    else:
        haze = np.array([0.82, 0.88, 0.95], np.float32)
        sky = (1 - s) * haze + s * np.array([0.35, 0.55, 0.85], np.float32)
        fog = np.exp(-t_ok / 150.0)[:, None]
        rgb[okn] = albedo * (0.35 + 0.65 * lambert)[:, None] * fog + (1 - fog) * haze
    rgb[sky_idx] = sky
    rgb8 = np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8).reshape(H, W, 3)
    return CameraRender(rgb8, cls.reshape(H, W), inst.reshape(H, W), depth.reshape(H, W))
