"""Poses at given stamps from a stamped trajectory: linear in translation, slerp in rotation."""

from __future__ import annotations

import numpy as np

from tasks.poses.rotations import quat_wxyz_to_matrix, quats_wxyz_to_matrices


def slerp(q0: np.ndarray, q1: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (w, x, y, z) between unit q0 and q1 (N, 4) at fractions alpha (N,) in
    [0, 1], along the shorter arc; alpha 0 gives q0 and 1 gives q1 exactly."""
    q0, q1 = np.asarray(q0, np.float64), np.asarray(q1, np.float64).copy()
    alpha = np.asarray(alpha, np.float64)[:, None]
    dot = np.sum(q0 * q1, axis=1)
    q1[dot < 0] *= -1.0  # the shorter arc
    dot = np.abs(dot)[:, None]
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin = np.sin(theta)
    near = sin[:, 0] < 1e-9  # (almost) the same rotation: linear, then normalised
    w0 = np.where(
        near[:, None],
        1.0 - alpha,
        np.sin((1.0 - alpha) * theta) / np.where(near[:, None], 1.0, sin),
    )
    w1 = np.where(near[:, None], alpha, np.sin(alpha * theta) / np.where(near[:, None], 1.0, sin))
    out = w0 * q0 + w1 * q1
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    out[alpha[:, 0] == 0.0] = q0[alpha[:, 0] == 0.0]
    out[alpha[:, 0] == 1.0] = q1[alpha[:, 0] == 1.0]
    return out


def interpolate_poses(
    stamps_ns: np.ndarray,
    translations: np.ndarray,
    quats_wxyz: np.ndarray,
    query_ns: np.ndarray,
    max_gap_ns: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(poses (Q, 4, 4) float64, valid (Q,) bool) at ``query_ns`` (Q,) int64.

    stamps_ns (M,) int64 strictly increasing; translations (M, 3); quats_wxyz (M, 4). A query at
    a sample's stamp gets that sample's pose exactly (the same arithmetic as one quaternion to a
    matrix, so two readers of the same values agree to the bit); between two samples, linear in
    translation and slerp in rotation. Not valid (identity pose): before the first or after the
    last sample, or between two samples more than ``max_gap_ns`` apart.
    """
    stamps = np.asarray(stamps_ns, np.int64)
    query = np.asarray(query_ns, np.int64)
    t = np.asarray(translations, np.float64)
    q = np.asarray(quats_wxyz, np.float64)
    poses = np.tile(np.eye(4), (len(query), 1, 1))
    valid = np.zeros(len(query), bool)
    if len(stamps) == 0 or len(query) == 0:
        return poses, valid
    hi = np.searchsorted(stamps, query, side="left")
    exact = (hi < len(stamps)) & (stamps[np.minimum(hi, len(stamps) - 1)] == query)
    for k in np.flatnonzero(exact):  # at a sample: its values, to the bit
        poses[k, :3, :3] = quat_wxyz_to_matrix(q[hi[k]])
        poses[k, :3, 3] = t[hi[k]]
    valid |= exact
    between = ~exact & (hi > 0) & (hi < len(stamps))
    if max_gap_ns is not None:
        gap = stamps[np.minimum(hi, len(stamps) - 1)] - stamps[np.maximum(hi - 1, 0)]
        between &= gap <= max_gap_ns
    k = np.flatnonzero(between)
    if k.size:
        i0, i1 = hi[k] - 1, hi[k]
        alpha = (query[k] - stamps[i0]).astype(np.float64) / (stamps[i1] - stamps[i0])
        poses[k, :3, 3] = t[i0] + alpha[:, None] * (t[i1] - t[i0])
        poses[k, :3, :3] = quats_wxyz_to_matrices(slerp(q[i0], q[i1], alpha))
        valid[k] = True
    return poses, valid
