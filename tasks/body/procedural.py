"""A procedurally generated body model in the official SMPL format (our own stand-in).

The licensed SMPL files cannot be shipped; tests and the demo use this model instead. It has
SMPL's topology of joints (24 joints, the SMPL kinematic tree) but its own mesh:

1. The rest skeleton is a hand-written T-pose close to SMPL's neutral template (y-up, metres,
   facing +z, left along +x, pelvis at about y = -0.22, ~1.74 m tall).
2. The body is the zero level set of a smooth union of tapered capsules and ellipsoids along the
   bones. Marching tetrahedra (Kuhn's 6-tetrahedra split of each grid cube, which is conforming)
   extract it as ONE closed, consistently oriented triangle mesh; vertices are then relaxed
   tangentially and projected back onto the level set to even out triangle shapes.
3. Skinning weights: a softmax of distances to the bones, restricted to the nearest bone and
   its tree neighbours; rows sum to 1.
4. J_regressor: per joint, non-negative weights (summing to 1) over the surrounding vertices,
   solved with NNLS so that the regressed joint equals the skeleton joint.
5. shapedirs: 10 smooth directions (height, girth, leg length, arm length, shoulder width,
   torso length, body depth, hip width, head size, chest-to-waist ratio), ~1 std each.
6. posedirs: a bulge along the normal in each joint's blend region proportional to
   (1 - cos angle) = -(trace(R) - 3) / 2, linear in the pose features R - I.

Everything is deterministic (the seed only jitters the body proportions slightly).
"""

from __future__ import annotations

import functools

import numpy as np
from scipy.optimize import nnls
from scipy.spatial import cKDTree

from tasks.body.model import NUM_JOINTS, BodyModel
from tasks.conventions import SMPL_PARENTS

#: Rest joints of the T-pose (24, 3), metres, y-up, facing +z, person's left = +x.
REST_JOINTS = np.array(
    [
        [0.000, -0.225, 0.020],  # 0 pelvis
        [0.070, -0.315, 0.010],  # 1 left_hip
        [-0.070, -0.315, 0.010],  # 2 right_hip
        [0.000, -0.115, 0.000],  # 3 spine1
        [0.095, -0.695, 0.010],  # 4 left_knee
        [-0.095, -0.695, 0.010],  # 5 right_knee
        [0.000, 0.020, 0.020],  # 6 spine2
        [0.090, -1.090, -0.030],  # 7 left_ankle
        [-0.090, -1.090, -0.030],  # 8 right_ankle
        [0.000, 0.075, 0.035],  # 9 spine3
        [0.105, -1.145, 0.085],  # 10 left_foot
        [-0.105, -1.145, 0.085],  # 11 right_foot
        [0.000, 0.290, 0.000],  # 12 neck
        [0.075, 0.195, 0.000],  # 13 left_collar
        [-0.075, 0.195, 0.000],  # 14 right_collar
        [0.000, 0.360, 0.045],  # 15 head
        [0.190, 0.235, -0.010],  # 16 left_shoulder
        [-0.190, 0.235, -0.010],  # 17 right_shoulder
        [0.450, 0.225, -0.035],  # 18 left_elbow
        [-0.450, 0.225, -0.035],  # 19 right_elbow
        [0.710, 0.230, -0.040],  # 20 left_wrist
        [-0.710, 0.230, -0.040],  # 21 right_wrist
        [0.795, 0.225, -0.045],  # 22 left_hand
        [-0.795, 0.225, -0.045],  # 23 right_hand
    ],
    dtype=np.float64,
)

# Where a leaf joint's bone ends (for skinning distances): a point beyond the joint.
_LEAF_TIPS = {
    10: np.array([0.110, -1.150, 0.150]),
    11: np.array([-0.110, -1.150, 0.150]),
    15: np.array([0.000, 0.500, 0.040]),
    22: np.array([0.880, 0.220, -0.045]),
    23: np.array([-0.880, 0.220, -0.045]),
}

_GRID_STEP_M = 0.0335
_SMOOTH_K_M = 0.03
_RELAX_ITERS = 6


# ---------------------------------------------------------------- implicit body (signed distance)


def _round_cone(p: np.ndarray, a: np.ndarray, b: np.ndarray, ra: float, rb: float) -> np.ndarray:
    """Approximate signed distance of points p (N, 3) to a capsule from a to b, radius ra -> rb."""
    ab = b - a
    t = np.clip(((p - a) @ ab) / (ab @ ab), 0.0, 1.0)
    d = np.linalg.norm(p - (a + t[:, None] * ab), axis=1)
    return d - (ra + (rb - ra) * t)


def _ellipsoid(p: np.ndarray, c: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Approximate signed distance to an axis-aligned ellipsoid (centre c, radii r)."""
    q = (p - c) / r
    k0 = np.linalg.norm(q, axis=1)
    k1 = np.linalg.norm(q / r, axis=1)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)


def _smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum (C1), blending within distance k."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def _primitives(J: np.ndarray) -> list[tuple]:
    """Shape primitives from the rest joints: ('cone', a, b, ra, rb) or ('ell', c, radii)."""
    prims: list[tuple] = []
    for s in (1, -1):
        i = 0 if s == 1 else 1  # left / right joint offsets
        hip, knee, ankle, foot = J[1 + i], J[4 + i], J[7 + i], J[10 + i]
        prims += [
            ("cone", hip + [0.0, 0.02, 0.0], knee, 0.085, 0.055),
            ("cone", knee, ankle, 0.052, 0.038),
            ("cone", ankle + [0.0, -0.03, -0.045], foot + [0.005 * s, -0.005, 0.06], 0.038, 0.032),
        ]
        col, sho, elb, wri, hand = J[13 + i], J[16 + i], J[18 + i], J[20 + i], J[22 + i]
        prims += [
            ("cone", col, sho, 0.065, 0.055),
            ("cone", sho, elb, 0.05, 0.04),
            ("cone", elb, wri, 0.038, 0.03),
            ("ell", hand + [0.01 * s, 0.0, 0.0], np.array([0.085, 0.028, 0.05])),
        ]
    prims += [
        ("ell", np.array([0.0, -0.27, 0.01]), np.array([0.175, 0.12, 0.115])),  # hips / pelvis
        ("ell", np.array([0.0, -0.09, 0.02]), np.array([0.15, 0.16, 0.11])),  # abdomen
        ("ell", np.array([0.0, 0.11, 0.015]), np.array([0.175, 0.15, 0.115])),  # chest
        ("cone", np.array([0.0, 0.22, 0.0]), np.array([0.0, 0.37, 0.02]), 0.055, 0.05),  # neck
        ("ell", np.array([0.0, 0.45, 0.03]), np.array([0.078, 0.108, 0.098])),  # head
    ]
    return prims


def _body_sdf(p: np.ndarray, prims: list[tuple]) -> np.ndarray:
    d = None
    for prim in prims:
        di = _round_cone(p, *prim[1:]) if prim[0] == "cone" else _ellipsoid(p, *prim[1:])
        d = di if d is None else _smin(d, di, _SMOOTH_K_M)
    return d


def _sdf_gradient(p: np.ndarray, prims: list[tuple], eps: float = 1e-4) -> np.ndarray:
    g = np.empty_like(p)
    for axis in range(3):
        dp = np.zeros(3)
        dp[axis] = eps
        g[:, axis] = (_body_sdf(p + dp, prims) - _body_sdf(p - dp, prims)) / (2 * eps)
    return g


# ---------------------------------------------------------------- marching tetrahedra

# Kuhn split: every cube is cut into 6 tetrahedra along its main diagonal (0,0,0)-(1,1,1); each
# tetrahedron walks from corner 000 to 111 along the axes in one order. The same split in every
# cube makes the triangulations of shared faces agree, so the extracted surface is closed.
_KUHN_TETS = []
for _perm in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
    _c = [np.zeros(3, dtype=np.int64)]
    for _ax in _perm:
        _n = _c[-1].copy()
        _n[_ax] = 1
        _c.append(_n)
    _KUHN_TETS.append(np.stack(_c))
_KUHN_TETS = np.stack(_KUHN_TETS)  # (6, 4, 3) corner offsets


def marching_tetrahedra(values: np.ndarray, origin: np.ndarray, step: float):
    """Zero level set of a sampled scalar field as a closed, outward-oriented triangle mesh.

    values: (nx, ny, nz) float64, negative inside; must be positive on the grid border.
    origin: (3,) position of values[0, 0, 0]; step: grid spacing. Returns vertices (V, 3) float64
    and faces (F, 3) int64 whose normals (right-hand rule) point toward increasing values.
    """
    nx, ny, nz = values.shape
    f = values.ravel()
    # Cube corners: base cube ids (all cubes that straddle the level set).
    inside = values < 0
    ci, cj, ck = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), np.arange(nz - 1), indexing="ij")
    base = np.stack((ci.ravel(), cj.ravel(), ck.ravel()), axis=1)
    corner_in = np.stack(
        [
            inside[base[:, 0] + dx, base[:, 1] + dy, base[:, 2] + dz]
            for dx in (0, 1)
            for dy in (0, 1)
            for dz in (0, 1)
        ],
        axis=1,
    )
    mixed = corner_in.any(1) & ~corner_in.all(1)
    base = base[mixed]
    # Tetrahedra: (T, 4) node ids.
    nodes = base[:, None, None, :] + _KUHN_TETS[None]  # (C, 6, 4, 3)
    ids = (nodes[..., 0] * ny + nodes[..., 1]) * nz + nodes[..., 2]
    tets = ids.reshape(-1, 4)
    tin = f[tets] < 0
    cnt = tin.sum(1)
    tets, tin, cnt = (
        tets[(cnt > 0) & (cnt < 4)],
        tin[(cnt > 0) & (cnt < 4)],
        cnt[(cnt > 0) & (cnt < 4)],
    )

    edge_a: list[np.ndarray] = []
    edge_b: list[np.ndarray] = []
    tri_in: list[np.ndarray] = []  # one inside node and one outside node per triangle
    tri_out: list[np.ndarray] = []

    # Sort each tet's nodes so inside ones come first (stable, keeps the rest in order).
    order = np.argsort(~tin, axis=1, kind="stable")
    st = np.take_along_axis(tets, order, axis=1)
    # One inside node: triangle (a-b, a-c, a-d). Three inside: (d-a, d-b, d-c).
    for n_in in (1, 3):
        s = st[cnt == n_in]
        if n_in == 1:
            lone, others = s[:, 0], s[:, 1:]
            tri_in.append(lone)
            tri_out.append(others[:, 0])
        else:
            lone, others = s[:, 3], s[:, :3]
            tri_in.append(others[:, 0])
            tri_out.append(lone)
        for e in range(3):
            edge_a.append(lone)
            edge_b.append(others[:, e])
    # Two inside (a, b), two outside (c, d): quad a-c, a-d, b-d, b-c -> two triangles.
    s = st[cnt == 2]
    a, b, c, d = s[:, 0], s[:, 1], s[:, 2], s[:, 3]
    for quad_tri in (((a, c), (a, d), (b, d)), ((a, c), (b, d), (b, c))):
        for u, w in quad_tri:
            edge_a.append(u)
            edge_b.append(w)
        tri_in.append(a)
        tri_out.append(c)

    # The loops appended 3 edge slots per triangle group (1 in, 3 in, quad half 1, quad half 2):
    # assemble (F, 3) edge endpoints in the same group order as tri_in / tri_out.
    ea = np.concatenate([np.stack(edge_a[g : g + 3], 1) for g in range(0, 12, 3)])
    eb = np.concatenate([np.stack(edge_b[g : g + 3], 1) for g in range(0, 12, 3)])
    t_in = np.concatenate(tri_in)
    t_out = np.concatenate(tri_out)

    lo, hi = np.minimum(ea, eb), np.maximum(ea, eb)
    key = lo.astype(np.int64) * f.size + hi
    uniq, inv = np.unique(key.ravel(), return_inverse=True)
    faces = inv.reshape(-1, 3).astype(np.int64)
    u_lo, u_hi = uniq // f.size, uniq % f.size

    def pos(node):
        k = node % nz
        j = (node // nz) % ny
        i = node // (ny * nz)
        return origin + step * np.stack((i, j, k), axis=1).astype(np.float64)

    fl, fh = f[u_lo], f[u_hi]
    t = (fl / (fl - fh))[:, None]
    verts = pos(u_lo) + t * (pos(u_hi) - pos(u_lo))

    # Orientation: the normal must point from the inside node toward the outside node.
    v0, v1, v2 = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    n = np.cross(v1 - v0, v2 - v0)
    flip = (n * (pos(t_out) - pos(t_in))).sum(1) < 0
    faces[flip] = faces[flip][:, [0, 2, 1]]
    return verts, faces


# ---------------------------------------------------------------- mesh helpers


def _vertex_neighbours(faces: np.ndarray, n: int):
    e = np.concatenate((faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]))
    e = np.concatenate((e, e[:, ::-1]))
    e = np.unique(e, axis=0)
    return e[:, 0], e[:, 1]


def _vertex_normals(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    fn = np.cross(verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]])
    vn = np.zeros_like(verts)
    for k in range(3):
        np.add.at(vn, faces[:, k], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)


def _largest_component(verts: np.ndarray, faces: np.ndarray):
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(verts)
    e = np.concatenate((faces[:, [0, 1]], faces[:, [1, 2]]))
    g = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    _, labels = connected_components(g, directed=False)
    main = np.bincount(labels[faces[:, 0]]).argmax()
    keep_f = labels[faces[:, 0]] == main
    faces = faces[keep_f]
    used = np.unique(faces)
    remap = np.full(n, -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return verts[used], remap[faces]


def _relax(verts: np.ndarray, faces: np.ndarray, prims: list[tuple], iters: int) -> np.ndarray:
    """Tangential Laplacian smoothing, each step projected back onto the zero level set."""
    src, dst = _vertex_neighbours(faces, len(verts))
    deg = np.bincount(src, minlength=len(verts)).astype(np.float64)
    for _ in range(iters):
        avg = np.zeros_like(verts)
        np.add.at(avg, src, verts[dst])
        avg /= deg[:, None]
        n = _vertex_normals(verts, faces)
        delta = avg - verts
        delta -= (delta * n).sum(1, keepdims=True) * n
        verts = verts + 0.5 * delta
        for _ in range(2):  # Newton steps onto f = 0
            d = _body_sdf(verts, prims)
            g = _sdf_gradient(verts, prims)
            verts = verts - (d / np.maximum((g * g).sum(1), 1e-12))[:, None] * g
    return verts


# ---------------------------------------------------------------- rigging


def _bone_segments(J: np.ndarray) -> list[list[tuple[np.ndarray, np.ndarray]]]:
    """Per joint the segments of its bone(s): joint -> each child, or joint -> tip for leaves."""
    children: dict[int, list[int]] = {j: [] for j in range(NUM_JOINTS)}
    for j, p in enumerate(SMPL_PARENTS):
        if p >= 0:
            children[p].append(j)
    segs = []
    for j in range(NUM_JOINTS):
        if children[j]:
            segs.append([(J[j], J[c]) for c in children[j]])
        else:
            segs.append([(J[j], _LEAF_TIPS[j])])
    return segs


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    t = np.clip(((p - a) @ ab) / max(ab @ ab, 1e-12), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1)


def _skinning_weights(verts: np.ndarray, J: np.ndarray, sigma: float = 0.02) -> np.ndarray:
    segs = _bone_segments(J)
    dist = np.stack(
        [np.min([_segment_distance(verts, a, b) for a, b in s], axis=0) for s in segs], 1
    )
    # Torso bones are thick: compare distances relative to a per-bone radius.
    radius = np.full(NUM_JOINTS, 0.05)
    radius[[0, 3, 6, 9]] = 0.12
    radius[[13, 14]] = 0.06
    radius[[12, 15]] = 0.06
    radius[[1, 2]] = 0.08
    score = dist - radius[None]
    nearest = score.argmin(1)
    adj = np.eye(NUM_JOINTS, dtype=bool)
    for j, p in enumerate(SMPL_PARENTS):
        if p >= 0:
            adj[j, p] = adj[p, j] = True
    mask = adj[nearest]
    logits = -(score - score.min(1, keepdims=True)) / sigma
    w = np.where(mask, np.exp(logits), 0.0)
    return w / w.sum(1, keepdims=True)


def _joint_regressor(verts: np.ndarray, J: np.ndarray, fit_tol_m: float = 5e-4) -> np.ndarray:
    """(24, V) non-negative rows summing to 1 with J_regressor @ verts ~= J (within fit_tol_m).

    Per joint: NNLS over the k nearest vertices with a soft sum-to-one row and a small pull
    toward uniform weights (so weight spreads over a ring instead of a few vertices); k doubles
    until the joint lies inside the reachable hull.
    """
    tree = cKDTree(verts)
    reg = np.zeros((NUM_JOINTS, len(verts)))
    lam, mu = 10.0, 1e-4
    for j in range(NUM_JOINTS):
        k = 40
        while True:
            _, idx = tree.query(J[j], k=min(k, len(verts)))
            P = verts[idx]
            kk = len(idx)
            A = np.vstack((P.T, lam * np.ones((1, kk)), np.sqrt(mu) * np.eye(kk)))
            b = np.concatenate((J[j], [lam], np.sqrt(mu) * np.full(kk, 1.0 / kk)))
            w, _ = nnls(A, b, maxiter=50 * kk)
            w = w / w.sum()
            if np.linalg.norm(w @ P - J[j]) < fit_tol_m or kk >= min(1280, len(verts)):
                break
            k *= 2
        reg[j, idx] = w
    return reg


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _shape_dirs(v: np.ndarray, normals: np.ndarray, W: np.ndarray, J: np.ndarray) -> np.ndarray:
    """(V, 3, 10) smooth shape directions, ~1 standard deviation per unit beta."""
    V = len(v)
    D = np.zeros((V, 3, 10))
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    torso = W[:, [0, 3, 6, 9, 12, 13, 14]].sum(1)
    head = W[:, 15] + 0.5 * W[:, 12]
    # 0 height: uniform scaling about the pelvis joint, +6 % per unit.
    D[:, :, 0] = 0.06 * (v - J[0])
    # 1 girth: push the surface out along its (smooth) normals, more on the torso.
    D[:, :, 1] = (0.012 + 0.02 * torso)[:, None] * normals
    # 2 leg length: stretch everything below the hips downward (feet move 5 cm).
    y_hip, y_sole = J[1, 1], v[:, 1].min()
    D[:, 1, 2] = -0.05 * _smoothstep((y_hip - y) / (y_hip - y_sole))
    # 3 arm length: stretch outward beyond the shoulders (hands move 4 cm).
    x_sh, x_tip = J[16, 0], np.abs(x).max()
    D[:, 0, 3] = np.sign(x) * 0.04 * _smoothstep((np.abs(x) - x_sh) / (x_tip - x_sh))
    # 4 shoulder width: the upper body moves sideways, growing from the midline to the shoulders.
    upper = _smoothstep((y - J[6, 1]) / (J[13, 1] - J[6, 1]))
    D[:, 0, 4] = np.sign(x) * 0.02 * _smoothstep(np.abs(x) / J[16, 0]) * upper
    # 5 torso length: everything above the waist moves up (4 cm at the neck).
    D[:, 1, 5] = 0.04 * _smoothstep((y - J[0, 1]) / (J[12, 1] - J[0, 1]))
    # 6 body depth (front-back): scale z of the torso by 12 %.
    D[:, 2, 6] = 0.12 * (z - J[0, 2]) * torso
    # 7 hip width: the pelvis and legs spread sideways.
    lower = _smoothstep((J[3, 1] - y) / (J[3, 1] - J[1, 1]))
    D[:, 0, 7] = 0.02 * np.tanh(x / 0.05) * lower
    # 8 head size: scale the head about its centre by 8 %.
    c_head = np.array([0.0, 0.45, 0.03])
    D[:, :, 8] = 0.08 * (v - c_head) * head[:, None]
    # 9 chest-to-waist ratio: widen the chest, narrow the waist.
    ramp = np.tanh((y - J[3, 1]) / (J[9, 1] - J[3, 1]))
    D[:, 0, 9] = 0.08 * (x - J[0, 0]) * ramp * torso
    return D


def _pose_dirs(
    verts: np.ndarray, faces: np.ndarray, W: np.ndarray, bulge_m: float = 0.01
) -> np.ndarray:
    """(V, 3, 207): offset = bulge_m * mask_j(v) * (1 - cos angle_j) * normal(v) per joint j."""
    V = len(verts)
    n = _vertex_normals(verts, faces)
    P = np.zeros((V, 3, 23, 9))
    for j in range(1, NUM_JOINTS):
        mask = 4.0 * W[:, j] * W[:, SMPL_PARENTS[j]]
        # 1 - cos t = -(R00 + R11 + R22 - 3) / 2: the diagonal features 0, 4, 8 of R - I.
        for d in (0, 4, 8):
            P[:, :, j - 1, d] = -0.5 * bulge_m * mask[:, None] * n
    return P.reshape(V, 3, 207)


# ---------------------------------------------------------------- public API


def generate_body_model(seed: int = 0) -> dict[str, np.ndarray]:
    """Build the procedural body model (deterministic for a seed).

    Returns the official SMPL keys: v_template (V, 3) float64 metres, f (F, 3) int64,
    shapedirs (V, 3, 10), posedirs (V, 3, 207), weights (V, 24), kintree_table (2, 24) int64 with
    the root parent 2**32 - 1, J_regressor (24, V) dense float64; extras: coco_vertex_ids (5,)
    int64 (nose, l_eye, r_eye, l_ear, r_ear) and J_rest (24, 3). V is about 6,500.
    """
    rng = np.random.default_rng(seed)
    J = REST_JOINTS.copy()
    if seed != 0:
        J = J * (1.0 + 0.02 * rng.standard_normal())
        J[:, 0] *= 1.0 + 0.02 * rng.standard_normal()
    prims = _primitives(J)
    lo = np.array([-0.98, -1.24, -0.21])
    hi = np.array([0.98, 0.62, 0.26])
    h = _GRID_STEP_M
    shape = np.ceil((hi - lo) / h).astype(int) + 1
    axes = [lo[a] + h * np.arange(shape[a]) for a in range(3)]
    P = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    vals = _body_sdf(P, prims).reshape(shape)
    # Keep samples off the level set so no crossing collapses onto a grid node.
    eps = 0.02 * h
    vals = np.where(np.abs(vals) < eps, np.where(vals < 0, -eps, eps), vals)
    verts, faces = marching_tetrahedra(vals, lo, h)
    verts, faces = _largest_component(verts, faces)
    verts = _relax(verts, faces, prims, _RELAX_ITERS)

    weights = _skinning_weights(verts, J)
    J_regressor = _joint_regressor(verts, J)
    shapedirs = _shape_dirs(verts, _vertex_normals(verts, faces), weights, J)
    posedirs = _pose_dirs(verts, faces, weights)
    kintree = np.zeros((2, NUM_JOINTS), dtype=np.int64)
    kintree[0] = [2**32 - 1 if p < 0 else p for p in SMPL_PARENTS]
    kintree[1] = np.arange(NUM_JOINTS)
    tree = cKDTree(verts)
    # Face keypoints (nose, l_eye, r_eye, l_ear, r_ear): nearest vertices to points on the head.
    targets = np.array(
        [
            [0.0, 0.445, 0.14],
            [0.032, 0.475, 0.13],
            [-0.032, 0.475, 0.13],
            [0.08, 0.45, 0.03],
            [-0.08, 0.45, 0.03],
        ]
    ) + (J[15] - REST_JOINTS[15])
    coco_ids = tree.query(targets)[1].astype(np.int64)
    return {
        "v_template": verts,
        "f": faces,
        "shapedirs": shapedirs,
        "posedirs": posedirs,
        "weights": weights,
        "kintree_table": kintree,
        "J_regressor": J_regressor,
        "coco_vertex_ids": coco_ids,
        "J_rest": J,
    }


@functools.lru_cache(maxsize=4)
def _cached_params(seed: int) -> dict[str, np.ndarray]:
    params = generate_body_model(seed)
    for a in params.values():
        a.setflags(write=False)
    return params


def default_body_params(seed: int = 0) -> dict[str, np.ndarray]:
    """The procedural model's parameters, memoised per process (read-only arrays)."""
    return _cached_params(seed)


@functools.lru_cache(maxsize=1)
def default_body_model() -> BodyModel:
    """The procedural body model (seed 0) as a float32 CPU BodyModel, memoised per process.

    Callers that move it to another device or dtype should use ``copy.deepcopy`` first or build
    their own with ``BodyModel(default_body_params())``.
    """
    return BodyModel(default_body_params(0))
