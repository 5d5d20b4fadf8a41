"""Visibility filter (paper appendix A): backface culling + body-part filtering from keypoints.

Sign convention (fixed here; the paper's text is ambiguous): a face f is *front-facing* when

    n_f . d_f > w,   d_f = (o - c_f) / ||o - c_f||,

with n_f the outward unit normal (counter-clockwise winding seen from outside), c_f the face
centroid and o the camera centre, i.e. d_f points from the face *to the camera*. So ``w`` is the
minimum cosine between the normal and the direction to the viewer: w = 0.2 keeps faces turned
at least ~78 deg towards the camera, w = -1 keeps every face (no culling; the paper's HumanM3
value). This equals the paper's ``n_f . p_f < -w`` with p_f the camera-to-face direction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

#: For each of the 24 SMPL body parts (part(v) = argmax_j skinning weight), the COCO-17
#: keypoints informative for it; the part is occluded when all of them are below J_conf.
SMPL_PART_TO_COCO: tuple[tuple[int, ...], ...] = (
    (11, 12),  # 0 pelvis: hips
    (11, 13),  # 1 left thigh
    (12, 14),  # 2 right thigh
    (5, 6, 11, 12),  # 3 spine1 (lower torso)
    (13, 15),  # 4 left shin
    (14, 16),  # 5 right shin
    (5, 6, 11, 12),  # 6 spine2
    (15,),  # 7 left ankle
    (16,),  # 8 right ankle
    (5, 6),  # 9 spine3 (chest)
    (15,),  # 10 left foot
    (16,),  # 11 right foot
    (0, 1, 2, 3, 4),  # 12 neck
    (5,),  # 13 left collar
    (6,),  # 14 right collar
    (0, 1, 2, 3, 4),  # 15 head
    (5, 7),  # 16 left upper arm
    (6, 8),  # 17 right upper arm
    (7, 9),  # 18 left forearm
    (8, 10),  # 19 right forearm
    (9,),  # 20 left wrist
    (10,),  # 21 right wrist
    (9,),  # 22 left hand
    (10,),  # 23 right hand
)


def vertex_parts(skin_weights) -> np.ndarray:
    """part(v) = argmax_j weights[v, j]. skin_weights (V, 24) -> (V,) int64 in [0, 24)."""
    w = (
        skin_weights.detach().cpu().numpy()
        if torch.is_tensor(skin_weights)
        else np.asarray(skin_weights)
    )
    return np.argmax(w, axis=1).astype(np.int64)


def part_keypoint_matrix(device=None) -> torch.Tensor:
    """(24, 17) bool: entry [b, i] is True when COCO keypoint i informs SMPL part b."""
    m = torch.zeros(24, 17, dtype=torch.bool, device=device)
    for b, ids in enumerate(SMPL_PART_TO_COCO):
        m[b, list(ids)] = True
    return m


@dataclass(frozen=True)
class Visibility:
    """vertex_mask (B, V) bool: visible vertices (front-facing and part not occluded).
    occluded_joints (B, 24) bool: parts / joints flagged occluded by the keypoints.
    front_vertex_mask (B, V) bool: backface culling alone."""

    vertex_mask: torch.Tensor
    occluded_joints: torch.Tensor
    front_vertex_mask: torch.Tensor


def front_facing_faces(
    vertices: torch.Tensor, faces: torch.Tensor, w: float, camera_center=None
) -> torch.Tensor:
    """Backface test per face. vertices (B, V, 3) cam frame (m); faces (F, 3) long.

    camera_center (3,) or (B, 3), default the origin of the cam frame. Returns (B, F) bool,
    True where n_f . (o - c_f)/||o - c_f|| > w (see module docstring).
    """
    v0, v1, v2 = (vertices[:, faces[:, k]] for k in range(3))
    n = torch.linalg.cross(v1 - v0, v2 - v0)
    n = n / n.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    c = (v0 + v1 + v2) / 3.0
    o = (
        torch.zeros(3, dtype=vertices.dtype, device=vertices.device)
        if camera_center is None
        else torch.as_tensor(camera_center, dtype=vertices.dtype, device=vertices.device)
    )
    if o.dim() == 2:
        o = o[:, None, :]
    d = o - c
    d = d / d.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    cos = (n * d).sum(-1)
    if w <= -1.0:
        return torch.ones_like(cos, dtype=torch.bool)
    return cos > w


@torch.no_grad()
def visibility_masks(
    vertices: torch.Tensor,
    faces: torch.Tensor,
    parts: torch.Tensor,
    keypoint_conf: torch.Tensor | None,
    w: float,
    j_conf: float,
    camera_center=None,
) -> Visibility:
    """Visible vertex set V of appendix A.

    vertices (B, V, 3) float, cam frame, m; faces (F, 3) long; parts (V,) long (vertex_parts);
    keypoint_conf (B, 17) float in [0, 1] or None (no part filtering). A vertex is visible when
    it belongs to at least one front-facing face and its part is not occluded, i.e. not all of
    the part's keypoints (SMPL_PART_TO_COCO) have confidence < j_conf.
    """
    B, V, _ = vertices.shape
    faces = faces.to(vertices.device).long()
    parts = parts.to(vertices.device).long()
    front_f = front_facing_faces(vertices, faces, w, camera_center)  # (B, F)
    front_v = torch.zeros(B, V, dtype=torch.int32, device=vertices.device)
    for k in range(3):
        # "any front face" scattered onto the face's vertices
        front_v.scatter_reduce_(
            1, faces[:, k].expand(B, -1), front_f.to(torch.int32), reduce="amax"
        )
    front_v = front_v > 0
    if keypoint_conf is None:
        occluded = torch.zeros(B, 24, dtype=torch.bool, device=vertices.device)
    else:
        conf = keypoint_conf.to(vertices.device)
        m = part_keypoint_matrix(vertices.device)  # (24, 17)
        part_max = torch.where(
            m[None], conf[:, None, :], torch.full_like(conf[:, None, :], -1.0)
        ).amax(-1)
        occluded = part_max < j_conf
    vis = front_v & ~occluded[:, parts]
    return Visibility(vertex_mask=vis, occluded_joints=occluded, front_vertex_mask=front_v)
