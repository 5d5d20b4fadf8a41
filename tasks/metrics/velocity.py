"""Absolute velocity error (AVE, m/s) of pedestrian voxels (the paper's Tab. panoptic / velocity).

- AVE-O: mean ||v_pred - v_gt|| over voxels that are pedestrian in both prediction and ground truth.
- AVE-T: mean ||v_pred - v_gt|| over all ground-truth pedestrian voxels; where the prediction does
  not label the voxel pedestrian its velocity counts as zero, so the error is ||v_gt||.
Velocities are per voxel in the base frame (vx, vy) or (vx, vy, vz), m/s. Add counts over frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tasks import conventions as C
from tasks.metrics._common import MetricInputError, check_label_grid, check_mask, ratio


@dataclass(frozen=True)
class VelocityErrors:
    """Sums of errors (m/s) and voxel counts behind AVE-O / AVE-T; add over frames."""

    sum_o: float = 0.0
    n_o: int = 0
    sum_t: float = 0.0
    n_t: int = 0

    def __add__(self, other: VelocityErrors) -> VelocityErrors:
        return VelocityErrors(
            self.sum_o + other.sum_o,
            self.n_o + other.n_o,
            self.sum_t + other.sum_t,
            self.n_t + other.n_t,
        )

    @property
    def ave_o(self) -> float:
        return ratio(self.sum_o, self.n_o)

    @property
    def ave_t(self) -> float:
        return ratio(self.sum_t, self.n_t)

    def as_dict(self) -> dict:
        return {
            "ave_o": self.ave_o,
            "ave_t": self.ave_t,
            "num_voxels_o": int(self.n_o),
            "num_voxels_t": int(self.n_t),
        }


def voxel_velocity_errors(
    pred: np.ndarray,
    pred_velocity: np.ndarray,
    gt: np.ndarray,
    gt_velocity: np.ndarray,
    mask: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-voxel errors (m/s) for histograms: (errors over both-pedestrian voxels (K,),
    errors over all GT pedestrian voxels (M,)) float64, C order over [x, y, z].

    pred, gt: (X, Y, Z) class ids (0 pedestrian); pred_velocity, gt_velocity: (X, Y, Z, D) float
    m/s, D = 2 or 3, base-frame axes; mask: (X, Y, Z) bool evaluated voxels or None (all).
    """
    gt = check_label_grid("gt", gt)
    pred = check_label_grid("pred", pred, gt.shape)
    m = check_mask("mask", mask, gt.shape)
    vp = np.asarray(pred_velocity, dtype=np.float64)
    vg = np.asarray(gt_velocity, dtype=np.float64)
    if vp.shape != vg.shape or vp.shape[:3] != gt.shape or vp.ndim != 4:
        raise MetricInputError(
            f"velocities: expected (X, Y, Z, D) = {gt.shape} + (D,) for both, "
            f"got pred {vp.shape} and gt {vg.shape}"
        )
    gt_ped = (gt == C.PEDESTRIAN) & m
    both = gt_ped & (pred == C.PEDESTRIAN)
    err_o = np.linalg.norm(vp[both] - vg[both], axis=-1)
    v_pred_t = np.where(both[gt_ped][:, None], vp[gt_ped], 0.0)
    err_t = np.linalg.norm(v_pred_t - vg[gt_ped], axis=-1)
    return err_o, err_t


def velocity_errors(pred, pred_velocity, gt, gt_velocity, mask=None) -> VelocityErrors:
    """AVE counts of one frame (arrays as in :func:`voxel_velocity_errors`)."""
    err_o, err_t = voxel_velocity_errors(pred, pred_velocity, gt, gt_velocity, mask)
    return VelocityErrors(float(err_o.sum()), len(err_o), float(err_t.sum()), len(err_t))


# ---- per limb, against per-vertex ground truth -----------------------------------------------------

#: the limb groups of a body; a vertex belongs to the group of its most weighted skinning joint
LIMB_GROUPS = ("legs", "arms", "torso")
#: SMPL joint (tasks.conventions.SMPL_JOINT_NAMES) -> index into LIMB_GROUPS: hips, knees, ankles and
#: feet are legs; shoulders, elbows, wrists and hands arms; pelvis, spine, neck, collars and head torso
SMPL_JOINT_LIMB = np.array(
    [2, 0, 0, 2, 0, 0, 2, 0, 0, 2, 0, 0, 2, 2, 2, 2, 1, 1, 1, 1, 1, 1, 1, 1], np.int64
)


def vertex_limb_groups(lbs_weights: np.ndarray) -> np.ndarray:
    """(V,) int64 index into LIMB_GROUPS of each vertex, from skinning weights (V, 24) float."""
    w = np.asarray(lbs_weights, np.float64)
    if w.ndim != 2 or w.shape[1] != len(SMPL_JOINT_LIMB):
        raise MetricInputError(f"lbs_weights: expected (V, {len(SMPL_JOINT_LIMB)}), got {w.shape}")
    return SMPL_JOINT_LIMB[np.argmax(w, axis=1)]


def vertex_velocity_grid(
    spec,
    instance_grid: np.ndarray,
    track_ids: np.ndarray,
    vertices: np.ndarray,
    faces: np.ndarray,
    vertex_velocity: np.ndarray,
    vertex_group: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth velocity and limb group of every pedestrian voxel from per-vertex velocities.

    spec: the grid (tasks.occupancy.grid.GridSpec, base frame). instance_grid (X, Y, Z) int: the
    track id owning each voxel (0 none). Per person k of track_ids (K,): vertices (K, V, 3) float
    metres, base frame, faces (F, 3), vertex_velocity (K, V, D) float m/s, base axes; vertex_group
    (V,) int (:func:`vertex_limb_groups`). A voxel's velocity is the mean over the body surface in
    it (:func:`tasks.occupancy.fuse.mesh_voxel_velocity`, the rule the fuse stage labels with);
    its group is that of the vertex nearest its centre. Returns (velocity (X, Y, Z, D) float64,
    zero off pedestrians; group (X, Y, Z) int8, -1 off pedestrians).
    """
    from scipy.spatial import cKDTree

    from tasks.occupancy.fuse import mesh_voxel_velocity

    inst = np.asarray(instance_grid)
    vel = np.asarray(vertex_velocity, np.float64)
    out = np.zeros(inst.shape + (vel.shape[-1],))
    group = np.full(inst.shape, -1, np.int8)
    for k, tid in enumerate(np.asarray(track_ids).reshape(-1)):
        voxels = np.argwhere(inst == tid)
        if not len(voxels) or tid == 0:
            continue
        _, v = mesh_voxel_velocity(spec, vertices[k], faces, vel[k], voxels)
        out[tuple(voxels.T)] = v
        _, nearest = cKDTree(np.asarray(vertices[k], np.float64)).query(spec.center_of(voxels))
        group[tuple(voxels.T)] = np.asarray(vertex_group)[nearest]
    return out, group


def limb_velocity_errors(
    pred, pred_velocity, gt, gt_velocity, group: np.ndarray, mask=None
) -> dict[str, VelocityErrors]:
    """AVE counts of one frame per limb group (LIMB_GROUPS; group (X, Y, Z) int, the group of
    each ground-truth pedestrian voxel, -1 elsewhere); arrays as in :func:`voxel_velocity_errors`."""
    m = np.ones(np.shape(gt), bool) if mask is None else np.asarray(mask, bool)
    return {
        name: velocity_errors(pred, pred_velocity, gt, gt_velocity, m & (np.asarray(group) == g))
        for g, name in enumerate(LIMB_GROUPS)
    }
