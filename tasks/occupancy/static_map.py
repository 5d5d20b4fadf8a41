"""The human-free static semantic map of a sequence (paper, "Static Map Generation").

Per sweep the caller lifts image semantics to the LiDAR points (:func:`lift_image_semantics`),
drops pedestrian points (:func:`pedestrian_point_mask`: instance masks and 3D boxes), moves the rest
to the world frame and adds them to a :class:`StaticSemanticMap`, which keeps compact per-voxel
label counts (uint16 per occupied class, one row per voxel of a sorted int64 key array), so memory
grows with the mapped volume, not with the number of sweeps. :meth:`StaticSemanticMap.finalize`
applies the ground-consistency check (road / terrain votes far from a robust local ground height
are rejected) and max voting.

Class ids are those of :mod:`tasks.conventions` (0 pedestrian .. 8 vegetation, 9 unclassified,
255 unlabeled). No return is thrown away for want of a class: an UNLABELED point votes
UNCLASSIFIED, and so does a ground vote the ground check rejects; any vote for a semantic class
outvotes those, so a voxel is UNCLASSIFIED only when its returns carry no class at all.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from tasks.conventions import FREE, NUM_SEMANTIC_CLASSES, PEDESTRIAN, UNCLASSIFIED, UNLABELED
from tasks.geometry import points_in_boxes, yaw_rotations
from tasks.occupancy.nearest import nearest_indices
from tasks.occupancy.settings import MapParams
from tasks.occupancy.surface import NUM_MOMENTS, group_sum, point_moments
from tasks.occupancy.voxel_keys import KEY_MASK, KEY_OFFSET, key_rows
from tasks.occupancy.voxel_keys import StaticMapError as StaticMapError
from tasks.occupancy.voxel_keys import pack_keys as pack_keys
from tasks.occupancy.voxel_keys import unpack_keys as unpack_keys
from tasks.perception.lidar_clusters import ground_height
from tasks.perception.person_points import associate_lidar_boxes

NUM_OCCUPIED_CLASSES = FREE  # classes 0..9 take votes (9: returns with no class); free never does


# -- per-sweep helpers ----------------------------------------------------------------------------
@njit(cache=True)
def _project(p, R, t, K, width, height, min_depth_m, pix, valid):
    for i in range(p.shape[0]):
        x = R[0, 0] * p[i, 0] + R[0, 1] * p[i, 1] + R[0, 2] * p[i, 2] + t[0]
        y = R[1, 0] * p[i, 0] + R[1, 1] * p[i, 1] + R[1, 2] * p[i, 2] + t[1]
        z = R[2, 0] * p[i, 0] + R[2, 1] * p[i, 1] + R[2, 2] * p[i, 2] + t[2]
        pix[i, 0] = 0
        pix[i, 1] = 0
        valid[i] = False
        if not z > min_depth_m:
            continue
        xn = x / z
        yn = y / z
        u = np.floor(xn * K[0, 0] + yn * K[0, 1] + K[0, 2] + 0.5)
        v = np.floor(xn * K[1, 0] + yn * K[1, 1] + K[1, 2] + 0.5)
        if u >= 0 and u < width and v >= 0 and v < height:
            pix[i, 0] = np.int64(u)
            pix[i, 1] = np.int64(v)
            valid[i] = True


_OFF, _MASK = KEY_OFFSET, KEY_MASK  # numba reads them as globals


def project_points(
    points_lidar: np.ndarray,
    K: np.ndarray,
    T_cam_from_lidar: np.ndarray,
    width: int,
    height: int,
    min_depth_m: float = 0.1,
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of LiDAR points in a rectified pinhole image.

    points_lidar: (N, 3) float metres, LiDAR frame. K: (3, 3) intrinsics (pixels).
    T_cam_from_lidar: (4, 4) float64. Returns (pixel (N, 2) int64 column/row of the pixel whose
    centre is nearest, OpenCV convention: centre of pixel (0, 0) at (0, 0); valid (N,) bool: depth
    z_cam > min_depth_m and inside the image; pixel is (0, 0) where not valid). One pass per point
    (a sweep is projected once and the result passed to the kernels that need it).
    """
    p = np.ascontiguousarray(np.asarray(points_lidar, dtype=np.float64).reshape(-1, 3))
    T = np.asarray(T_cam_from_lidar, dtype=np.float64)
    pix = np.empty((len(p), 2), dtype=np.int64)
    valid = np.empty(len(p), dtype=bool)
    _project(
        p,
        np.ascontiguousarray(T[:3, :3]),
        np.ascontiguousarray(T[:3, 3]),
        np.ascontiguousarray(np.asarray(K, dtype=np.float64)),
        int(width),
        int(height),
        float(min_depth_m),
        pix,
        valid,
    )
    return pix, valid


def _checked_projection(
    projection, n: int, image: np.ndarray, what: str
) -> tuple[np.ndarray, np.ndarray]:
    """A caller's (pixel, valid) from :func:`project_points`, checked against the points and image."""
    pix, valid = projection
    pix, valid = np.asarray(pix), np.asarray(valid, dtype=bool)
    if pix.shape != (n, 2) or valid.shape != (n,):
        raise StaticMapError(
            f"projection for {what} has shapes {pix.shape}, {valid.shape}; "
            f"expected ({n}, 2), ({n},)"
        )
    if valid.any():
        top = pix[valid].max(axis=0)
        if top[0] >= image.shape[1] or top[1] >= image.shape[0]:
            raise StaticMapError(
                f"projection reaches pixel {tuple(int(v) for v in top)} but the "
                f"{what} is {image.shape[1]} x {image.shape[0]}"
            )
    return pix, valid


def lift_image_semantics(
    points_lidar: np.ndarray,
    semantic_image: np.ndarray,
    K: np.ndarray,
    T_cam_from_lidar: np.ndarray,
    class_lut: np.ndarray,
    params: MapParams,
    projection: tuple[np.ndarray, np.ndarray] | None = None,
    threads: int | None = None,
) -> np.ndarray:
    """Class of each LiDAR point from a semantic image.

    points_lidar: (N, 3) float metres, LiDAR frame. semantic_image: (H, W) uint8 Cityscapes train
    ids of a rectified image. K: (3, 3). T_cam_from_lidar: (4, 4). class_lut: (256,) uint8 train id
    -> our class (UNLABELED for none, e.g. :data:`tasks.conventions.CITYSCAPES_TO_CLASS`).
    params.outside_image_fallback for points not in the image: "nearest" (class of the nearest
    labelled point, 3D, at the same level: a point less than ``ground_max_deviation_m`` above the
    local ground (the lowest point of its ``ground_cell_m`` cell's 3 x 3 neighbourhood) takes the
    label of the nearest such in-image point, any other point that of the nearest other in-image
    point, so the side of a car beside the robot is not labelled road and the road beside it not
    car; on exact distance ties the in-image point that comes first) or "unknown" (UNLABELED).
    ``fallback_ground_lateral_scale`` > 1 stretches the LiDAR y axis (across the direction of
    travel, LiDAR x forward) when matching ground points: roads, sidewalks and lawn strips run along the robot's
    path, so the ground beside the robot takes the label seen ahead at the same lateral offset
    rather than that of the nearest in-view (mostly road) point. projection: this sweep's
    :func:`project_points` into an image of this size (computed here when None). threads: for
    the nearest-neighbour search (None: one per core). Returns (N,) uint8.
    """
    fallback = params.outside_image_fallback
    if fallback not in ("nearest", "unknown"):
        raise StaticMapError(f"fallback must be 'nearest' or 'unknown', got {fallback!r}")
    img = np.asarray(semantic_image)
    if img.ndim != 2:
        raise StaticMapError(f"semantic_image must be (H, W), got shape {img.shape}")
    lut = np.asarray(class_lut, dtype=np.uint8)
    if lut.shape != (256,):
        raise StaticMapError(f"class_lut must be (256,) uint8, got shape {lut.shape}")
    p = np.asarray(points_lidar, dtype=np.float64).reshape(-1, 3)
    if projection is None:
        pix, valid = project_points(p, K, T_cam_from_lidar, img.shape[1], img.shape[0])
    else:
        pix, valid = _checked_projection(projection, len(p), img, "semantic image")
    labels = np.full(len(p), UNLABELED, dtype=np.uint8)
    labels[valid] = lut[img[pix[valid, 1], pix[valid, 0]].astype(np.uint8)]
    if fallback == "nearest" and not valid.all():
        low = p[:, 2] - ground_height(p, params.ground_cell_m) < params.ground_max_deviation_m
        labelled = valid & (labels != UNLABELED)
        stretched = p * np.array([1.0, params.fallback_ground_lateral_scale, 1.0])
        for level, q in ((low, stretched), (~low, p)):
            src, dst = labelled & level, ~valid & level
            if not src.any():  # nothing of this level in view: any in-view label
                src = labelled
            if src.any() and dst.any():
                labels[dst] = labels[src][nearest_indices(q[src], q[dst], threads)]
    return labels


def pedestrian_point_mask(
    points_lidar: np.ndarray,
    *,
    K: np.ndarray | None = None,
    T_cam_from_lidar: np.ndarray | None = None,
    instance_image: np.ndarray | None = None,
    boxes_lidar: np.ndarray | None = None,
    box_margin_m: float = 0.1,
    projection: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Points to remove before static mapping: True where a point projects into a pedestrian
    instance mask (instance_image (H, W) int > 0, with K (3, 3) and T_cam_from_lidar (4, 4), or
    this sweep's :func:`project_points` into an image of that size as projection) or lies in a
    pedestrian box (boxes_lidar (M, 7) [cx, cy, cz, l, w, h, yaw], LiDAR frame, grown by
    box_margin_m). points_lidar: (N, 3) float metres, LiDAR frame. Returns (N,) bool."""
    p = np.asarray(points_lidar, dtype=np.float64).reshape(-1, 3)
    out = np.zeros(len(p), dtype=bool)
    if instance_image is not None:
        inst = np.asarray(instance_image)
        if projection is not None:
            pix, valid = _checked_projection(projection, len(p), inst, "instance image")
        elif K is None or T_cam_from_lidar is None:
            raise StaticMapError("instance_image needs K and T_cam_from_lidar (or a projection)")
        else:
            pix, valid = project_points(p, K, T_cam_from_lidar, inst.shape[1], inst.shape[0])
        out[valid] = inst[pix[valid, 1], pix[valid, 0]] > 0
    if boxes_lidar is not None and len(boxes_lidar):
        b = np.ascontiguousarray(np.asarray(boxes_lidar, dtype=np.float64).reshape(-1, 7))
        out |= points_in_boxes(
            p, b[:, :3], b[:, 3:6], yaw_rotations(b[:, 6]), margin_m=box_margin_m
        )
    return out


def pedestrian_boxes_for_masking(
    boxes_xyxy: np.ndarray,
    lidar_centers: np.ndarray,
    lidar_sizes: np.ndarray,
    lidar_yaws: np.ndarray,
    K: np.ndarray,
    T_cam_from_lidar: np.ndarray,
    width: int,
    height: int,
    min_iou: float,
    lidar_scores: np.ndarray | None = None,
    out_of_view_min_score: float = 0.0,
) -> np.ndarray:
    """(M', 7) LiDAR pedestrian boxes [cx, cy, cz, l, w, h, yaw] used to remove people's points.

    boxes_xyxy: (D, 4) image detections (pixels). lidar_centers, lidar_sizes: (M, 3) metres, LiDAR
    frame; lidar_yaws: (M,) rad. Inside the camera view (width x height, K, T_cam_from_lidar) the
    image decides (instance masks are sharper and a geometric LiDAR detector fires on trunks and
    posts): a box there counts only if an image detection confirms it (IoU >= min_iou of its
    projected corners). Outside the view the LiDAR boxes are all there is: a box counts there when
    its person score (lidar_scores (M,), e.g. tasks.perception.lidar_clusters.person_score) is at
    least out_of_view_min_score (None: every box counts). An unconfirmed candidate's returns stay
    in the map: a false box on a post would delete the post (issue 39).
    """
    centers = np.asarray(lidar_centers).reshape(-1, 3)
    boxes = np.column_stack(
        [centers, np.asarray(lidar_sizes).reshape(-1, 3), np.asarray(lidar_yaws).reshape(-1)]
    )
    if len(boxes) == 0:
        return boxes.reshape(0, 7)
    _, in_view = project_points(centers, K, T_cam_from_lidar, width, height)
    matched = associate_lidar_boxes(
        boxes_xyxy, centers, lidar_sizes, lidar_yaws, K, T_cam_from_lidar, min_iou
    )
    confirmed = np.zeros(len(boxes), bool)
    confirmed[matched[matched >= 0]] = True
    if lidar_scores is not None:
        sure = np.asarray(lidar_scores, np.float64).reshape(-1) >= out_of_view_min_score
        return boxes[(~in_view & sure) | confirmed]
    return boxes[~in_view | confirmed]


# -- the map --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class StaticMap:
    """The final static map: one row per labelled voxel, world frame.

    keys: (K, 3) int64, voxel [k, k + 1) * voxel_size_m (aligned to multiples of the voxel size
    around 0, like the occupancy map). labels: (K,) uint8 class ids. counts: (K, 10) uint16 votes
    per occupied class 0..9 after the ground check (column 9: returns with no class, and rejected
    ground votes). ground_rejected: ground votes removed by the check.
    surface: (K, 6) float32 where the surface lies in each voxel (centroid of its points relative
    to the voxel's corner, m, and the unit normal of its own plane, zeros where it has none:
    :class:`tasks.occupancy.surface.SurfaceFit`), or None (a map built without point moments:
    resampled by voxel centres).
    """

    voxel_size_m: float
    keys: np.ndarray
    labels: np.ndarray
    counts: np.ndarray
    ground_rejected: int
    surface: np.ndarray | None = None

    def _rows(self, keep: np.ndarray) -> StaticMap:
        return StaticMap(
            self.voxel_size_m,
            self.keys[keep],
            self.labels[keep],
            self.counts[keep],
            self.ground_rejected,
            None if self.surface is None else self.surface[keep],
        )

    def centers(self) -> np.ndarray:
        """(K, 3) float64 voxel centres, metres, world frame."""
        return (self.keys + 0.5) * self.voxel_size_m

    def crop(self, center_world: np.ndarray, radius_m: float) -> StaticMap:
        """Voxels whose centre is within radius_m (horizontally) of center_world (3,)."""
        c = self.centers()
        keep = np.hypot(c[:, 0] - center_world[0], c[:, 1] - center_world[1]) <= radius_m
        return self._rows(keep)

    def crop_to_grid(self, spec, T_world_from_grid: np.ndarray) -> StaticMap:
        """Voxels that can overlap a grid: centre within the grid box (spec: GridSpec in its own
        frame, T_world_from_grid (4, 4) float64) grown by one map voxel diagonal."""
        T = np.asarray(T_world_from_grid, dtype=np.float64)
        c = (self.centers() - T[:3, 3]) @ T[:3, :3]  # world -> grid frame
        pad = self.voxel_size_m * np.sqrt(3.0)
        keep = np.all(
            (c >= np.asarray(spec.range_min) - pad) & (c <= np.asarray(spec.range_max) + pad),
            axis=1,
        )
        return self._rows(keep)

    def sample_points(self, spacing_m: float) -> tuple[np.ndarray, np.ndarray]:
        """Points filling every voxel at <= spacing_m (for voxelizing into a finer grid).

        Returns (points (K * n^3, 3) float32 world frame, labels (K * n^3,) uint8), n =
        ceil(voxel_size_m / spacing_m) sub-voxel centres per axis (n = 1: the voxel centres).
        """
        n = max(1, int(np.ceil(self.voxel_size_m / spacing_m - 1e-9)))
        sub = (np.arange(n) + 0.5) / n
        offs = np.stack(np.meshgrid(sub, sub, sub, indexing="ij"), -1).reshape(-1, 3)
        pts = ((self.keys[:, None, :] + offs[None]) * self.voxel_size_m).reshape(-1, 3)
        return pts.astype(np.float32), np.repeat(self.labels, len(offs))


class StaticSemanticMap:
    """Accumulates semantic sweeps into per-voxel label counts (one sequence, world frame).

    voxel_size_m: map resolution. flush_points: pending points merged into the sorted count table
    once this many are buffered (memory vs merge cost). moments: also keep each voxel's point
    moments (:mod:`tasks.occupancy.surface`; every sweep then needs its sensor origin). State
    lives on the instance.
    """

    def __init__(
        self, voxel_size_m: float, flush_points: int = 2_000_000, moments: bool = False
    ) -> None:
        if not voxel_size_m > 0:
            raise StaticMapError(f"voxel_size_m must be > 0, got {voxel_size_m}")
        self.voxel_size_m = float(voxel_size_m)
        self.flush_points = int(flush_points)
        self.with_moments = bool(moments)
        self._keys = np.empty(0, dtype=np.int64)  # sorted packed keys
        self._counts = np.empty((0, NUM_OCCUPIED_CLASSES), dtype=np.uint16)
        self._moments = np.empty((0, NUM_MOMENTS), dtype=np.int64)
        self._pending_keys: list[np.ndarray] = []
        self._pending_labels: list[np.ndarray] = []
        self._pending_moments: list[tuple[np.ndarray, np.ndarray]] = []
        self._pending = 0
        self.num_sweeps = 0

    @property
    def num_voxels(self) -> int:
        self._flush()
        return len(self._keys)

    @property
    def memory_bytes(self) -> int:
        return self._keys.nbytes + self._counts.nbytes + 9 * self._pending

    def add_sweep(
        self,
        points_world: np.ndarray,
        labels: np.ndarray,
        keep: np.ndarray | None = None,
        origin_world: np.ndarray | None = None,
    ) -> None:
        """Add one sweep's votes.

        points_world: (N, 3) float32 metres, world frame. labels: (N,) uint8 class ids (UNLABELED
        points vote UNCLASSIFIED; FREE is rejected). keep: optional (N,) bool, False for points to drop
        (pedestrian points). origin_world: (3,) the sensor's position (needed with moments).
        """
        if self.with_moments and origin_world is None:
            raise StaticMapError(f"sweep {self.num_sweeps}: a map with moments needs origin_world")
        p = np.asarray(points_world).reshape(-1, 3)
        lab = np.asarray(labels).reshape(-1)
        if len(lab) != len(p):
            raise StaticMapError(f"sweep {self.num_sweeps}: {len(p)} points but {len(lab)} labels")
        sel = np.ones(len(lab), dtype=bool)
        if keep is not None:
            keep = np.asarray(keep, dtype=bool).reshape(-1)
            if len(keep) != len(p):
                raise StaticMapError(
                    f"sweep {self.num_sweeps}: keep has {len(keep)} rows, expected {len(p)}"
                )
            sel &= keep
        sel &= np.all(np.isfinite(p), axis=1)
        lab = lab[sel].astype(np.uint8)
        lab[lab == UNLABELED] = UNCLASSIFIED  # a return with no class still holds a surface
        if len(lab) and lab.max() >= NUM_OCCUPIED_CLASSES:
            raise StaticMapError(
                f"sweep {self.num_sweeps}: class {int(lab.max())} cannot vote (expected 0..9 or 255)"
            )
        keys = np.floor(np.asarray(p[sel], dtype=np.float64) / self.voxel_size_m).astype(np.int64)
        packed = pack_keys(keys)
        self._pending_keys.append(packed)
        self._pending_labels.append(lab)
        if self.with_moments:
            rows = point_moments(p[sel], keys, origin_world, self.voxel_size_m)
            self._pending_moments.append(group_sum(packed, rows))
        self._pending += len(lab)
        self.num_sweeps += 1
        if self._pending >= self.flush_points:
            self._flush()

    def _flush(self) -> None:
        if not self._pending_keys:
            return
        pk = np.concatenate(self._pending_keys)
        pl = np.concatenate(self._pending_labels)
        pending_moments = self._pending_moments
        self._pending_keys, self._pending_labels, self._pending = [], [], 0
        self._pending_moments = []
        if not len(pk):
            return
        uk, inv = np.unique(pk, return_inverse=True)
        add = np.bincount(
            inv * NUM_OCCUPIED_CLASSES + pl, minlength=len(uk) * NUM_OCCUPIED_CLASSES
        ).reshape(len(uk), -1)
        keys = np.union1d(self._keys, uk)
        counts = np.zeros((len(keys), NUM_OCCUPIED_CLASSES), dtype=np.uint32)
        counts[np.searchsorted(keys, self._keys)] = self._counts
        counts[np.searchsorted(keys, uk)] += add.astype(np.uint32)
        if self.with_moments:
            mk, mm = group_sum(
                np.concatenate([k for k, _ in pending_moments]),
                np.concatenate([m for _, m in pending_moments]),
            )
            moments = np.zeros((len(keys), NUM_MOMENTS), dtype=np.int64)
            moments[np.searchsorted(keys, self._keys)] = self._moments
            moments[np.searchsorted(keys, mk)] += mm
            self._moments = moments
        self._keys = keys
        self._counts = np.minimum(counts, np.iinfo(np.uint16).max).astype(np.uint16)  # saturate

    def counts(self) -> tuple[np.ndarray, np.ndarray]:
        """Raw votes so far: keys (K, 3) int64 and counts (K, 10) uint16."""
        self._flush()
        return unpack_keys(self._keys), self._counts.copy()

    def packed_moments(self) -> np.ndarray:
        """Point moments (K, 13) int64 of the voxels of :meth:`packed_counts` (same rows; a map
        made without moments: empty)."""
        self._flush()
        return self._moments

    def packed_counts(self) -> tuple[np.ndarray, np.ndarray]:
        """Raw votes so far: packed keys (K,) int64 ascending (:func:`pack_keys`), counts (K, 10)
        uint16 (the arrays themselves, not copies)."""
        self._flush()
        return self._keys, self._counts

    def finalize(
        self,
        params: MapParams,
        ground_classes: tuple[int, ...],
        ignore_classes: tuple[int, ...] = (PEDESTRIAN,),
    ) -> StaticMap:
        """Ground check, then max voting (params: its ``voxel_size_m`` is this map's).

        Ground check: per xy cell of ``ground_cell_m``, the local ground height is the
        vote-weighted ``ground_quantile`` of the z of voxels with votes of ground_classes, over the
        (2 * ``ground_neighbourhood_cells`` + 1)^2 surrounding cells; ground votes of a voxel whose
        centre is more than ``ground_max_deviation_m`` from it are rejected (they become UNCLASSIFIED
        votes: the returns are there, their class is not). Voting: the semantic class with most
        votes (ties: the lower id), ignoring ignore_classes (the map is human-free); a voxel whose
        semantic votes are fewer than ``min_votes`` is UNCLASSIFIED when its votes with the
        UNCLASSIFIED ones reach ``min_votes``, else dropped.
        """
        if params.voxel_size_m != self.voxel_size_m:
            raise StaticMapError(
                f"params.voxel_size_m {params.voxel_size_m} is not the map's {self.voxel_size_m}"
            )
        self._flush()
        return vote(self._keys, self._counts, params, ground_classes, ignore_classes)


def vote(
    packed_keys: np.ndarray,
    counts: np.ndarray,
    params: MapParams,
    ground_classes: tuple[int, ...],
    ignore_classes: tuple[int, ...] = (PEDESTRIAN,),
    select: np.ndarray | None = None,
) -> StaticMap:
    """:meth:`StaticSemanticMap.finalize` of raw votes: packed_keys (K,) int64 ascending, counts
    (K, 10) uint16 of voxels of ``params.voxel_size_m``. select: (K,) bool, the voxels to return (default all); the ground heights use
    every voxel given, so the votes of a tile plus its halo (:func:`tasks.occupancy.tiles.
    ground_halo_tiles`) give the tile's voxels exactly as the whole map does (the weights are
    integer vote counts: their sums are exact in float64). ground_rejected counts selected voxels.
    """
    voxel_size_m = params.voxel_size_m
    keys = unpack_keys(packed_keys)
    counts = np.asarray(counts).astype(np.int64)
    centers = (keys + 0.5) * voxel_size_m
    g_idx = np.asarray(ground_classes, dtype=np.int64)
    sel = np.ones(len(keys), bool) if select is None else np.asarray(select, dtype=bool)
    rejected = 0
    if len(g_idx) and len(keys):
        gvotes = counts[:, g_idx].sum(axis=1)
        height = _local_ground_height(
            centers,
            gvotes,
            params.ground_cell_m,
            params.ground_neighbourhood_cells,
            params.ground_quantile,
        )
        bad = (
            (gvotes > 0)
            & np.isfinite(height)
            & (np.abs(centers[:, 2] - height) > params.ground_max_deviation_m)
        )
        rejected = int(gvotes[bad & sel].sum())
        counts[bad, UNCLASSIFIED] += gvotes[bad]
        counts[np.ix_(bad, g_idx)] = 0
    vote = counts.copy()
    if ignore_classes:
        vote[:, list(ignore_classes)] = 0
    semantic = vote[:, :NUM_SEMANTIC_CLASSES]
    need = max(1, params.min_votes)
    labels = np.argmax(semantic, axis=1).astype(np.uint8)
    classed = semantic.max(axis=1) >= need
    labels[~classed] = UNCLASSIFIED
    keep = (classed | (vote.sum(axis=1) >= need)) & sel
    return StaticMap(
        voxel_size_m,
        keys[keep],
        labels[keep],
        np.minimum(counts[keep], 65535).astype(np.uint16),
        rejected,
    )


#: the 13 neighbour offsets of a 26-neighbourhood that come after a voxel in packed-key order
_FORWARD = np.array(
    [
        (i, j, k)
        for i in (-1, 0, 1)
        for j in (-1, 0, 1)
        for k in (-1, 0, 1)
        if (i, j, k) > (0, 0, 0)
    ],
    dtype=np.int64,
)


def small_fragments(keys: np.ndarray, labels: np.ndarray, min_voxels: int) -> np.ndarray:
    """(K,) bool: True for the voxels of a fragment, a set of voxels of one class connected
    through faces, edges or corners (26-neighbourhood), that holds fewer than ``min_voxels``
    voxels. keys (K, 3) int64 voxel indices, labels (K,) class ids. Only the voxels given count:
    give a halo of at least ``min_voxels`` voxels around the ones whose answer is used."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    keys = np.asarray(keys, dtype=np.int64).reshape(-1, 3)
    labels = np.asarray(labels).reshape(-1)
    n = len(keys)
    if min_voxels <= 1 or n == 0:
        return np.zeros(n, dtype=bool)
    packed = pack_keys(keys)
    order = np.argsort(packed, kind="stable")
    table = packed[order]
    rows, cols = [], []
    for off in _FORWARD:
        at = key_rows(table, keys + off)
        other = order[np.maximum(at, 0)]
        same = (at >= 0) & (labels[other] == labels)
        rows.append(np.nonzero(same)[0])
        cols.append(other[same])
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(r), np.int8), (r, c)), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    return np.bincount(comp)[comp] < min_voxels


def sum_votes(parts: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Votes of several windows of sweeps added: parts of (packed keys (K,) int64 ascending, counts
    (K, 10) uint16) -> the same for their union. Counts saturate at 65535 like
    :class:`StaticSemanticMap`'s (a sum of non-negative counts saturated once equals any order of
    saturated partial sums), so the windows of a sequence sum to its sequential votes."""
    parts = [(np.asarray(k, np.int64), np.asarray(c, np.uint16)) for k, c in parts if len(k)]
    if not parts:
        return np.empty(0, np.int64), np.empty((0, NUM_OCCUPIED_CLASSES), np.uint16)
    if len(parts) == 1:
        return parts[0]
    keys, inv = np.unique(np.concatenate([k for k, _ in parts]), return_inverse=True)
    total = np.zeros((len(keys), NUM_OCCUPIED_CLASSES), np.int64)
    np.add.at(total, inv, np.concatenate([c for _, c in parts]).astype(np.int64))
    return keys, np.minimum(total, np.iinfo(np.uint16).max).astype(np.uint16)


def _local_ground_height(
    centers: np.ndarray, gvotes: np.ndarray, cell_m: float, nb: int, quantile: float
) -> np.ndarray:
    """Per voxel: the vote-weighted quantile of ground-voxel z over the neighbouring xy cells
    (NaN where no ground votes are near). centers (K, 3) metres; gvotes (K,) int."""
    cell = np.floor(centers[:, :2] / cell_m).astype(np.int64) + _OFF
    cell_id = (cell[:, 0] << 21) | cell[:, 1]
    g = gvotes > 0
    if not g.any():
        return np.full(len(centers), np.nan)
    gz, gw, gc = centers[g, 2], gvotes[g].astype(np.float64), cell[g]
    tz, tw, tid = [], [], []
    for dx in range(-nb, nb + 1):  # every ground voxel votes in its neighbours' cells too
        for dy in range(-nb, nb + 1):
            tid.append(((gc[:, 0] + dx) << 21) | (gc[:, 1] + dy))
            tz.append(gz)
            tw.append(gw)
    tid, tz, tw = np.concatenate(tid), np.concatenate(tz), np.concatenate(tw)
    order = np.lexsort((tz, tid))
    tid, tz, tw = tid[order], tz[order], tw[order]
    ucell, start = np.unique(tid, return_index=True)
    sizes = np.diff(np.append(start, len(tid)))
    csum = np.cumsum(tw)
    before = np.concatenate([[0.0], csum])[start]
    rel = csum - np.repeat(before, sizes)  # cumulative weight within each cell
    target = np.repeat(quantile * np.add.reduceat(tw, start), sizes)
    # the first row of each cell whose cumulative weight reaches the quantile
    rows = np.nonzero(rel >= target - 1e-9)[0]
    grp = np.searchsorted(start, rows, side="right") - 1
    first_rows = np.full(len(ucell), len(tid) - 1, dtype=np.int64)
    np.minimum.at(first_rows, grp, rows)
    height_cell = tz[first_rows]
    pos = np.searchsorted(ucell, cell_id)
    pos_c = np.minimum(pos, len(ucell) - 1)
    found = ucell[pos_c] == cell_id
    return np.where(found, height_cell[pos_c], np.nan)


def merge_static_maps(primary: StaticMap, secondary: StaticMap) -> StaticMap:
    """Union of two maps of one voxel size: ``primary`` wins where both have a voxel.

    Used to let camera-labelled votes decide every voxel the camera saw, and fallback labels (points
    outside the image) fill only the voxels it never saw: out-of-view points outnumber in-view ones
    several times, so pooling their votes would let the fallback outvote the camera. Where the
    primary voxel is UNCLASSIFIED and the secondary's has a class, the secondary's wins (a class
    beats no class).
    """
    if primary.voxel_size_m != secondary.voxel_size_m:
        raise StaticMapError(
            f"cannot merge maps of {primary.voxel_size_m} m and {secondary.voxel_size_m} m voxels"
        )
    a, b = pack_keys(primary.keys), pack_keys(secondary.keys)
    classed_b = b[secondary.labels != UNCLASSIFIED]
    weak_a = (primary.labels == UNCLASSIFIED) & np.isin(a, classed_b)
    if weak_a.any():
        primary = StaticMap(
            primary.voxel_size_m,
            primary.keys[~weak_a],
            primary.labels[~weak_a],
            primary.counts[~weak_a],
            primary.ground_rejected,
            None if primary.surface is None else primary.surface[~weak_a],
        )
        a = a[~weak_a]
    only_b = ~np.isin(b, a)
    keys = np.concatenate([primary.keys, secondary.keys[only_b]])
    order = np.argsort(pack_keys(keys), kind="stable")
    surface = None
    if primary.surface is not None and secondary.surface is not None:
        surface = np.concatenate([primary.surface, secondary.surface[only_b]])[order]
    return StaticMap(
        primary.voxel_size_m,
        keys[order],
        np.concatenate([primary.labels, secondary.labels[only_b]])[order],
        np.concatenate([primary.counts, secondary.counts[only_b]])[order],
        primary.ground_rejected + secondary.ground_rejected,
        surface,
    )


def sorted_table(static: StaticMap) -> tuple[np.ndarray, np.ndarray]:
    """(packed keys (K,) int64 ascending, labels (K,) uint8 in that order) of a map, for
    :func:`lookup_packed`. Maps written by the map stage are already in this order (no sort)."""
    table = pack_keys(static.keys)
    if len(table) > 1 and not np.all(table[1:] > table[:-1]):
        order = np.argsort(table, kind="stable")
        return table[order], static.labels[order]
    return table, np.asarray(static.labels)


@njit(cache=True, inline="always")
def lookup_packed(table, labels, kx, ky, kz):
    """Label of map voxel key (kx, ky, kz) in a :func:`sorted_table`, UNLABELED if absent."""
    if not (
        -_OFF <= kx <= _MASK - _OFF and -_OFF <= ky <= _MASK - _OFF and -_OFF <= kz <= _MASK - _OFF
    ):
        return np.uint8(UNLABELED)
    q = ((kx + _OFF) << 42) | ((ky + _OFF) << 21) | (kz + _OFF)
    at = np.searchsorted(table, q)
    if at < table.shape[0] and table[at] == q:
        return labels[at]
    return np.uint8(UNLABELED)


@njit(cache=True)
def _lookup_points(p, vs, table, labels, out):
    for i in range(p.shape[0]):
        out[i] = lookup_packed(
            table,
            labels,
            np.int64(np.floor(p[i, 0] / vs)),
            np.int64(np.floor(p[i, 1] / vs)),
            np.int64(np.floor(p[i, 2] / vs)),
        )


def lookup_labels(static: StaticMap, points_world: np.ndarray) -> np.ndarray:
    """Label of the map voxel containing each point, UNLABELED where the map has none.

    points_world: (N, 3) float metres, world frame. Returns (N,) uint8. This is nearest-voxel
    resampling: querying the centres of another grid gives every voxel of that grid the label of
    the map voxel under its centre, with no holes where the two grids are offset (pushing the map's
    voxel centres into an offset grid would leave every other cell empty).
    """
    p = np.ascontiguousarray(np.asarray(points_world, dtype=np.float64).reshape(-1, 3))
    out = np.full(len(p), UNLABELED, dtype=np.uint8)
    if len(static.keys) == 0 or len(p) == 0:
        return out
    table, labels = sorted_table(static)
    _lookup_points(p, static.voxel_size_m, table, labels, out)
    return out
