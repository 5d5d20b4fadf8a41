"""SMPL-topology body model: linear blend skinning with shape and pose blend shapes (torch).

Frames and units: the template is y-up, metres, the person facing +z with their left along +x
(the SMPL canonical frame). ``BodyModel.forward`` returns vertices and joints in the frame in
which ``global_orient`` and ``transl`` are expressed. As in SMPL, the root rotation acts about
the rest root joint J_0(beta), not the origin:

    v = R_root (v_local - J_0) + J_0 + transl

so moving a fit by a rigid motion (R, t) gives ``transl' = R (J_0 + transl) + t - J_0``
(:func:`rigid_transform_params`).

The model parameters are a dict with the keys of the official SMPL model files (as SMPL's release
and the ``smplx`` package, github.com/vchoutas/smplx ``smplx/body_models.py``, read them):
``v_template`` (V, 3), ``f`` (F, 3), ``shapedirs``
(V, 3, B), ``posedirs`` (V, 3, 207), ``weights`` (V, 24), ``kintree_table`` (2, 24) (root parent
2**32-1), ``J_regressor`` (24, V) dense; optional extra ``coco_vertex_ids`` (5,).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from tasks.body.rotations import axis_angle_to_matrix
from tasks.conventions import COCO_TO_SMPL_VERTEX, SMPL_MODEL_KEYS

NUM_JOINTS = 24
NUM_BODY_JOINTS = 23
NUM_POSE_FEATURES = NUM_BODY_JOINTS * 9
#: Official SMPL vertex ids of the COCO face keypoints (nose, l_eye, r_eye, l_ear, r_ear).
OFFICIAL_COCO_VERTEX_IDS = np.array([COCO_TO_SMPL_VERTEX[i] for i in range(5)], dtype=np.int64)


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
    if (
        parents[0] != -1
        or np.any(parents[1:] < 0)
        or np.any(parents[1:] >= np.arange(1, NUM_JOINTS))
    ):
        raise BodyModelError(
            f"kintree_table: not a tree rooted at joint 0: parents {parents.tolist()}"
        )
    return parents


def validate_body_params(params: dict[str, np.ndarray]) -> None:
    """Raise BodyModelError naming the key when a required key is missing or mis-shaped."""
    missing = [k for k in SMPL_MODEL_KEYS if k not in params]
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
            raise BodyModelError(
                f"{key}: expected shape {shape}, got {tuple(np.shape(params[key]))}"
            )
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
            raise BodyModelError(
                f"coco_vertex_ids: expected 5 ids in [0, {self.num_vertices}), got {ids}"
            )
        self.keypoint_vertex_ids = ids
        posedirs = np.asarray(params["posedirs"], dtype=np.float64)
        # (V, 3, 207) -> (207, V * 3) so that pose_features @ posedirs gives flat offsets.
        posedirs_flat = posedirs.reshape(-1, NUM_POSE_FEATURES).T.copy()
        f32 = torch.float32
        self.register_buffer("v_template", torch.tensor(v_template, dtype=f32))
        self.register_buffer("shapedirs", torch.tensor(shapedirs, dtype=f32))
        self.register_buffer("posedirs", torch.tensor(posedirs_flat, dtype=f32))
        self.register_buffer(
            "J_regressor",
            torch.tensor(np.asarray(params["J_regressor"], dtype=np.float64), dtype=f32),
        )
        self.register_buffer(
            "lbs_weights", torch.tensor(np.asarray(params["weights"], dtype=np.float64), dtype=f32)
        )
        J_regressor = np.asarray(params["J_regressor"], dtype=np.float64)
        # float64 on purpose: the joints' shape basis, formed once (see rest_joints)
        self.register_buffer("J_template", torch.tensor(J_regressor @ v_template), persistent=False)
        self.register_buffer(
            "J_shapedirs",
            torch.tensor(np.einsum("jv,vcl->jcl", J_regressor, shapedirs)),
            persistent=False,
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
            self.register_buffer(
                f"_level{d}_joints", torch.tensor(np.flatnonzero(at_depth)), persistent=False
            )
            self.register_buffer(
                f"_level{d}_parents", torch.tensor(self.parents[at_depth]), persistent=False
            )
        self.register_buffer(
            "_parents_clamped_t", torch.tensor(self._parents_clamped), persistent=False
        )

    def rest_joints(self, betas: Tensor) -> Tensor:
        """betas (B, L<=num_betas) -> rest-pose joints (B, 24, 3), metres, template frame.

        J = J_regressor (v_template + shapedirs beta), evaluated as J_template + J_shapedirs beta
        with both products formed once in float64 (24 x 3 x L instead of V x 3 x L per call)."""
        if betas.ndim != 2 or betas.shape[1] > self.num_betas:
            raise ValueError(f"betas: expected (B, <= {self.num_betas}), got {tuple(betas.shape)}")
        L = betas.shape[1]
        return self.J_template.to(betas)[None] + torch.einsum(
            "jcl,bl->bjc", self.J_shapedirs[:, :, :L].to(betas), betas
        )

    def select_vertices(self, vertex_ids: Tensor) -> VertexSubset:
        """The model's per-vertex data at vertex_ids (B, N) long (a different subset per person),
        for :meth:`forward` with ``vertex_subset``: evaluating only the vertices a loss needs."""
        ids = vertex_ids.to(self.v_template.device).long()
        return VertexSubset(ids=ids, weights=self.lbs_weights[ids].transpose(1, 2).contiguous())

    def forward(
        self,
        betas: Tensor,
        global_orient: Tensor,
        body_pose: Tensor,
        transl: Tensor,
        pose2rot: bool = True,
        vertex_subset: VertexSubset | None = None,
        pose_offsets: Tensor | None = None,
    ) -> BodyOutput:
        """Pose and shape the body.

        betas (B, L<=10); global_orient (B, 3) axis-angle [or (B, 3, 3) with pose2rot=False];
        body_pose (B, 69) or (B, 23, 3) axis-angle [or (B, 23, 3, 3)]; transl (B, 3), metres.
        Returns BodyOutput with vertices (B, V, 3) and posed joints (B, 24, 3), in the frame of
        the global pose; device and dtype of ``betas``. With ``vertex_subset`` (from
        :meth:`select_vertices`, B rows) only those vertices are posed: vertices (B, N, 3).
        pose_offsets (B, V, 3): pose blend-shape offsets to use instead of forming them from this
        pose (:meth:`pose_offsets`; an optimiser may hold them fixed for a few steps).
        """
        B = betas.shape[0]
        dtype = betas.dtype
        rot = self._rotations(B, global_orient, body_pose, pose2rot).to(dtype)
        if transl.shape != (B, 3):
            raise ValueError(f"transl: expected ({B}, 3), got {tuple(transl.shape)}")
        J = self.rest_joints(betas)  # (B, 24, 3)
        G_rot, joints = self._kinematics(rot, J)
        # Skinning transform of joint j, [G_rot | joints_j - G_rot J_j] (B, 24, 3, 4), maps a
        # rest-pose point x to G_rot (x - J_j) + joints_j.
        A = torch.cat((G_rot, (joints - (G_rot @ J[..., None])[..., 0])[..., None]), dim=-1)
        if pose_offsets is None:
            pose_offsets = self._pose_offsets(rot)
        elif pose_offsets.shape != (B, self.num_vertices, 3):
            raise ValueError(
                f"pose_offsets: expected ({B}, {self.num_vertices}, 3), got {tuple(pose_offsets.shape)}"
            )
        # Shape blend shapes of every vertex as one matrix product (B, L) x (L, 3V): cheaper than
        # gathering per-person rows of the basis (memory-bound) for a vertex subset.
        L = betas.shape[1]
        v_posed = (
            self.v_template.to(dtype)[None]
            + pose_offsets.to(dtype)
            + torch.einsum("bl,vcl->bvc", betas, self.shapedirs[:, :, :L].to(dtype))
        )
        A = A.reshape(B, NUM_JOINTS, 12)
        t = transl.to(dtype)[:, None, :]
        if vertex_subset is not None:
            s = vertex_subset
            if s.ids.shape[0] != B:
                raise ValueError(f"vertex_subset: {s.ids.shape[0]} rows for {B} persons")
            # vertices last (B, 12, N) = A^T W^T: the long axis innermost makes the batched
            # product and the per-coordinate products below twice as fast on the CPU as (B, N,
            # 12), with the same sums (each entry is one dot product over the 24 joints)
            v_t = torch.gather(v_posed.transpose(1, 2), 2, s.ids[:, None, :].expand(-1, 3, -1))
            c0, c1, c2, c3 = (
                (A.transpose(1, 2) @ s.weights.to(dtype)).unflatten(1, (3, 4)).unbind(2)
            )
            x, y, z = (c[:, None, :] for c in v_t.unbind(1))
            verts = (c0 * x + c1 * y + c2 * z + c3).transpose(1, 2).contiguous()
            return BodyOutput(vertices=verts + t, joints=joints + t)
        T = torch.einsum("vj,bjk->bvk", self.lbs_weights.to(dtype), A)  # (B, V, 12)
        # v = T[:, :3] v_posed + T[:, 3], one column at a time: a batched matmul of B x V tiny
        # 3 x 3 matrices, or a sum over a last axis of 3, is several times slower on the CPU;
        # unbind (not slicing) keeps the backward pass to one stack instead of zero-filled copies
        c0, c1, c2, c3 = T.unflatten(-1, (3, 4)).unbind(-1)
        x, y, z = (c[..., None] for c in v_posed.unbind(-1))
        verts = c0 * x + c1 * y + c2 * z + c3
        return BodyOutput(vertices=verts + t, joints=joints + t)

    def pose_offsets(self, global_orient: Tensor, body_pose: Tensor) -> Tensor:
        """Pose blend-shape offsets (B, V, 3) of axis-angle poses global_orient (B, 3), body_pose
        (B, 69) (the root's rotation does not enter), in the rest frame, metres."""
        B = body_pose.shape[0]
        return self._pose_offsets(self._rotations(B, global_orient, body_pose, True))

    def _pose_offsets(self, rot: Tensor) -> Tensor:
        # (B, 207) x (207, 3V): the largest product of a forward pass (a per-person subset of
        # posedirs would be a memory-bound gather of 207 x 3 floats per vertex)
        B = rot.shape[0]
        pose_feat = (rot[:, 1:] - self._eye3.to(rot)).reshape(B, NUM_POSE_FEATURES)
        return (pose_feat @ self.posedirs.to(rot.dtype)).reshape(B, self.num_vertices, 3)

    @staticmethod
    def _rotations(B: int, global_orient: Tensor, body_pose: Tensor, pose2rot: bool) -> Tensor:
        """Validated joint rotation matrices (B, 24, 3, 3)."""
        if pose2rot:
            if body_pose.numel() != B * NUM_BODY_JOINTS * 3 or global_orient.numel() != B * 3:
                raise ValueError(
                    f"global_orient / body_pose: expected ({B}, 3) / ({B}, 69) axis-angle, got "
                    f"{tuple(global_orient.shape)} / {tuple(body_pose.shape)}"
                )
            aa = torch.cat(
                (global_orient.reshape(B, 1, 3), body_pose.reshape(B, NUM_BODY_JOINTS, 3)), dim=1
            )
            return axis_angle_to_matrix(aa)
        if body_pose.numel() != B * NUM_BODY_JOINTS * 9 or global_orient.numel() != B * 9:
            raise ValueError(
                f"global_orient / body_pose: expected ({B}, 3, 3) / ({B}, 23, 3, 3) rotation "
                f"matrices, got {tuple(global_orient.shape)} / {tuple(body_pose.shape)}"
            )
        return torch.cat(
            (global_orient.reshape(B, 1, 3, 3), body_pose.reshape(B, NUM_BODY_JOINTS, 3, 3)), dim=1
        )

    def _kinematics(self, rot: Tensor, J: Tensor) -> tuple[Tensor, Tensor]:
        """Forward kinematics, G_j = G_parent(j) [R_j | J_j - J_parent(j)], one tree level at a
        time (9 levels instead of 23 joints: fewer, larger kernels on CPU and GPU). rot (B, 24,
        3, 3), J (B, 24, 3) rest joints -> global rotations (B, 24, 3, 3), posed joints (B, 24, 3)."""
        B, device = rot.shape[0], rot.device
        rel = J - J[:, self._parents_clamped_t.to(device)]  # (B, 24, 3); root row unused
        G_rot = rot[:, :1].expand(B, NUM_JOINTS, 3, 3)
        joints = J[:, :1].expand(B, NUM_JOINTS, 3)
        for d in range(1, self._num_levels + 1):
            js = getattr(self, f"_level{d}_joints").to(device)
            ps = getattr(self, f"_level{d}_parents").to(device)
            Rp = G_rot[:, ps]
            G_rot = G_rot.index_copy(1, js, Rp @ rot[:, js])
            joints = joints.index_copy(1, js, joints[:, ps] + (Rp @ rel[:, js, :, None])[..., 0])
        return G_rot, joints


@dataclass(frozen=True)
class VertexSubset:
    """Per-person vertex subset of a BodyModel (:meth:`BodyModel.select_vertices`): ids (B, N)
    int64 and their skinning weights, transposed (B, 24, N), gathered once, so that skinning touches N
    instead of V vertices per person (the blend shapes are still formed for all V)."""

    ids: Tensor
    weights: Tensor

    def take(self, rows: Tensor) -> VertexSubset:
        """The subset of some persons, rows (K,) int64."""
        return VertexSubset(self.ids[rows], self.weights[rows])


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
