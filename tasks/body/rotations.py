"""Batched, differentiable rotation conversions (torch), stable at zero angle.

Axis-angle vectors are ``(..., 3)`` in radians (direction = axis, norm = angle); rotation matrices
are ``(..., 3, 3)`` acting on column vectors. Device and dtype follow the input.
"""

from __future__ import annotations

import torch
from torch import Tensor

# Below this squared angle the Taylor series of sin(t)/t and (1-cos t)/t^2 are used: their next
# terms (t^6 / 5040, t^6 / 40320) are then far below float64 precision.
_SMALL_ANGLE_SQ = 1e-6


def _skew(v: Tensor) -> Tensor:
    """(..., 3) -> (..., 3, 3) cross-product matrices [v]_x."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack((o, -z, y, z, o, -x, -y, x, o), dim=-1).reshape(*v.shape, 3)


def axis_angle_to_matrix(aa: Tensor) -> Tensor:
    """Rodrigues' formula. aa: (..., 3) axis-angle, radians -> (..., 3, 3) rotation matrices.

    R = I + a(t) K + b(t) K^2 with K = [aa]_x, a = sin t / t, b = (1 - cos t) / t^2; both
    coefficients switch to their Taylor series near t = 0 so values and gradients stay finite.
    """
    if aa.shape[-1] != 3:
        raise ValueError(f"axis_angle_to_matrix expects (..., 3), got shape {tuple(aa.shape)}")
    t2 = (aa * aa).sum(-1)
    small = t2 < _SMALL_ANGLE_SQ
    t2_safe = torch.where(small, torch.ones_like(t2), t2)
    t = torch.sqrt(t2_safe)
    a = torch.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, torch.sin(t) / t)
    b = torch.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - torch.cos(t)) / t2_safe)
    K = _skew(aa)
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device).expand(K.shape)
    return eye + a[..., None, None] * K + b[..., None, None] * (K @ K)


def matrix_to_quaternion(R: Tensor) -> Tensor:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions (w, x, y, z) with w >= 0.

    Shepperd's method: of the four algebraically equal formulas, each entry uses the one whose
    divisor (4 |q_i|) is largest, so no division by a small number happens.
    """
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"matrix_to_quaternion expects (..., 3, 3), got shape {tuple(R.shape)}")
    m = R
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    # 4 q_i^2 for i = w, x, y, z
    four_sq = torch.stack(
        (
            1.0 + m00 + m11 + m22,
            1.0 + m00 - m11 - m22,
            1.0 - m00 + m11 - m22,
            1.0 - m00 - m11 + m22,
        ),
        dim=-1,
    )
    # candidate quaternions scaled by 4 q_i (row i assumes q_i is the large component)
    cand = torch.stack(
        (
            torch.stack((four_sq[..., 0], m21 - m12, m02 - m20, m10 - m01), -1),
            torch.stack((m21 - m12, four_sq[..., 1], m10 + m01, m02 + m20), -1),
            torch.stack((m02 - m20, m10 + m01, four_sq[..., 2], m12 + m21), -1),
            torch.stack((m10 - m01, m20 + m02, m21 + m12, four_sq[..., 3]), -1),
        ),
        dim=-2,
    )
    idx = four_sq.argmax(-1)
    denom = 2.0 * torch.sqrt(four_sq.clamp_min(0.1))  # = 4 |q_i| for the chosen i (>= ~0.5 there)
    q = cand / denom[..., None]
    q = torch.gather(q, -2, idx[..., None, None].expand(*idx.shape, 1, 4)).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def quaternion_to_axis_angle(q: Tensor) -> Tensor:
    """(..., 4) quaternions (w, x, y, z), any sign -> (..., 3) axis-angle with angle in [0, pi]."""
    q = torch.where(q[..., :1] < 0, -q, q)
    w, v = q[..., 0], q[..., 1:]
    n2 = (v * v).sum(-1)
    small = n2 < _SMALL_ANGLE_SQ
    n = torch.sqrt(torch.where(small, torch.ones_like(n2), n2))
    # angle = 2 atan2(|v|, w); axis-angle = angle / |v| * v. For small |v| (w ~ 1) the factor is
    # 2 / w - (2/3) |v|^2 / w^3 + O(|v|^4).
    w_safe = torch.where(small, w, torch.ones_like(w))
    factor = torch.where(
        small,
        2.0 / w_safe - (2.0 / 3.0) * n2 / w_safe**3,
        2.0 * torch.atan2(n, w) / n,
    )
    return factor[..., None] * v


def matrix_to_axis_angle(R: Tensor) -> Tensor:
    """(..., 3, 3) rotation matrices -> (..., 3) axis-angle, radians, angle in [0, pi]."""
    return quaternion_to_axis_angle(matrix_to_quaternion(R))
