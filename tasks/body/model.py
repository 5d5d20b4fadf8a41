"""SMPL-topology body model: linear blend skinning with shape and pose blend shapes (torch).

Frames and units: the template is y-up, metres, the person facing +z with their left along +x
(the SMPL canonical frame). ``BodyModel.forward`` returns vertices and joints in the frame in
which ``global_orient`` and ``transl`` are expressed. As in SMPL, the root rotation acts about
the rest root joint J_0(beta), not the origin:

    v = R_root (v_local - J_0) + J_0 + transl

so moving a fit by a rigid motion (R, t) gives ``transl' = R (J_0 + transl) + t - J_0``
(:func:`rigid_transform_params`).

The model parameters are a dict with the official SMPL keys (see
/work/shared/reference/human-fitting.md): ``v_template`` (V, 3), ``f`` (F, 3), ``shapedirs``
(V, 3, B), ``posedirs`` (V, 3, 207), ``weights`` (V, 24), ``kintree_table`` (2, 24) (root parent
2**32-1), ``J_regressor`` (24, V) dense; optional extra ``coco_vertex_ids`` (5,).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from tasks.body.rotations import axis_angle_to_matrix
from tasks.conventions import COCO_TO_SMPL_VERTEX

NUM_JOINTS = 24
NUM_BODY_JOINTS = 23
NUM_POSE_FEATURES = NUM_BODY_JOINTS * 9
#: Official SMPL vertex ids of the COCO face keypoints (nose, l_eye, r_eye, l_ear, r_ear).
OFFICIAL_COCO_VERTEX_IDS = np.array([COCO_TO_SMPL_VERTEX[i] for i in range(5)], dtype=np.int64)
REQUIRED_KEYS = ("v_template", "f", "shapedirs", "posedirs", "weights", "kintree_table", "J_regressor")


class BodyModelError(ValueError):
    """Body model parameters with a missing key or a wrong shape."""


@dataclass(frozen=True)
class BodyOutput:
    """vertices: (B, V, 3) and joints: (B, 24, 3), metres, frame of the global pose."""

    vertices: Tensor
    joints: Tensor


def _parents_from_kintree(kintree_table: np.ndarray) -> np.ndarray:
    kt = np.asarray(kintree_table).astype(np.int64)
    if kt.shape != (2, NUM_JOINTS):
        raise BodyModelError(f"kintree_table: expected shape (2, 24), got {kt.shape}")
    # The official files store joint ids in row 1 and parents in row 0; the root parent is
    # 2**32 - 1 (an unsigned -1).
    parents = np.full(NUM_JOINTS, -1, dtype=np.int64)
    for parent, child in zip(kt[0], kt[1]):
        parents[child] = -1 if parent >= 2**31 - 1 or parent < 0 else parent
    if parents[0] != -1 or np.any(parents[1:] < 0) or np.any(parents[1:] >= np.arange(1, NUM_JOINTS)):
        raise BodyModelError(f"kintree_table: not a tree rooted at joint 0: parents {parents.tolist()}")
    return parents


def validate_body_params(params: dict[str, np.ndarray]) -> None:
    """Raise BodyModelError naming the key when a required key is missing or mis-shaped."""
    missing = [k for k in REQUIRED_KEYS if k not in params]
    if missing:
        raise BodyModelError(f"body model parameters lack keys {missing}; have {sorted(params)}")
    V = np.shape(params["v_template"])[0]
    expect = {
        "v_template": (V, 3),
        "weights": (V, NUM_JOINTS),
        "J_regressor": (NUM_JOINTS, V),
    }
    for key, shape in expect.items():
        if tuple(np.shape(params[key])) != shape:
            raise BodyModelError(f"{key}: expected shape {shape}, got {tuple(np.shape(params[key]))}")
    sd = np.shape(params["shapedirs"])
    if len(sd) != 3 or sd[:2] != (V, 3):
        raise BodyModelError(f"shapedirs: expected shape ({V}, 3, B), got {sd}")
    pd = np.shape(params["posedirs"])
    if pd != (V, 3, NUM_POSE_FEATURES):
        raise BodyModelError(f"posedirs: expected shape ({V}, 3, 207), got {pd}")
    f = np.shape(params["f"])
    if len(f) != 2 or f[1] != 3:
        raise BodyModelError(f"f: expected shape (F, 3), got {f}")


class BodyModel(torch.nn.Module):
    """SMPL-format body model. Buffers follow ``.to(device, dtype)``; forward follows its inputs.

    Attributes: faces (F, 3) int64; num_vertices; num_betas; parents (24,) int64 with
    parents[0] == -1; keypoint_vertex_ids (5,) int64 (COCO nose, l_eye, r_eye, l_ear, r_ear).
    """

    def __init__(self, params: dict[str, np.ndarray]):
        super().__init__()
        validate_body_params(params)
        self.parents = _parents_from_kintree(params["kintree_table"])
        self.faces = np.asarray(params["f"]).astype(np.int64)
        v_template = np.asarray(params["v_template"], dtype=np.float64)
        self.num_vertices = int(v_template.shape[0])
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= self.num_vertices):
            raise BodyModelError(f"f: vertex ids outside [0, {self.num_vertices})")
        shapedirs = np.asarray(params["shapedirs"], dtype=np.float64)
        self.num_betas = int(shapedirs.shape[2])
        if "coco_vertex_ids" in params:
            ids = np.asarray(params["coco_vertex_ids"]).astype(np.int64).reshape(-1)
        else:
            ids = OFFICIAL_COCO_VERTEX_IDS.copy()
        if ids.shape != (5,) or ids.min() < 0 or ids.max() >= self.num_vertices:
            raise BodyModelError(f"coco_vertex_ids: expected 5 ids in [0, {self.num_vertices}), got {ids}")
        self.keypoint_vertex_ids = ids
        posedirs = np.asarray(params["posedirs"], dtype=np.float64)
        # (V, 3, 207) -> (207, V * 3) so that pose_features @ posedirs gives flat offsets.
        posedirs_flat = posedirs.reshape(-1, NUM_POSE_FEATURES).T.copy()
        f32 = torch.float32
        self.register_buffer("v_template", torch.tensor(v_template, dtype=f32))
        self.register_buffer("shapedirs", torch.tensor(shapedirs, dtype=f32))
        self.register_buffer("posedirs", torch.tensor(posedirs_flat, dtype=f32))
        self.register_buffer(
            "J_regressor", torch.tensor(np.asarray(params["J_regressor"], dtype=np.float64), dtype=f32)
        )
        self.register_buffer(
            "lbs_weights", torch.tensor(np.asarray(params["weights"], dtype=np.float64), dtype=f32)
        )
        self.register_buffer("faces_tensor", torch.tensor(self.faces), persistent=False)
        self.register_buffer("_eye3", torch.eye(3, dtype=f32), persistent=False)
        self._parents_clamped = np.maximum(self.parents, 0)
        depth = np.zeros(NUM_JOINTS, dtype=np.int64)
        for j in range(1, NUM_JOINTS):
            depth[j] = depth[self.parents[j]] + 1
        self._num_levels = int(depth.max())
        for d in range(1, self._num_levels + 1):
            at_depth = depth == d
            self.register_buffer(f"_level{d}_joints", torch.tensor(np.flatnonzero(at_depth)), persistent=False)
            self.register_buffer(f"_level{d}_parents", torch.tensor(self.parents[at_depth]), persistent=False)
        self.register_buffer("_parents_clamped_t", torch.tensor(self._parents_clamped), persistent=False)

    def rest_joints(self, betas: Tensor) -> Tensor:
        """betas (B, L<=num_betas) -> rest-pose joints (B, 24, 3), metres, template frame."""
        v_shaped = self._shaped(betas)
        return torch.einsum("jv,bvc->bjc", self.J_regressor.to(v_shaped), v_shaped)

    def _shaped(self, betas: Tensor) -> Tensor:
        if betas.ndim != 2 or betas.shape[1] > self.num_betas:
            raise ValueError(f"betas: expected (B, <= {self.num_betas}), got {tuple(betas.shape)}")
        L = betas.shape[1]
        v_template = self.v_template.to(betas)
        shapedirs = self.shapedirs[:, :, :L].to(betas)
        return v_template[None] + torch.einsum("bl,vcl->bvc", betas, shapedirs)

    def forward(
        self,
        betas: Tensor,
        global_orient: Tensor,
        body_pose: Tensor,
        transl: Tensor,
        pose2rot: bool = True,
    ) -> BodyOutput:
        """Pose and shape the body.

        betas (B, L<=10); global_orient (B, 3) axis-angle [or (B, 3, 3) with pose2rot=False];
        body_pose (B, 69) or (B, 23, 3) axis-angle [or (B, 23, 3, 3)]; transl (B, 3), metres.
        Returns BodyOutput with vertices (B, V, 3) and posed joints (B, 24, 3), in the frame of
        the global pose; device and dtype of ``betas``.
        """
        B = betas.shape[0]
        dtype, device = betas.dtype, betas.device
        if pose2rot:
            if body_pose.numel() != B * NUM_BODY_JOINTS * 3 or global_orient.numel() != B * 3:
                raise ValueError(
                    f"global_orient / body_pose: expected ({B}, 3) / ({B}, 69) axis-angle, got "
                    f"{tuple(global_orient.shape)} / {tuple(body_pose.shape)}"
                )
            go = global_orient.reshape(B, 1, 3)
            bp = body_pose.reshape(B, NUM_BODY_JOINTS, 3)
            if bp.shape[1] != NUM_BODY_JOINTS:
                raise ValueError(f"body_pose: expected (B, 69) or (B, 23, 3), got {tuple(body_pose.shape)}")
            rot = axis_angle_to_matrix(torch.cat((go, bp), dim=1).to(dtype))
        else:
            if body_pose.numel() != B * NUM_BODY_JOINTS * 9 or global_orient.numel() != B * 9:
                raise ValueError(
                    f"global_orient / body_pose: expected ({B}, 3, 3) / ({B}, 23, 3, 3) rotation "
                    f"matrices, got {tuple(global_orient.shape)} / {tuple(body_pose.shape)}"
                )
            go = global_orient.reshape(B, 1, 3, 3)
            bp = body_pose.reshape(B, NUM_BODY_JOINTS, 3, 3)
            if bp.shape[1] != NUM_BODY_JOINTS:
                raise ValueError(f"body_pose: expected (B, 23, 3, 3), got {tuple(body_pose.shape)}")
            rot = torch.cat((go, bp), dim=1).to(dtype)
        if transl.shape != (B, 3):
            raise ValueError(f"transl: expected ({B}, 3), got {tuple(transl.shape)}")

        v_shaped = self._shaped(betas)  # (B, V, 3)
        J = torch.einsum("jv,bvc->bjc", self.J_regressor.to(v_shaped), v_shaped)  # (B, 24, 3)

        eye = self._eye3.to(rot)
        pose_feat = (rot[:, 1:] - eye).reshape(B, NUM_POSE_FEATURES)
        v_posed = v_shaped + (pose_feat @ self.posedirs.to(v_shaped)).reshape(B, self.num_vertices, 3)

        # Forward kinematics, G_j = G_parent(j) [R_j | J_j - J_parent(j)], one tree level at a
        # time (9 levels instead of 23 joints: fewer, larger kernels on CPU and GPU).
        rel = J - J[:, self._parents_clamped_t.to(device)]  # (B, 24, 3); root row unused
        G_rot_t = rot[:, :1].expand(B, NUM_JOINTS, 3, 3)
        joints = J[:, :1].expand(B, NUM_JOINTS, 3)
        for d in range(1, self._num_levels + 1):
            js = getattr(self, f"_level{d}_joints").to(device)
            ps = getattr(self, f"_level{d}_parents").to(device)
            Rp = G_rot_t[:, ps]
            new_R = Rp @ rot[:, js]
            new_t = joints[:, ps] + (Rp @ rel[:, js, :, None])[..., 0]
            G_rot_t = G_rot_t.index_copy(1, js, new_R)
            joints = joints.index_copy(1, js, new_t)
        # Skinning transform of joint j maps a rest-pose point x to G_rot (x - J_j) + joints_j.
        A_t = joints - (G_rot_t @ J[..., None])[..., 0]  # (B, 24, 3)
        W = self.lbs_weights.to(v_shaped)  # (V, 24)
        T_rot = torch.einsum("vj,bjrc->bvrc", W, G_rot_t)  # (B, V, 3, 3)
        T_t = torch.einsum("vj,bjc->bvc", W, A_t)  # (B, V, 3)
        verts = (T_rot @ v_posed[..., None])[..., 0] + T_t
        t = transl.to(dtype)[:, None, :]
        return BodyOutput(vertices=verts + t, joints=joints + t)


def rigid_transform_params(
    global_orient_R: Tensor, transl: Tensor, J0: Tensor, R: Tensor, t: Tensor
) -> tuple[Tensor, Tensor]:
    """Express a fit in another frame: p' = R p + t.

    global_orient_R (B, 3, 3), transl (B, 3), J0 (B, 3) rest root joint J_0(beta), R (3, 3) or
    (B, 3, 3), t (3,) or (B, 3). Returns (R @ global_orient_R, R (J0 + transl) + t - J0).
    """
    R = R.to(transl).expand(transl.shape[0], 3, 3)
    t = t.to(transl).expand(transl.shape[0], 3)
    new_R = R @ global_orient_R
    new_t = (R @ (J0 + transl)[..., None])[..., 0] + t - J0
    return new_R, new_t
