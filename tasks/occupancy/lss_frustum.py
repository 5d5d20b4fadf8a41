"""Which BEV cells of a grid a Lift-Splat-Shoot frustum reaches (FlashOcc / BEVDet's
``LSSViewTransformer``), at a given network input size: a trainer's settings check.

The frustum, as FlashOcc / BEVDet build it at test time (read from Yzichen/FlashOCC
``projects/mmdet3d_plugin/models/necks/view_transformer.py`` ``create_frustum`` /
``get_ego_coor`` / ``voxel_pooling_prepare_v2`` and ``datasets/pipelines/loading.py``
``PrepareImageInputs.sample_augmentation``):

- the image (W x H) is resized by fW / W to (int(W s), int(H s)) and cropped to the input size
  (fH, fW): rows from int(H s) - fH (the bottom kept), columns centred;
- one feature pixel per ``downsample`` (16) input pixels: u = linspace(0, fW - 1, fW // 16),
  v = linspace(0, fH - 1, fH // 16); depths arange(d_min, d_max, d_step);
- each (u, v, d) goes back to the original image, through K^-1 and the camera pose to the ego
  (base) frame, and lands in BEV cell trunc((p - lower) / interval) (z: one layer for the whole
  height), kept when inside the grid.

Coverage = the share of *camera-visible* BEV cells (a voxel centre of the column projects into
the image, in front of the camera) that at least one frustum point lands in: the rest of the
visible grid gets no image feature at all.
"""

from __future__ import annotations

import numpy as np


def frustum_points_base(
    K: np.ndarray,
    T_base_from_cam: np.ndarray,
    image_size_wh: tuple[int, int],
    input_size_hw: tuple[int, int],
    depth_m: tuple[float, float, float],
    downsample: int = 16,
) -> np.ndarray:
    """(D * fH' * fW', 3) float64 frustum points in the base frame, m.

    K: (3, 3) intrinsics of the original image (px); T_base_from_cam: (4, 4); image_size_wh:
    original (W, H) px; input_size_hw: network input (fH, fW) px; depth_m: (min, max, step)."""
    W, H = (int(v) for v in image_size_wh)
    fH, fW = (int(v) for v in input_size_hw)
    s = float(fW) / float(W)
    new_h = int(H * s)
    crop_w, crop_h = int(max(0, int(W * s) - fW) / 2), new_h - fH
    u = np.linspace(0, fW - 1, fW // downsample)
    v = np.linspace(0, fH - 1, fH // downsample)
    d = np.arange(*depth_m)
    dd, vv, uu = np.meshgrid(d, v, u, indexing="ij")
    u0, v0 = (uu + crop_w) / s, (vv + crop_h) / s  # the original image's pixels
    rays = np.stack([u0 * dd, v0 * dd, dd], axis=-1).reshape(-1, 3)
    p_cam = rays @ np.linalg.inv(np.asarray(K, np.float64)).T
    T = np.asarray(T_base_from_cam, np.float64)
    return p_cam @ T[:3, :3].T + T[:3, 3]


def bev_cells(points_base: np.ndarray, range_min, range_max, voxel_size_m: float) -> np.ndarray:
    """(N,) int64 flat BEV cell (ix * Y + iy) of each point inside the grid, -1 outside; cells
    by truncation toward zero as the LSS pooling does; z: one layer over the grid's height."""
    lo, hi = np.asarray(range_min, np.float64), np.asarray(range_max, np.float64)
    nx, ny = (int(round((hi[a] - lo[a]) / voxel_size_m)) for a in (0, 1))
    rel = (np.asarray(points_base, np.float64) - lo) / np.array(
        [voxel_size_m, voxel_size_m, hi[2] - lo[2]]
    )
    idx = np.trunc(rel).astype(np.int64)
    ok = (idx >= 0).all(axis=1) & (idx[:, 0] < nx) & (idx[:, 1] < ny) & (idx[:, 2] < 1)
    return np.where(ok, idx[:, 0] * ny + idx[:, 1], -1)


def visible_bev_cells(
    K: np.ndarray,
    T_base_from_cam: np.ndarray,
    image_size_wh: tuple[int, int],
    shape: tuple[int, int, int],
    range_min,
    voxel_size_m: float,
) -> np.ndarray:
    """(X * Y,) bool: BEV cells with a voxel centre that projects into the image (z_cam > 0)."""
    X, Y, Z = shape
    T = np.linalg.inv(np.asarray(T_base_from_cam, np.float64))
    P = np.asarray(K, np.float64) @ T[:3]  # (3, 4) image from base
    W, H = image_size_wh
    lo = np.asarray(range_min, np.float64)
    yz = np.indices((Y, Z)).reshape(2, -1).T
    out = np.zeros((X, Y), bool)
    for ix in range(X):  # one x slice at a time: fine grids hold 10^7..10^8 voxels
        c = lo + (np.c_[np.full(len(yz), ix), yz] + 0.5) * voxel_size_m
        q = c @ P[:, :3].T + P[:, 3]
        z = q[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = q[:, 0] / z, q[:, 1] / z
        inside = (z > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        out[ix] = inside.reshape(Y, Z).any(axis=1)
    return out.reshape(-1)


def frustum_coverage(
    K: np.ndarray,
    T_base_from_cam: np.ndarray,
    image_size_wh: tuple[int, int],
    input_size_hw: tuple[int, int],
    depth_m: tuple[float, float, float],
    shape: tuple[int, int, int],
    range_min,
    range_max,
    voxel_size_m: float,
    downsample: int = 16,
) -> float:
    """Share of camera-visible BEV cells that at least one frustum point lands in (module doc)."""
    visible = visible_bev_cells(K, T_base_from_cam, image_size_wh, shape, range_min, voxel_size_m)
    if not visible.any():
        return float("nan")
    cells = bev_cells(
        frustum_points_base(K, T_base_from_cam, image_size_wh, input_size_hw, depth_m, downsample),
        range_min,
        range_max,
        voxel_size_m,
    )
    hit = np.zeros(visible.shape, bool)
    hit[cells[cells >= 0]] = True
    return float((hit & visible).sum() / visible.sum())
