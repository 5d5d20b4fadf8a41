"""Plausible SMPL body poses (69-d axis-angle, float64, radians) for simulation and the prior.

Axes in the SMPL canonical frame (y-up, facing +z, the person's left along +x): a negative
x-rotation of a hip or shoulder swings the limb forward, a positive x-rotation of a knee flexes
it; the shoulders' z-rotation lowers the arms from the T-pose (left: negative, right: positive);
elbow flexion is a negative y-rotation on the left and positive on the right. Body pose index of
joint j (1..23) is ``3 * (j - 1)``.
"""

from __future__ import annotations

import numpy as np

# Joint ids (see tasks.conventions.SMPL_JOINT_NAMES).
L_HIP, R_HIP, SPINE1, L_KNEE, R_KNEE, SPINE2, L_ANKLE, R_ANKLE, SPINE3 = 1, 2, 3, 4, 5, 6, 7, 8, 9
NECK, L_COLLAR, R_COLLAR, HEAD, L_SHOULDER, R_SHOULDER, L_ELBOW, R_ELBOW = (
    12,
    13,
    14,
    15,
    16,
    17,
    18,
    19,
)
L_WRIST, R_WRIST = 20, 21


def _set(pose: np.ndarray, joint: int, aa) -> None:
    pose[3 * (joint - 1) : 3 * joint] = aa


def _rotvec_to_matrix(r: np.ndarray) -> np.ndarray:
    t = np.linalg.norm(r)
    if t < 1e-12:
        return np.eye(3)
    k = r / t
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(t) * K + (1.0 - np.cos(t)) * (K @ K)


def _matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    # Angles here stay well below pi, where the antisymmetric part determines the axis.
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    t = np.arccos(c)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    s = np.sin(t)
    return v * (0.5 if t < 1e-8 else t / (2.0 * s))


def _arm(side: int, lower: float, swing: float, abduct: float = 0.0) -> np.ndarray:
    """Shoulder axis-angle: lower the arm by `lower` rad from the T-pose, then swing it forward
    by `swing` rad (about the parent's x axis). side: +1 left, -1 right."""
    R = _rotvec_to_matrix(np.array([-swing, 0.0, 0.0])) @ _rotvec_to_matrix(
        np.array([0.0, 0.0, -side * (lower - abduct)])
    )
    return _matrix_to_rotvec(R)


def _arms_down(
    pose: np.ndarray, lower: float, swing_l: float, swing_r: float, elbow: float
) -> None:
    _set(pose, L_COLLAR, [0.0, 0.0, -0.12])
    _set(pose, R_COLLAR, [0.0, 0.0, 0.12])
    _set(pose, L_SHOULDER, _arm(+1, lower, swing_l))
    _set(pose, R_SHOULDER, _arm(-1, lower, swing_r))
    _set(pose, L_ELBOW, [0.0, -elbow, 0.0])
    _set(pose, R_ELBOW, [0.0, elbow, 0.0])


def gait_pose(phase: float, speed_mps: float = 1.2) -> np.ndarray:
    """A walking-cycle pose. phase in [0, 1) (0: left heel strike); speed in m/s (0.3-2.5).

    Returns (69,) float64 axis-angle. Amplitudes grow with speed: hip flexion about +-0.3 rad
    and peak swing-phase knee flexion about 1 rad at 1.2 m/s; the arms swing against the legs.
    """
    s = float(np.clip(speed_mps, 0.3, 2.5)) / 1.2
    w = 2.0 * np.pi * float(phase)
    pose = np.zeros(69)
    hip_amp = 0.32 * s**0.6
    knee_peak = 0.95 * s**0.5
    for side, off in ((+1, 0.0), (-1, np.pi)):
        ph = w + off
        hip_flex = hip_amp * np.cos(ph)  # forward at heel strike
        # Swing-phase knee flexion peaks ~70 % into the side's cycle; a small stance flexion.
        knee = 0.08 + knee_peak * np.exp(-((np.angle(np.exp(1j * (ph - 1.4 * np.pi)))) ** 2) / 0.35)
        ankle = 0.15 * np.sin(ph - 0.5)
        hip, kn, an = (L_HIP, L_KNEE, L_ANKLE) if side > 0 else (R_HIP, R_KNEE, R_ANKLE)
        _set(pose, hip, [-hip_flex, 0.0, 0.0])
        _set(pose, kn, [knee, 0.0, 0.0])
        _set(pose, an, [ankle, 0.0, 0.0])
    arm_amp = 0.25 * s
    _arms_down(pose, 1.25, -arm_amp * np.cos(w), arm_amp * np.cos(w), 0.25 + 0.1 * s)
    # Counter-rotation of the thorax and a slight forward lean growing with speed.
    _set(pose, SPINE1, [0.03 * s, 0.0, 0.0])
    _set(pose, SPINE2, [0.02 * s, -0.05 * s * np.cos(w), 0.0])
    _set(pose, SPINE3, [0.0, -0.05 * s * np.cos(w), 0.0])
    return pose


def neutral_pose() -> np.ndarray:
    """Standing upright, arms hanging (lowered 1.25 rad from the T-pose), elbows slightly bent,
    legs straight: the deterministic body pose a weight-free initial estimate starts from
    (tasks.fit.init_lidar). Returns (69,) float64."""
    pose = np.zeros(69)
    _arms_down(pose, 1.25, 0.0, 0.0, 0.25)
    return pose


def standing_pose(rng: np.random.Generator) -> np.ndarray:
    """A relaxed standing pose with random small variations. Returns (69,) float64."""
    pose = np.zeros(69)
    lower = rng.uniform(1.05, 1.4)
    _arms_down(pose, lower, rng.normal(0.0, 0.15), rng.normal(0.0, 0.15), rng.uniform(0.05, 0.5))
    weight_shift = rng.normal(0.0, 0.05)
    _set(pose, L_HIP, [rng.normal(0.0, 0.05), 0.0, weight_shift])
    _set(pose, R_HIP, [rng.normal(0.0, 0.05), 0.0, weight_shift])
    _set(pose, L_KNEE, [abs(rng.normal(0.05, 0.05)), 0.0, 0.0])
    _set(pose, R_KNEE, [abs(rng.normal(0.05, 0.05)), 0.0, 0.0])
    _set(pose, NECK, [rng.normal(0.0, 0.1), rng.normal(0.0, 0.2), 0.0])
    _set(pose, HEAD, [rng.normal(0.0, 0.1), rng.normal(0.0, 0.15), 0.0])
    return pose


def arm_swing_pose(phase: float, rng: np.random.Generator) -> np.ndarray:
    """Standing with one or both arms moving (pointing, waving, reaching): phase in [0, 1).

    Returns (69,) float64.
    """
    pose = standing_pose(rng)
    w = 2.0 * np.pi * float(phase)
    side = +1 if rng.random() < 0.5 else -1
    raise_amt = 0.6 + 0.6 * np.sin(w)  # lower angle from the T-pose: 0 .. 1.2 rad
    fwd = rng.uniform(0.0, 1.2)
    sh, el = (L_SHOULDER, L_ELBOW) if side > 0 else (R_SHOULDER, R_ELBOW)
    _set(pose, sh, _arm(side, raise_amt, fwd))
    flex = rng.uniform(0.1, 1.6)
    _set(pose, el, [0.0, -side * flex, 0.0])
    if rng.random() < 0.3:  # both arms
        sh2, el2 = (R_SHOULDER, R_ELBOW) if side > 0 else (L_SHOULDER, L_ELBOW)
        _set(pose, sh2, _arm(-side, 0.6 + 0.6 * np.cos(w), rng.uniform(0.0, 1.0)))
        _set(pose, el2, [0.0, side * rng.uniform(0.1, 1.4), 0.0])
    return pose


def sample_plausible_poses(
    n: int, rng: np.random.Generator, jitter_rad: float = 0.06
) -> np.ndarray:
    """(n, 69) float64 poses: 50 % gait (random phase, speed 0.6-2.0 m/s), 25 % standing, 25 %
    arm swings, each with Gaussian joint jitter of std ``jitter_rad`` on every coordinate."""
    kinds = rng.choice(3, size=n, p=[0.5, 0.25, 0.25])
    out = np.zeros((n, 69))
    for i, kind in enumerate(kinds):
        if kind == 0:
            out[i] = gait_pose(rng.random(), rng.uniform(0.6, 2.0))
        elif kind == 1:
            out[i] = standing_pose(rng)
        else:
            out[i] = arm_swing_pose(rng.random(), rng)
    return out + rng.normal(0.0, jitter_rad, size=out.shape)
