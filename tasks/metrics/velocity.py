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

    def __add__(self, other: "VelocityErrors") -> "VelocityErrors":
        return VelocityErrors(self.sum_o + other.sum_o, self.n_o + other.n_o,
                              self.sum_t + other.sum_t, self.n_t + other.n_t)

    @property
    def ave_o(self) -> float:
        return ratio(self.sum_o, self.n_o)

    @property
    def ave_t(self) -> float:
        return ratio(self.sum_t, self.n_t)

    def as_dict(self) -> dict:
        return {"ave_o": self.ave_o, "ave_t": self.ave_t, "num_voxels_o": int(self.n_o),
                "num_voxels_t": int(self.n_t)}


def voxel_velocity_errors(pred: np.ndarray, pred_velocity: np.ndarray, gt: np.ndarray,
                          gt_velocity: np.ndarray, mask: np.ndarray | None = None
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
        raise MetricInputError(f"velocities: expected (X, Y, Z, D) = {gt.shape} + (D,) for both, "
                               f"got pred {vp.shape} and gt {vg.shape}")
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
