"""Pure render kernels for figures: arrays in, RGB uint8 arrays out (no files, no matplotlib).

Bird's-eye views follow the grid convention of :mod:`tasks.conventions` ([x, y, z] voxels in
the base frame); in the picture x (forward) points up and y (left) points left.
"""

from __future__ import annotations

import numpy as np

from tasks import conventions as C
from tasks.geometry import transform_points


def instance_colors(ids: np.ndarray) -> np.ndarray:
    """(N,) integer ids -> (N, 3) uint8 colours for pedestrian instances: warm hues (magenta,
    red, orange, yellow, away from the blues of vehicles) and three brightness levels, a fixed
    hash of the id."""
    ids = np.asarray(ids, dtype=np.uint64)
    h = ((ids * np.uint64(2654435761)) >> np.uint64(4)) % np.uint64(1024)
    hue = (h.astype(np.float64) / 1024.0) * 150.0 - 90.0  # degrees in [-90, 60)
    level = np.array([1.0, 0.8, 0.6])[(ids % np.uint64(3)).astype(np.int64)]
    hue = np.mod(hue, 360.0) / 60.0
    x = 1.0 - np.abs(hue % 2.0 - 1.0)
    one, zero = np.ones_like(hue), np.zeros_like(hue)
    sector = hue.astype(np.int64) % 6
    rgb = np.select(
        [sector[:, None] == k for k in range(6)],
        [
            np.stack(c, axis=1)
            for c in (
                (one, x, zero),
                (x, one, zero),
                (zero, one, x),
                (zero, x, one),
                (x, zero, one),
                (one, zero, x),
            )
        ],
    )
    return (255 * rgb * level[:, None]).astype(np.uint8)


def bev_image(
    occupancy: np.ndarray,
    instance: np.ndarray | None = None,
    visible: np.ndarray | None = None,
    scale: int = 8,
) -> np.ndarray:
    """Top-down view of a semantic grid.

    occupancy (X, Y, Z) uint8 class ids (10 free); instance (X, Y, Z) uint16 pedestrian ids or
    None; visible (X, Y, Z) bool/uint8 observation mask or None (all known). Each column shows
    its highest occupied voxel (class colour, pedestrians per instance, darker when low), white
    when free, grey when no voxel of the column is visible. Returns (X*scale, Y*scale, 3) uint8.
    """
    X, Y, Z = occupancy.shape
    occ = (occupancy != C.FREE) & (occupancy != C.UNLABELED)
    if visible is not None:
        occ &= visible.astype(bool)
    has = occ.any(axis=2)
    top = Z - 1 - np.argmax(occ[:, :, ::-1], axis=2)  # highest occupied z per column
    xi, yi = np.meshgrid(np.arange(X), np.arange(Y), indexing="ij")
    cls = occupancy[xi, yi, top]
    img = np.empty((X, Y, 3), dtype=np.float64)
    img[:] = C.CLASS_COLORS[C.FREE]
    colors = C.CLASS_COLORS[np.minimum(cls, C.FREE)].astype(np.float64)
    if instance is not None:
        ids = instance[xi, yi, top]
        ped = has & (cls == C.PEDESTRIAN) & (ids > 0)
        colors[ped] = instance_colors(ids[ped])
    shade = 0.55 + 0.45 * (top + 1) / Z
    img[has] = colors[has] * shade[has, None]
    if visible is not None:
        unknown = ~visible.astype(bool).any(axis=2)
        img[unknown & ~has] = C.UNKNOWN_COLOR
    img = np.flip(img, axis=(0, 1))  # x up, y left
    img = np.repeat(np.repeat(img, scale, axis=0), scale, axis=1)
    return np.clip(img, 0, 255).astype(np.uint8)


def depth_colors(depth: np.ndarray, max_depth: float = 30.0) -> np.ndarray:
    """(N,) depths in metres -> (N, 3) uint8, near red through yellow and green to far blue."""
    return ramp_colors(np.asarray(depth, float) / max_depth, (0.5, 1.7, 3.2))


def ramp_colors(t: np.ndarray, centres: tuple[float, float, float]) -> np.ndarray:
    """(N,) values in [0, 1] (clipped) -> (N, 3) uint8: a "jet"-like ramp whose red, green and
    blue channels peak where 4 t equals their ``centres``."""
    t = np.clip(np.asarray(t, np.float64), 0.0, 1.0)
    rgb = [np.clip(1.5 - np.abs(4 * t - c), 0, 1) for c in centres]
    return (255 * np.stack(rgb, axis=1)).astype(np.uint8)


def bev_points(
    points_base: np.ndarray,
    range_min: np.ndarray,
    range_max: np.ndarray,
    voxel_size_m: float,
    scale: int = 8,
) -> np.ndarray:
    """Top-down view of a sweep with no labels (a robot log before the pipeline ran).

    points_base (N, 3) float32 base frame, metres; range_min / range_max (3,) the grid's bounds;
    columns of ``voxel_size_m`` holding returns take the colour of their highest return's height
    (the depth ramp over the grid's z range), the rest white. Same orientation as
    :func:`bev_image` (x up, y left). Returns (X*scale, Y*scale, 3) uint8."""
    lo, hi = np.asarray(range_min, np.float64), np.asarray(range_max, np.float64)
    X, Y = (np.round((hi[:2] - lo[:2]) / voxel_size_m)).astype(int)
    p = np.asarray(points_base, np.float64).reshape(-1, 3)
    ij = np.floor((p[:, :2] - lo[:2]) / voxel_size_m).astype(np.int64)
    keep = (ij[:, 0] >= 0) & (ij[:, 0] < X) & (ij[:, 1] >= 0) & (ij[:, 1] < Y)
    keep &= (p[:, 2] >= lo[2]) & (p[:, 2] < hi[2])
    top = np.full((X, Y), -np.inf)
    np.maximum.at(top, (ij[keep, 0], ij[keep, 1]), p[keep, 2])
    has = np.isfinite(top)
    img = np.empty((X, Y, 3), np.float64)
    img[:] = C.CLASS_COLORS[C.FREE]
    img[has] = depth_colors(top[has] - lo[2], max_depth=float(hi[2] - lo[2]))
    img = np.flip(img, axis=(0, 1))
    img = np.repeat(np.repeat(img, scale, axis=0), scale, axis=1)
    return np.clip(img, 0, 255).astype(np.uint8)


def draw_points(
    image: np.ndarray,
    points_lidar: np.ndarray,
    K: np.ndarray,
    T_cam_from_lidar: np.ndarray,
    max_depth: float = 30.0,
    radius: int = 1,
) -> np.ndarray:
    """Project LiDAR points onto an image, coloured by camera depth.

    image (H, W, 3) uint8; points_lidar (N, 3) float32 m (zeros = no return, skipped); K (3, 3);
    T_cam_from_lidar (4, 4). Far points are drawn first so near ones stay on top. Returns a copy.
    """
    out = image.copy()
    H, W = out.shape[:2]
    p = np.asarray(points_lidar, np.float64)
    p = p[np.any(p != 0, axis=1)]
    pc = transform_points(T_cam_from_lidar, p)
    pc = pc[pc[:, 2] > 0.1]
    u = np.rint(pc[:, 0] / pc[:, 2] * K[0, 0] + K[0, 2]).astype(np.int64)
    v = np.rint(pc[:, 1] / pc[:, 2] * K[1, 1] + K[1, 2]).astype(np.int64)
    order = np.argsort(-pc[:, 2], kind="stable")
    u, v, z = u[order], v[order], pc[order, 2]
    col = depth_colors(z, max_depth)
    for du in range(-radius + 1, radius):
        for dv in range(-radius + 1, radius):
            uu, vv = u + du, v + dv
            ok = (uu >= 0) & (uu < W) & (vv >= 0) & (vv < H)
            out[vv[ok], uu[ok]] = col[ok]
    return out


def resize_nearest(image: np.ndarray, height: int) -> np.ndarray:
    """Nearest-neighbour resize of (H, W, 3) uint8 to the given height (aspect kept)."""
    H, W = image.shape[:2]
    width = max(1, int(round(W * height / H)))
    rows = np.minimum((np.arange(height) + 0.5) * H / height, H - 1).astype(np.int64)
    cols = np.minimum((np.arange(width) + 0.5) * W / width, W - 1).astype(np.int64)
    return image[rows][:, cols]


def side_by_side(images: list[np.ndarray], height: int, gap: int = 8) -> np.ndarray:
    """Resize each (H, W, 3) uint8 image to ``height`` and place them left to right on white."""
    parts = [resize_nearest(im, height) for im in images]
    width = sum(p.shape[1] for p in parts) + gap * (len(parts) - 1)
    out = np.full((height, width, 3), 255, dtype=np.uint8)
    x = 0
    for p in parts:
        out[:, x : x + p.shape[1]] = p
        x += p.shape[1] + gap
    return out
