"""Pedestrian voxel quality: vs ground-truth 3D boxes and vs LiDAR body ground truth.

Against boxes (the paper, "Pedestrian occupancy quality"). Boxes hold empty air and the ground at
the feet, so only part of them is compared. A voxel is "in a box" when its centre lies inside the
oriented box; the bottom ``bottom_exclude_m`` (0.1 m) of every box is left out of both sides.
With V = camera-visible voxels (mask_camera), B = voxels in some box above its bottom slab,
S = voxels in the bottom slab of some box, P = voxels labelled pedestrian, O = reference occupied
voxels (default: occupied in the evaluated grid, any class):

- precision = |P & V & B| / |P & V & ~S|  (visible pedestrian voxels that lie in a box);
- recall    = |P & V & B & O| / |V & B & O| (visible occupied box voxels labelled pedestrian).

Against LiDAR body ground truth (the paper, "vs. LiDAR body GT"): per-pedestrian LiDAR points
inside the annotated boxes are voxelised on the evaluation grid (G), compared with P inside the
evaluated region R (camera frustum, benchmark range) at +-1 voxel centre-to-centre tolerance
(a 3x3x3 dilation D):

- precision = |P & D(G)| / |P|  (SMPL -> GT);  recall = |G & D(P)| / |G|  (GT -> SMPL).

Both return :class:`~tasks.metrics._common.PRCounts`; add them over frames and sequences for the
"All" column (micro average).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from tasks import conventions as C
from tasks.metrics._common import MetricInputError, PRCounts, check_label_grid, check_mask

#: m: a voxel centre this close to a box face or to the top of its bottom slab counts as lying on
#: it (inside the box, above the slab). Boxes stand on the ground, so the slab top falls exactly
#: on a layer of voxel centres (0.1 m above a 0.2 m voxel face); without the tolerance the last
#: bits of the box values (float32 ground truth vs 6-decimal 3d_bbox JSON) decided that whole
#: layer of each box's footprint, one way or the other.
BOX_FACE_TOL_M = 1e-5


def _check_boxes(centers, sizes, yaws) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    s = np.asarray(sizes, dtype=np.float64).reshape(-1, 3)
    y = np.asarray(yaws, dtype=np.float64).reshape(-1)
    if not (len(c) == len(s) == len(y)):
        raise MetricInputError(
            f"boxes: {len(c)} centers, {len(s)} sizes and {len(y)} yaws differ in number"
        )
    if np.any(s <= 0):
        raise MetricInputError(f"boxes: sizes must be > 0, got {s[np.any(s <= 0, axis=1)][0]}")
    return c, s, y


def box_voxel_masks(
    shape, range_min, voxel_size_m: float, centers, sizes, yaws, bottom_exclude_m: float = 0.1
) -> tuple[np.ndarray, np.ndarray]:
    """Voxels whose centre lies in some box, split at ``bottom_exclude_m`` above each box bottom.

    shape: (X, Y, Z) voxels; range_min: (3,) m grid corner; centers (B, 3) m and sizes (B, 3)
    (l, w, h) m of the boxes in the grid frame, yaws (B,) rad about z (l along the rotated x).
    Returns (body, bottom): two (X, Y, Z) bool grids, centres inside a box above / below its slab.
    A centre within ``BOX_FACE_TOL_M`` of a face is inside; of the slab top, above it.
    """
    c, s, yaw = _check_boxes(centers, sizes, yaws)
    shape = tuple(int(v) for v in shape)
    lo = np.asarray(range_min, dtype=np.float64)
    vs = float(voxel_size_m)
    body = np.zeros(shape, dtype=bool)
    bottom = np.zeros(shape, dtype=bool)
    for cb, sb, yb in zip(c, s, yaw):
        half_xy = 0.5 * np.hypot(sb[0], sb[1])  # bounding radius in the xy plane
        ext = np.array([half_xy, half_xy, 0.5 * sb[2]])
        i0 = np.clip(np.floor((cb - ext - lo) / vs).astype(np.int64), 0, shape)
        i1 = np.clip(np.ceil((cb + ext - lo) / vs).astype(np.int64) + 1, 0, shape)
        if np.any(i1 <= i0):
            continue
        axes = [lo[a] + (np.arange(i0[a], i1[a]) + 0.5) * vs - cb[a] for a in range(3)]
        dx, dy, dz = np.meshgrid(*axes, indexing="ij")
        cos, sin = np.cos(yb), np.sin(yb)
        lx = cos * dx + sin * dy  # rotate into the box frame (R^T d)
        ly = -sin * dx + cos * dy
        tol = BOX_FACE_TOL_M
        inside = (
            (np.abs(lx) <= sb[0] / 2 + tol)
            & (np.abs(ly) <= sb[1] / 2 + tol)
            & (np.abs(dz) <= sb[2] / 2 + tol)
        )
        low = dz < -sb[2] / 2 + bottom_exclude_m - tol
        sl = tuple(slice(i0[a], i1[a]) for a in range(3))
        body[sl] |= inside & ~low
        bottom[sl] |= inside & low
    return body, bottom


def pedestrian_box_counts(
    pred: np.ndarray,
    range_min,
    voxel_size_m: float,
    centers,
    sizes,
    yaws,
    visible: np.ndarray | None = None,
    reference_occupied: np.ndarray | None = None,
    bottom_exclude_m: float = 0.1,
) -> PRCounts:
    """Pedestrian voxels of one frame vs its GT pedestrian boxes (definitions in the module doc).

    pred: (X, Y, Z) uint8 class ids (0 pedestrian, 10 free) in the grid frame; range_min (3,) m;
    voxel_size_m m; centers (B, 3) m, sizes (B, 3) m (l, w, h), yaws (B,) rad: boxes in the grid
    frame; visible: (X, Y, Z) bool mask_camera or None (all); reference_occupied: (X, Y, Z) bool
    voxels counted as occupied for recall, None = ``pred != FREE``.
    """
    pred = check_label_grid("pred", pred)
    vis = check_mask("visible", visible, pred.shape)
    occ = (
        (pred != C.FREE)
        if reference_occupied is None
        else check_mask("reference_occupied", reference_occupied, pred.shape)
    )
    body, bottom = box_voxel_masks(
        pred.shape, range_min, voxel_size_m, centers, sizes, yaws, bottom_exclude_m
    )
    ped = (pred == C.PEDESTRIAN) & vis
    ref = body & vis & occ
    return PRCounts(
        int(np.sum(ped & body)),
        int(np.sum(ped & ~bottom)),
        int(np.sum(ref & ped)),
        int(np.sum(ref)),
    )


def voxelize_points(points, range_min, voxel_size_m: float, shape) -> np.ndarray:
    """(N, 3) metres in the grid frame -> (X, Y, Z) bool, True where a point falls (outside ignored)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    shape = tuple(int(v) for v in shape)
    idx = np.floor((pts - np.asarray(range_min, dtype=np.float64)) / float(voxel_size_m)).astype(
        np.int64
    )
    idx = idx[np.all((idx >= 0) & (idx < np.asarray(shape)), axis=1)]
    grid = np.zeros(shape, dtype=bool)
    grid[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    return grid


def pedestrian_lidar_counts(
    pred: np.ndarray,
    gt_body: np.ndarray,
    region: np.ndarray | None = None,
    tolerance_voxels: int = 1,
) -> PRCounts:
    """Pedestrian voxels of one frame vs LiDAR body ground truth at +-``tolerance_voxels``.

    pred: (X, Y, Z) uint8 class ids (pedestrian = 0); gt_body: (X, Y, Z) bool voxelised LiDAR body
    points of the annotated pedestrians (see :func:`voxelize_points`); region: (X, Y, Z) bool
    evaluated voxels (camera frustum within range), None = all. Counts are voxels.
    """
    pred = check_label_grid("pred", pred)
    reg = check_mask("region", region, pred.shape)
    gt = check_mask("gt_body", gt_body, pred.shape) & reg
    ped = (pred == C.PEDESTRIAN) & reg
    if tolerance_voxels < 0:
        raise MetricInputError(f"tolerance_voxels must be >= 0, got {tolerance_voxels}")
    if tolerance_voxels == 0:
        near_gt, near_ped = gt, ped
    else:
        st = np.ones(
            (3, 3, 3), dtype=bool
        )  # 26-neighbourhood: +-1 voxel per axis, centre to centre
        near_gt = ndimage.binary_dilation(gt, structure=st, iterations=tolerance_voxels)
        near_ped = ndimage.binary_dilation(ped, structure=st, iterations=tolerance_voxels)
    return PRCounts(
        int(np.sum(ped & near_gt)), int(np.sum(ped)), int(np.sum(gt & near_ped)), int(np.sum(gt))
    )


def person_point_counts(
    point_instance: np.ndarray, extracted: list[np.ndarray], gt_ids: np.ndarray
) -> PRCounts:
    """Person-point extraction against per-point ground-truth instances.

    point_instance: (N,) int GT instance id of every point of the sweep. extracted: per tracked
    person, the indices (into the same N points) the pipeline assigned to it. gt_ids: (P,) the GT
    instance of each tracked person (rows < 0, false positives, count only in the precision).
    precision = extracted points of the right person / extracted points; recall = the person's
    points that were extracted / the person's points in the sweep.
    """
    inst = np.asarray(point_instance).reshape(-1)
    counts = PRCounts()
    for idx, gid in zip(extracted, np.asarray(gt_ids).reshape(-1)):
        idx = np.asarray(idx, np.int64)
        hit = int((inst[idx] == gid).sum()) if gid >= 0 else 0
        truth = int((inst == gid).sum()) if gid >= 0 else 0
        counts = counts + PRCounts(hit, len(idx), hit, truth)
    return counts
