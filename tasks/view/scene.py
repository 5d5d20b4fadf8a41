"""The scene of one frame as plain arrays: voxel layers, boxes, velocity arrows, LiDAR points and
the camera. flows/viewer/ hands these to the viewer library; nothing here knows it.

Everything is in the ``base`` frame of the frame (tasks.conventions), metres; colours are (N, 3)
uint8 RGB. Voxel grids are ``[x, y, z]``; the centre of voxel i is
``range_min + (i + 0.5) * voxel_size_m``.

Fine grids: a viewer holds every drawn voxel in the page, so a layer keeps only **surface**
voxels (a 6-neighbour not in the layer: the others cannot be seen from outside) and, when more
than ``max_voxels`` remain, merges them into blocks of ``b x b x b`` voxels (b = 2, 3, ... the
smallest that fits), each block taking the most frequent code of its voxels and drawn at ``b``
times the voxel size. A 0.02 m grid thus shows as a coarser one rather than freezing the page;
:class:`VoxelLayer` says what was kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tasks import conventions as C
from tasks.geometry import transform_points
from tasks.metrics.bev import (
    DIFF_COLORS,
    DIFF_CORRECT,
    DIFF_EXTRA,
    DIFF_FREE,
    DIFF_MISSED,
    DIFF_UNKNOWN,
    DIFF_WRONG_CLASS,
)
from tasks.perception.types import box_corners
from tasks.viz import ramp_colors

#: at most this many voxels (or blocks) per layer by default: ~200k instanced cubes or points
#: draw smoothly in a software-rendered browser (measured: flows/bench/viewer.py)
MAX_VOXELS = 200_000


class SceneError(ValueError):
    """Arrays that do not describe a frame (shape or dtype), naming the array and the value."""


@dataclass(frozen=True)
class VoxelLayer:
    """Voxels (or blocks of voxels) to draw as cubes.

    centers (N, 3) float32 m, base frame; colors (N, 3) uint8; codes (N,) uint8 (class ids, or
    DIFF_* codes for a difference layer); size_m: edge of each cube drawn (block x voxel size);
    selected: voxels the layer holds; surface: those of them with an exposed face; block: the
    decimation factor b (1: every surface voxel drawn).
    """

    centers: np.ndarray
    colors: np.ndarray
    codes: np.ndarray
    size_m: float
    selected: int
    surface: int
    block: int

    def __len__(self) -> int:
        return int(self.centers.shape[0])


def _grid(name: str, a, ndim: int = 3) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != ndim or min(a.shape[:3]) < 1:
        raise SceneError(f"{name}: expected a non-empty {ndim}-D grid, got shape {a.shape}")
    return a


def surface_voxels(keep: np.ndarray, border_exposed: bool = True) -> np.ndarray:
    """(X, Y, Z) bool: voxels of ``keep`` with at least one of their 6 face neighbours not in
    ``keep``. border_exposed: a face on the grid's border counts as exposed (True for occupied
    voxels, seen from outside the grid; False for a region such as unknown space that the border
    cuts, whose cut faces are not a surface)."""
    keep = _grid("keep", keep).astype(bool, copy=False)
    hidden = keep.copy()
    for axis in range(3):
        n = keep.shape[axis]
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[axis], hi[axis] = slice(0, n - 1), slice(1, n)
        lo, hi = tuple(lo), tuple(hi)
        hidden[lo] &= keep[hi]  # neighbour at +1
        hidden[hi] &= keep[lo]  # neighbour at -1
        if border_exposed:
            first = [slice(None)] * 3
            last = [slice(None)] * 3
            first[axis], last[axis] = 0, n - 1
            hidden[tuple(first)] = False
            hidden[tuple(last)] = False
    return keep & ~hidden


def _pack(index: np.ndarray, dims: np.ndarray) -> np.ndarray:
    return (index[:, 0] * dims[1] + index[:, 1]) * dims[2] + index[:, 2]


def merge_blocks(
    index: np.ndarray, codes: np.ndarray, block: int, grid_shape: tuple[int, int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Voxels (N, 3) int index with (N,) uint8 codes -> blocks of ``block``^3 voxels: (M, 3) block
    index (voxel index // block), ascending, and (M,) the most frequent code in each block (ties:
    the lowest code)."""
    index = np.asarray(index, np.int64).reshape(-1, 3)
    codes = np.asarray(codes, np.uint8).reshape(-1)
    if block <= 1 or index.shape[0] == 0:
        return index, codes
    dims = -(-np.asarray(grid_shape, np.int64) // block)
    keys = _pack(index // block, dims) * 256 + codes
    uniq, counts = np.unique(keys, return_counts=True)
    blk, code = uniq // 256, (uniq % 256).astype(np.uint8)
    order = np.lexsort((code, -counts, blk))  # per block: most voxels first, then lowest code
    blk_sorted = blk[order]
    first = np.r_[True, blk_sorted[1:] != blk_sorted[:-1]]
    pick = order[first]
    b = blk[pick]
    out = np.stack([b // (dims[1] * dims[2]), (b // dims[2]) % dims[1], b % dims[2]], axis=1)
    return out, code[pick]


def select_voxels(
    codes: np.ndarray,
    keep: np.ndarray,
    range_min,
    voxel_size_m: float,
    palette: np.ndarray,
    surface_only: bool = True,
    max_voxels: int = MAX_VOXELS,
    border_exposed: bool = True,
) -> VoxelLayer:
    """The voxels of ``keep`` (X, Y, Z) bool as a layer coloured by ``palette[codes]`` (codes
    (X, Y, Z) uint8, palette (K, 3) uint8): surface voxels only (``surface_only``), merged into
    blocks while more than ``max_voxels`` remain (module docstring)."""
    codes = _grid("codes", codes)
    keep = _grid("keep", keep).astype(bool, copy=False)
    if keep.shape != codes.shape:
        raise SceneError(f"keep has shape {keep.shape}, codes {codes.shape}")
    if max_voxels < 1:
        raise SceneError(f"max_voxels must be >= 1, got {max_voxels}")
    selected = int(np.count_nonzero(keep))
    shown = surface_voxels(keep, border_exposed) if surface_only else keep
    index = np.argwhere(shown)
    layer_codes = codes[shown]
    block = 1
    if index.shape[0] > max_voxels:
        full_index, full_codes = index, layer_codes
        # a surface of n voxels merges into ~n / b^2 blocks: start just below that estimate
        block = max(1, int(np.sqrt(index.shape[0] / max_voxels)))
        while index.shape[0] > max_voxels:
            block += 1
            index, layer_codes = merge_blocks(full_index, full_codes, block, codes.shape)
    size = float(voxel_size_m) * block
    centers = np.asarray(range_min, np.float64) + (index + 0.5) * size
    palette = np.asarray(palette, np.uint8)
    return VoxelLayer(
        centers=centers.astype(np.float32),
        colors=palette[np.minimum(layer_codes, len(palette) - 1)],
        codes=layer_codes.astype(np.uint8),
        size_m=size,
        selected=selected,
        surface=int(np.count_nonzero(shown)),
        block=block,
    )


def occupied(semantics: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """(X, Y, Z) bool: voxels holding a class 0..8 (and inside ``mask`` when one is given)."""
    semantics = _grid("semantics", semantics)
    occ = semantics < C.FREE
    if mask is not None:
        mask = _grid("mask", mask)
        if mask.shape != semantics.shape:
            raise SceneError(f"mask has shape {mask.shape}, semantics {semantics.shape}")
        occ &= mask.astype(bool, copy=False)
    return occ


def class_layer(
    semantics: np.ndarray,
    range_min,
    voxel_size_m: float,
    mask: np.ndarray | None = None,
    surface_only: bool = True,
    max_voxels: int = MAX_VOXELS,
) -> VoxelLayer:
    """Occupied voxels in the class colours (tasks.conventions.CLASS_COLORS).

    semantics (X, Y, Z) uint8 class ids (10 free); mask (X, Y, Z) uint8/bool: only voxels where it
    is 1 (mask_camera or mask_lidar: what a network trained with that mask is scored on), or
    None for every occupied voxel."""
    return select_voxels(
        semantics,
        occupied(semantics, mask),
        range_min,
        voxel_size_m,
        C.CLASS_COLORS,
        surface_only,
        max_voxels,
    )


def unknown_layer(
    semantics: np.ndarray,
    mask: np.ndarray,
    range_min,
    voxel_size_m: float,
    max_voxels: int = MAX_VOXELS,
) -> VoxelLayer:
    """Unknown space (mask == 0 and not occupied) as grey voxels: the surface of the unknown
    region where it meets observed space (the grid's border is not a surface of it)."""
    semantics, mask = _grid("semantics", semantics), _grid("mask", mask)
    if mask.shape != semantics.shape:
        raise SceneError(f"mask has shape {mask.shape}, semantics {semantics.shape}")
    keep = ~mask.astype(bool) & (semantics >= C.FREE)
    return select_voxels(
        np.zeros(semantics.shape, np.uint8),
        keep,
        range_min,
        voxel_size_m,
        C.UNKNOWN_COLOR[None, :],
        True,
        max_voxels,
        border_exposed=False,
    )


def difference_codes(
    pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None
) -> np.ndarray:
    """Voxel by voxel comparison of two class grids, the codes of the report's BEV difference
    (tasks.metrics.bev): correct (both occupied, same class), wrong class (both occupied, classes
    differ), missed (ground truth occupied, prediction free), extra (prediction occupied, ground
    truth free), free in both; unknown where ``mask`` is 0. pred, gt (X, Y, Z) uint8; mask (X, Y,
    Z) or None. Returns (X, Y, Z) uint8."""
    pred, gt = _grid("pred", pred), _grid("gt", gt)
    if pred.shape != gt.shape:
        raise SceneError(f"prediction grid {pred.shape} differs from the ground truth's {gt.shape}")
    p, g = pred < C.FREE, gt < C.FREE
    out = np.full(gt.shape, DIFF_FREE, np.uint8)
    out[p & g] = DIFF_CORRECT
    out[p & g & (pred != gt)] = DIFF_WRONG_CLASS
    out[g & ~p] = DIFF_MISSED
    out[p & ~g] = DIFF_EXTRA
    if mask is not None:
        mask = _grid("mask", mask)
        if mask.shape != gt.shape:
            raise SceneError(f"mask has shape {mask.shape}, grids {gt.shape}")
        out[~mask.astype(bool)] = DIFF_UNKNOWN
    return out


def difference_layer(
    pred: np.ndarray,
    gt: np.ndarray,
    range_min,
    voxel_size_m: float,
    mask: np.ndarray | None = None,
    max_voxels: int = MAX_VOXELS,
) -> VoxelLayer:
    """Voxels occupied in either grid, coloured by :func:`difference_codes` (DIFF_COLORS)."""
    codes = difference_codes(pred, gt, mask)
    keep = np.isin(codes, (DIFF_CORRECT, DIFF_WRONG_CLASS, DIFF_MISSED, DIFF_EXTRA))
    return select_voxels(codes, keep, range_min, voxel_size_m, DIFF_COLORS, True, max_voxels)


# ---- people -------------------------------------------------------------------------------------


#: corner pairs of a box's 12 edges, in the corner order of tasks.perception.types.box_corners
#: (corner 4 * ix + 2 * iy + iz: an edge joins two corners that differ in one axis)
BOX_EDGES = np.array(
    [[0, 1], [2, 3], [4, 5], [6, 7], [0, 2], [1, 3], [4, 6], [5, 7], [0, 4], [1, 5], [2, 6], [3, 7]]
)


def box_segments(center: np.ndarray, size: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """(B * 12, 2, 3) float32 line segments of upright boxes' edges. center (B, 3) m; size (B, 3)
    = (l, w, h), l along the heading; yaw (B,) rad about z."""
    center = np.asarray(center, np.float64).reshape(-1, 3)
    size = np.asarray(size, np.float64).reshape(-1, 3)
    yaw = np.asarray(yaw, np.float64).reshape(-1)
    if not len(center) == len(size) == len(yaw):
        raise SceneError(f"boxes: {len(center)} centres, {len(size)} sizes, {len(yaw)} yaws")
    corners = box_corners(center, size, yaw)
    return corners[:, BOX_EDGES].reshape(-1, 2, 3).astype(np.float32)


def velocity_arrows(
    semantics: np.ndarray,
    velocity: np.ndarray,
    range_min,
    voxel_size_m: float,
    seconds: float = 0.5,
    min_speed_mps: float = 0.05,
    arrow_spacing_m: float = 0.2,
) -> tuple[np.ndarray, np.ndarray]:
    """Arrows of pedestrian voxel velocities: where each voxel will be ``seconds`` later.

    semantics (X, Y, Z) uint8; velocity (X, Y, Z, 2) (vx, vy) m/s base frame (the store's
    ``velocity``). On grids finer than ``arrow_spacing_m`` the pedestrian voxels of each block of
    that size share one arrow (their mean position and velocity), so a 0.02 m grid is not a
    forest. Voxels slower than ``min_speed_mps`` get none. Returns (N, 2, 3) float32 start / end
    points and (N,) float32 speeds (m/s)."""
    semantics = _grid("semantics", semantics)
    velocity = np.asarray(velocity)
    if velocity.shape != (*semantics.shape, 2):
        raise SceneError(f"velocity has shape {velocity.shape}, expected {(*semantics.shape, 2)}")
    ped = semantics == C.PEDESTRIAN
    index = np.argwhere(ped)
    vel = velocity[ped].astype(np.float64)
    if index.shape[0] == 0:
        return np.zeros((0, 2, 3), np.float32), np.zeros(0, np.float32)
    block = max(1, int(round(arrow_spacing_m / voxel_size_m)))
    pos = np.asarray(range_min, np.float64) + (index + 0.5) * voxel_size_m
    if block > 1:
        dims = -(-np.asarray(semantics.shape, np.int64) // block)
        keys = _pack(index // block, dims)
        uniq, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
        pos = np.stack([np.bincount(inverse, pos[:, k]) for k in range(3)], 1) / counts[:, None]
        vel = np.stack([np.bincount(inverse, vel[:, k]) for k in range(2)], 1) / counts[:, None]
    speed = np.linalg.norm(vel, axis=1)
    moving = speed >= min_speed_mps
    start = pos[moving]
    end = start.copy()
    end[:, :2] += vel[moving] * seconds
    return np.stack([start, end], axis=1).astype(np.float32), speed[moving].astype(np.float32)


# ---- sensors ------------------------------------------------------------------------------------


def height_colors(z: np.ndarray, z_min: float = -1.0, z_max: float = 3.0) -> np.ndarray:
    """(N,) heights m -> (N, 3) uint8, low dark blue through cyan and yellow to high red."""
    return ramp_colors((np.asarray(z, np.float64) - z_min) / (z_max - z_min), (3.0, 2.0, 1.0))


def lidar_points(
    points_lidar: np.ndarray,
    T_base_from_lidar: np.ndarray,
    max_points: int = 60_000,
    box_min=None,
    box_max=None,
) -> tuple[np.ndarray, np.ndarray]:
    """A sweep (N, 3) float32 m, LiDAR frame (all-zero rows = no return, dropped) -> its points in
    the base frame inside [box_min, box_max] (3,) m when given (the grid and its surroundings:
    a sweep reaches 100 m and would hide the grid), thinned to every k-th point (at most
    ``max_points``, k the smallest that fits: deterministic, keeps the ring structure), and their
    height colours. Returns (M, 3) float32, (M, 3) uint8."""
    p = np.asarray(points_lidar, np.float32).reshape(-1, 3)
    p = p[np.any(p != 0, axis=1)]
    base = transform_points(T_base_from_lidar, p)
    if box_min is not None and box_max is not None:
        base = base[np.all((base >= box_min) & (base <= box_max), axis=1)]
    step = max(1, -(-base.shape[0] // max(1, int(max_points))))
    base = base[::step].astype(np.float32)
    return base, height_colors(base[:, 2])


def quat_wxyz(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> (4,) float64 unit quaternion (w, x, y, z), w >= 0."""
    R = np.asarray(R, np.float64)
    w = np.sqrt(max(0.0, 1.0 + R[0, 0] + R[1, 1] + R[2, 2])) / 2.0
    x = np.sqrt(max(0.0, 1.0 + R[0, 0] - R[1, 1] - R[2, 2])) / 2.0
    y = np.sqrt(max(0.0, 1.0 - R[0, 0] + R[1, 1] - R[2, 2])) / 2.0
    z = np.sqrt(max(0.0, 1.0 - R[0, 0] - R[1, 1] + R[2, 2])) / 2.0
    x = np.copysign(x, R[2, 1] - R[1, 2])
    y = np.copysign(y, R[0, 2] - R[2, 0])
    z = np.copysign(z, R[1, 0] - R[0, 1])
    q = np.array([w, x, y, z])
    return q / np.linalg.norm(q)


@dataclass(frozen=True)
class CameraView:
    """Where the camera and its image stand in the base frame.

    fov_y: vertical field of view, rad; aspect: width / height; wxyz (4,), position (3,): the
    camera's orientation and centre (OpenCV axes: x right, y down, z forward); the image is a
    plane at ``depth_m`` in front of it (z_cam = depth_m), centred at ``image_center`` (3,) base
    frame, ``image_size_m`` (width, height) m, pixel (u, v) at camera point
    ((u - cx) / fx * d, (v - cy) / fy * d, d).
    """

    fov_y: float
    aspect: float
    wxyz: np.ndarray
    position: np.ndarray
    depth_m: float
    image_center: np.ndarray
    image_size_m: tuple[float, float]


def camera_view(
    K: np.ndarray, width: int, height: int, T_base_from_cam: np.ndarray, depth_m: float = 0.8
) -> CameraView:
    """The camera of intrinsics K (3, 3) px and image size width x height px, at pose
    T_base_from_cam (4, 4), with its image drawn ``depth_m`` in front of it."""
    K = np.asarray(K, np.float64)
    T = np.asarray(T_base_from_cam, np.float64)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if not (fx > 0 and fy > 0 and width > 0 and height > 0 and depth_m > 0):
        raise SceneError(f"camera: fx {fx}, fy {fy}, size {width}x{height}, depth {depth_m}")
    center_cam = np.array(
        [(width / 2 - cx) / fx * depth_m, (height / 2 - cy) / fy * depth_m, depth_m]
    )
    return CameraView(
        fov_y=float(2 * np.arctan(height / (2 * fy))),
        aspect=float(width * fy / (height * fx)),
        wxyz=quat_wxyz(T[:3, :3]),
        position=T[:3, 3].copy(),
        depth_m=float(depth_m),
        image_center=T[:3, :3] @ center_cam + T[:3, 3],
        image_size_m=(float(width / fx * depth_m), float(height / fy * depth_m)),
    )


def pixel_from_ray(
    ray_origin: np.ndarray,
    ray_direction: np.ndarray,
    K: np.ndarray,
    T_base_from_cam: np.ndarray,
    depth_m: float,
) -> tuple[float, float] | None:
    """The image pixel (u, v) a click ray hits on the camera's image plane (z_cam = depth_m, as
    :func:`camera_view` draws it); None when the ray runs parallel to the plane or away from it.
    ray_origin, ray_direction (3,) base frame."""
    T_cam_from_base = np.linalg.inv(np.asarray(T_base_from_cam, np.float64))
    o = T_cam_from_base[:3, :3] @ np.asarray(ray_origin, np.float64) + T_cam_from_base[:3, 3]
    d = T_cam_from_base[:3, :3] @ np.asarray(ray_direction, np.float64)
    if abs(d[2]) < 1e-12:
        return None
    t = (depth_m - o[2]) / d[2]
    if t < 0:
        return None
    p = o + t * d
    K = np.asarray(K, np.float64)
    return float(K[0, 0] * p[0] / p[2] + K[0, 2]), float(K[1, 1] * p[1] / p[2] + K[1, 2])


def draw_boxes_2d(
    image: np.ndarray, boxes_xyxy: np.ndarray, colors: np.ndarray, width: int = 3
) -> np.ndarray:
    """A copy of ``image`` (H, W, 3) uint8 with the outlines of ``boxes_xyxy`` (B, 4) px (x0, y0,
    x1, y1, clipped to the image) drawn ``width`` px wide in ``colors`` (B, 3) uint8."""
    out = np.array(image, np.uint8, copy=True)
    H, W = out.shape[:2]
    boxes = np.asarray(boxes_xyxy, np.float64).reshape(-1, 4)
    colors = np.asarray(colors, np.uint8).reshape(-1, 3)
    for (x0, y0, x1, y1), col in zip(boxes, colors):
        if not np.all(np.isfinite([x0, y0, x1, y1])):
            continue
        a, b = (
            int(np.clip(np.floor(min(x0, x1)), 0, W - 1)),
            int(np.clip(np.ceil(max(x0, x1)), 0, W - 1)),
        )
        c, d = (
            int(np.clip(np.floor(min(y0, y1)), 0, H - 1)),
            int(np.clip(np.ceil(max(y0, y1)), 0, H - 1)),
        )
        w = max(1, int(width))
        out[c : min(c + w, d + 1), a : b + 1] = col
        out[max(d - w + 1, c) : d + 1, a : b + 1] = col
        out[c : d + 1, a : min(a + w, b + 1)] = col
        out[c : d + 1, max(b - w + 1, a) : b + 1] = col
    return out
