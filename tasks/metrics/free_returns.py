"""Label honesty without ground truth: how many voxels holding LiDAR returns are exported free.

A return is a surface: its voxel (or, by the voxel convention of storage/SCHEMA.md, a neighbour)
is occupied. A voxel that holds returns of the frame, is FREE in the exported semantics (with
mask_lidar 1: observed) and has nothing occupied among its 26 neighbours is a *free return voxel*.
Single such voxels are range noise or a stray return (a bird, rain, a mixed pixel); a 26-connected
cluster of at least ``min_cluster_voxels`` of them is a surface the labels call empty (a wall of
unlabelled returns, a person whose body was not fitted). :func:`free_return_counts` counts those
clusters' voxels against every return-holding voxel of the frame; :func:`label_counts` gives the
occupied / unclassified / pedestrian voxel counts beside it. Both need no ground truth.

Grids are ``[x, y, z]`` class ids of :mod:`tasks.conventions` (FREE 10 free, 9 unclassified).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tasks import conventions as C
from tasks.metrics._common import MetricInputError, check_label_grid, check_mask, ratio

#: a cluster of free return voxels smaller than this is noise, not a surface called free
MIN_CLUSTER_VOXELS = 5

_STRUCTURE = np.ones((3, 3, 3), dtype=bool)


@dataclass(frozen=True)
class FreeReturnCounts:
    """Accumulable counts (add two to sum frames). return_voxels: voxels of the grid holding
    returns; free_return_voxels: those exported FREE (mask_lidar 1) with nothing occupied among
    their 26 neighbours, in 26-connected clusters of >= min_cluster_voxels; clusters: how many
    such clusters; frames: frames added."""

    return_voxels: int = 0
    free_return_voxels: int = 0
    clusters: int = 0
    frames: int = 0

    def __add__(self, other: FreeReturnCounts) -> FreeReturnCounts:
        return FreeReturnCounts(
            self.return_voxels + other.return_voxels,
            self.free_return_voxels + other.free_return_voxels,
            self.clusters + other.clusters,
            self.frames + other.frames,
        )

    @property
    def share(self) -> float:
        """free_return_voxels / return_voxels (NaN: no return in the grid)."""
        return ratio(self.free_return_voxels, self.return_voxels)

    def as_dict(self) -> dict:
        return {
            "free_returns_share": self.share,
            "return_voxels": int(self.return_voxels),
            "free_return_voxels": int(self.free_return_voxels),
            "free_return_clusters": int(self.clusters),
            "frames": int(self.frames),
        }


def free_return_voxels(
    semantics: np.ndarray,
    mask_lidar: np.ndarray | None,
    points: np.ndarray,
    range_min,
    voxel_size_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """(return voxels (R, 3) int64 unique, rows ascending; free (R,) bool: exported FREE with
    mask_lidar 1 and nothing occupied (class < FREE) among the 26 neighbours).

    semantics: (X, Y, Z) uint8 class ids; mask_lidar: (X, Y, Z) 0/1 (None: all observed);
    points: (N, 3) float metres, this frame's returns in the grid's frame; range_min (3,) metres;
    voxel_size_m metres. Points outside the grid or not finite are left out."""
    sem = check_label_grid("semantics", semantics)
    m = check_mask("mask_lidar", mask_lidar, sem.shape)
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise MetricInputError(f"points: expected (N, 3) metres, got shape {pts.shape}")
    if not float(voxel_size_m) > 0:
        raise MetricInputError(f"voxel_size_m {voxel_size_m} must be > 0")
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    lo = np.asarray(range_min, dtype=np.float64).reshape(3)
    idx = np.floor((pts - lo) / float(voxel_size_m)).astype(np.int64)
    inside = np.all((idx >= 0) & (idx < np.asarray(sem.shape)), axis=1)
    vox = np.unique(idx[inside], axis=0).reshape(-1, 3)
    padded = np.pad(sem < C.FREE, 1)
    near = np.zeros(len(vox), dtype=bool)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                q = vox + (1 + dx, 1 + dy, 1 + dz)
                near |= padded[q[:, 0], q[:, 1], q[:, 2]]
    at = tuple(vox.T)
    free = (sem[at] == C.FREE) & m[at] & ~near
    return vox, free


def free_return_counts(
    semantics: np.ndarray,
    mask_lidar: np.ndarray | None,
    points: np.ndarray,
    range_min,
    voxel_size_m: float,
    min_cluster_voxels: int = MIN_CLUSTER_VOXELS,
) -> FreeReturnCounts:
    """One frame's :class:`FreeReturnCounts` (arguments as :func:`free_return_voxels`; clusters
    are 26-connected sets of free return voxels, counted when they hold >= min_cluster_voxels)."""
    from scipy import ndimage

    vox, free = free_return_voxels(semantics, mask_lidar, points, range_min, voxel_size_m)
    cand = vox[free]
    counted = clusters = 0
    if len(cand):
        lo = cand.min(axis=0)
        box = np.zeros(tuple(cand.max(axis=0) - lo + 1), dtype=bool)
        box[tuple((cand - lo).T)] = True
        lab, _ = ndimage.label(box, structure=_STRUCTURE)
        sizes = np.bincount(lab[tuple((cand - lo).T)])
        big = np.flatnonzero(sizes >= max(1, int(min_cluster_voxels)))
        big = big[big > 0]
        counted, clusters = int(sizes[big].sum()), len(big)
    return FreeReturnCounts(len(vox), counted, clusters, 1)


@dataclass(frozen=True)
class LabelCounts:
    """Accumulable voxel counts among voxels with mask_lidar 1: occupied (class < FREE),
    unclassified (UNCLASSIFIED), pedestrian (PEDESTRIAN), pedestrian_no_instance (PEDESTRIAN with
    instance id 0: a person's returns with no fitted body)."""

    occupied: int = 0
    unclassified: int = 0
    pedestrian: int = 0
    pedestrian_no_instance: int = 0

    def __add__(self, other: LabelCounts) -> LabelCounts:
        return LabelCounts(
            self.occupied + other.occupied,
            self.unclassified + other.unclassified,
            self.pedestrian + other.pedestrian,
            self.pedestrian_no_instance + other.pedestrian_no_instance,
        )

    def as_dict(self) -> dict:
        return {
            "unclassified_share": ratio(self.unclassified, self.occupied),
            "occupied_voxels": int(self.occupied),
            "unclassified_voxels": int(self.unclassified),
            "pedestrian_voxels": int(self.pedestrian),
            "pedestrian_voxels_without_body": int(self.pedestrian_no_instance),
        }


def label_counts(
    semantics: np.ndarray, mask_lidar: np.ndarray | None, instances: np.ndarray | None = None
) -> LabelCounts:
    """One frame's :class:`LabelCounts`: semantics (X, Y, Z) uint8 class ids, mask_lidar (X, Y, Z)
    0/1 (None: all), instances (X, Y, Z) uint16 ids (None: pedestrian_no_instance 0)."""
    sem = check_label_grid("semantics", semantics)
    m = check_mask("mask_lidar", mask_lidar, sem.shape)
    s = sem[m]
    ped = s == C.PEDESTRIAN
    no_inst = 0
    if instances is not None:
        inst = np.asarray(instances)
        if inst.shape != sem.shape:
            raise MetricInputError(f"instances: shape {inst.shape}, expected {sem.shape}")
        no_inst = int(np.count_nonzero(ped & (inst[m] == 0)))
    return LabelCounts(
        int(np.count_nonzero(s < C.FREE)),
        int(np.count_nonzero(s == C.UNCLASSIFIED)),
        int(np.count_nonzero(ped)),
        no_inst,
    )
