"""Per-frame fusion: exact voxel states on analytic scenes (a plane, a box, a body-like box mesh)."""

from __future__ import annotations

import numpy as np
import pytest

from tasks.conventions import FREE, OTHER_STRUCTURE, PEDESTRIAN, ROAD, TERRAIN, VEGETATION
from tasks.occupancy.frame import relative_pose
from tasks.occupancy.freespace import OccupancyMap
from tasks.occupancy.fuse import (
    CameraView,
    FrameGrids,
    PedestrianMesh,
    fuse_frame,
    surface_points,
    voxelize_labels,
    voxelize_mesh,
)
from tasks.occupancy.grid import GridError, GridSpec
from tasks.occupancy.settings import FreeSpaceParams, FuseSettings
from tasks.occupancy.synthetic import box_mesh
from tasks.occupancy.visibility import camera_mask, lidar_mask

SPEC = GridSpec((0.0, -1.0, 0.0), (3.0, 1.0, 2.0), 0.1)  # 30 x 20 x 20


def _box(lo, hi):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    m = box_mesh((lo + hi) / 2, hi - lo)
    return np.asarray(m.vertices), np.asarray(m.triangles)


def _idx_box(lo, hi):
    ax = [np.arange(a, b + 1) for a, b in zip(lo, hi)]
    return {tuple(i) for i in np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)}


def test_relative_pose_of_a_frame_stack():
    """T_world_from_base from T_world_from_lidar and T_base_from_lidar: a quarter turn about z and
    a shift; one pose or a stack of them against one."""
    T_base_from_lidar = np.eye(4)
    T_base_from_lidar[:3, 3] = [0.5, 0.0, 1.2]
    T_world_from_base = np.eye(4)
    T_world_from_base[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    T_world_from_base[:3, 3] = [10.0, 2.0, 0.0]
    T_world_from_lidar = T_world_from_base @ T_base_from_lidar
    assert np.allclose(relative_pose(T_world_from_lidar, T_base_from_lidar), T_world_from_base)
    np.testing.assert_allclose(T_world_from_lidar[:3, 3], [10.0, 2.5, 1.2])
    stack = relative_pose(np.stack([T_world_from_lidar, T_base_from_lidar]), T_base_from_lidar)
    assert stack.shape == (2, 4, 4) and np.allclose(stack, [T_world_from_base, np.eye(4)])


def test_grid_spec_shapes_and_errors():
    assert GridSpec((0.4, -4.8, -1.0), (10.0, 4.8, 3.8), 0.2).shape == (48, 48, 24)
    assert GridSpec((0.4, -4.8, -1.0), (10.0, 4.8, 3.8), 0.02).shape == (480, 480, 240)
    np.testing.assert_array_equal(SPEC.index_of([[0.05, -0.95, 1.99]]), [[0, 0, 19]])
    with pytest.raises(GridError, match="whole number"):
        GridSpec((0, 0, 0), (1.0, 1.0, 1.05), 0.1)


def test_majority_label_and_ties():
    c = SPEC.center_of([[3, 4, 5], [6, 7, 8]])
    pts = np.concatenate([np.repeat(c[:1], 5, 0), np.repeat(c[1:], 4, 0)])
    lab = np.array([VEGETATION] * 2 + [ROAD] * 3 + [TERRAIN] * 2 + [OTHER_STRUCTURE] * 2, np.uint8)
    flat, label = voxelize_labels(SPEC, pts, lab)
    assert dict(zip(flat.tolist(), label.tolist())) == {
        SPEC.flat_index([[3, 4, 5]])[0]: ROAD,  # 3 votes beat 2
        SPEC.flat_index([[6, 7, 8]])[0]: OTHER_STRUCTURE,  # 2 : 2, the lower id wins
    }


def test_box_on_plane_static_voxels_exact():
    """A road plane (z in voxel 0) and a building box: static voxels take the map's labels, the
    rest is free."""
    xs, ys = np.meshgrid(np.arange(0.05, 3.0, 0.1), np.arange(-0.95, 1.0, 0.1), indexing="ij")
    plane = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 0.05)], 1)
    box = SPEC.center_of(np.array(sorted(_idx_box((10, 5, 1), (12, 7, 4)))))
    pts = np.concatenate([plane, box])
    lab = np.concatenate([np.full(len(plane), ROAD), np.full(len(box), OTHER_STRUCTURE)]).astype(
        np.uint8
    )
    # a yawed pose: give the points in the world, the grid in the base frame
    yaw, t = 0.4, np.array([5.0, -2.0, 0.3])
    R = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    g = fuse_frame(
        SPEC, T, static_points_world=(pts @ R.T + t).astype(np.float32), static_labels=lab
    )
    assert isinstance(g, FrameGrids)
    assert g.semantics.shape == SPEC.shape and g.semantics.dtype == np.uint8
    assert (g.semantics[:, :, 0] == ROAD).all()
    occ = {tuple(i) for i in np.argwhere(g.semantics == OTHER_STRUCTURE)}
    assert occ == _idx_box((10, 5, 1), (12, 7, 4))
    assert (g.semantics == FREE).sum() == SPEC.num_voxels - 30 * 20 - len(occ)
    assert (g.instances == 0).all() and (g.occupancy_state == -1).all()


def test_pedestrian_volume_filled_and_over_static():
    # body-like closed box 0.36 x 0.36 x 1.56 m, faces off the voxel faces
    v, f = _box((1.02, -0.18, 0.02), (1.38, 0.18, 1.58))
    idx = voxelize_mesh(SPEC, v, f)
    expected = _idx_box((10, 8, 0), (13, 11, 15))
    assert {tuple(i) for i in idx} == expected
    # a 1 m cube: the interior (far from any surface sample) is filled too
    v2, f2 = _box((0.52, -0.48, 0.52), (1.48, 0.48, 1.48))
    assert {tuple(i) for i in voxelize_mesh(SPEC, v2, f2)} == _idx_box((5, 5, 5), (14, 14, 14))
    static = SPEC.center_of([[11, 9, 3], [20, 9, 3]]).astype(np.float32)
    g = fuse_frame(
        SPEC,
        np.eye(4),
        static_points_world=static,
        static_labels=np.array([VEGETATION, VEGETATION], np.uint8),
        pedestrians=[PedestrianMesh(7, v, f, np.array([0.5, -1.25]))],
    )
    ped = {tuple(i) for i in np.argwhere(g.semantics == PEDESTRIAN)}
    assert ped == expected
    assert g.semantics[20, 9, 3] == VEGETATION and g.semantics[11, 9, 3] == PEDESTRIAN
    assert set(np.unique(g.instances[g.semantics == PEDESTRIAN])) == {7}
    assert (g.instances[g.semantics != PEDESTRIAN] == 0).all()
    np.testing.assert_allclose(g.velocity[g.semantics == PEDESTRIAN], [[0.5, -1.25]] * len(ped))
    assert not g.velocity[g.semantics != PEDESTRIAN].any()


def _reference_voxels(spec, v, f):
    """The definition, computed the slow way: voxels of surface_points at half-voxel spacing, plus
    voxels whose centre open3d finds inside (3 rays, majority: one ray can graze an edge)."""
    import open3d as o3d

    surf = spec.index_of(surface_points(v, f, 0.5 * spec.voxel_size_m))
    idx = np.argwhere(np.ones(spec.shape, bool))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
    occ = scene.compute_occupancy(
        o3d.core.Tensor(spec.center_of(idx).astype(np.float32)), nsamples=3
    )
    return {tuple(i) for i in surf[spec.in_bounds(surf)]} | {
        tuple(i) for i in idx[occ.numpy() > 0.5]
    }


@pytest.mark.parametrize("shape", ["sphere", "torus", "yawed_box"])
def test_voxelize_mesh_equals_surface_plus_inside_centres(shape):
    """Column parity fill == open3d's inside test at voxel centres (plus the surface lattice), on
    a convex, a non-convex (4 crossings per column) and a rotated mesh, cut by the grid's side."""
    import open3d as o3d

    if shape == "sphere":
        m = o3d.geometry.TriangleMesh.create_sphere(radius=0.55, resolution=24).translate(
            (1.3, 0.1, 1.0)
        )
    elif shape == "torus":
        m = o3d.geometry.TriangleMesh.create_torus(torus_radius=0.5, tube_radius=0.2).translate(
            (1.5, -0.05, 1.0)
        )
        m.rotate(
            o3d.geometry.get_rotation_matrix_from_xyz((0.3, 0.2, 0.0)), center=(1.5, -0.05, 1.0)
        )
    else:
        m = box_mesh((2.8, 0.7, 0.9), (0.5, 0.9, 1.2), yaw=0.5)  # crosses the grid's x and y ends
    v, f = np.asarray(m.vertices), np.asarray(m.triangles)
    for spec in (SPEC, GridSpec((0.0, -1.0, 0.0), (3.0, 1.0, 2.0), 0.05)):
        idx = voxelize_mesh(spec, v, f)
        assert idx.dtype == np.int64 and spec.in_bounds(idx).all()
        assert np.array_equal(idx, np.unique(idx, axis=0))  # unique rows, lexicographic order
        assert {tuple(i) for i in idx} == _reference_voxels(spec, v, f)


def test_voxelize_mesh_column_through_a_shared_edge():
    """A vertical line through the diagonal shared by a box's two top faces (and the two bottom
    faces) crosses the surface once there, not 0 or 2 times: the columns on the diagonal are
    filled like their neighbours. Coordinates are exact binary fractions, so the lines pass
    exactly through the edge."""
    spec = GridSpec((0.0, 0.0, 0.0), (4.0, 4.0, 4.0), 0.25)
    c = lambda i: (i + 0.5) * 0.25  # noqa: E731 - voxel centres
    lo, hi = (c(2), c(2), 0.3), (c(12), c(12), 2.7)
    corners = np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )
    # 12 outward faces; the top (z = hi) and bottom faces are split along the xy diagonal
    faces = np.array(
        [
            [0, 2, 6],
            [0, 6, 4],
            [1, 5, 7],
            [1, 7, 3],
            [0, 1, 3],
            [0, 3, 2],
            [4, 6, 7],
            [4, 7, 5],
            [0, 4, 5],
            [0, 5, 1],
            [2, 3, 7],
            [2, 7, 6],
        ]
    )
    got = {tuple(i) for i in voxelize_mesh(spec, corners, faces)}
    inside = _idx_box((3, 3, 2), (11, 11, 9))  # centres strictly inside: z 0.375 .. 2.375
    assert inside <= got
    assert all((i, i, k) in got for i in range(3, 12) for k in range(4, 8))  # the diagonal columns
    assert not any(k > 10 for _, _, k in got)


def test_voxelize_mesh_bad_faces():
    with pytest.raises(Exception, match="faces index"):
        voxelize_mesh(SPEC, np.zeros((3, 3)), np.array([[0, 1, 3]]))


def test_surface_points_cover_triangle():
    v = np.array([[0, 0, 0], [1.0, 0, 0], [0, 1.0, 0]])
    p = surface_points(v, np.array([[0, 1, 2]]), 0.1)
    assert len(p) == 3 + 16 * 17 // 2  # vertices + lattice with k = ceil(sqrt(2) / 0.1) = 15
    assert (
        np.allclose(p[:, 2], 0)
        and (p[:, :2] >= -1e-12).all()
        and (p[:, :2].sum(1) <= 1 + 1e-12).all()
    )
    rng = np.random.default_rng(0)
    q = rng.dirichlet(np.ones(3), 500) @ v
    d = np.linalg.norm(q[:, None] - p[None], axis=2).min(1)
    assert d.max() <= 0.1


R_BASE_FROM_CAM = np.array([[0, 0, 1.0], [-1.0, 0, 0], [0, -1.0, 0]])  # cam z forward = base x


def _camera(origin=(-0.5, 0.05, 1.05)):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_BASE_FROM_CAM, origin
    K = np.array([[100.0, 0, 9.5], [0, 100.0, 9.5], [0, 0, 1]])
    return CameraView(K, 20, 20, T)


@pytest.mark.parametrize("method", ["zbuffer", "rays"])
def test_camera_mask_occlusion_and_frustum(method):
    occ = np.zeros(SPEC.shape, bool)
    occ[15, 10, 10] = True
    cam = _camera()
    m = camera_mask(SPEC, occ, cam.K, cam.width, cam.height, cam.T_base_from_cam, 1, method)
    assert m.dtype == np.uint8
    assert m[0, 10, 10] == 1 and m[14, 10, 10] == 1  # in front of the blocker
    assert m[15, 10, 10] == 1  # the first occupied voxel is observed
    assert m[16, 10, 10] == 0 and m[29, 10, 10] == 0  # behind it
    assert m[5, 0, 10] == 0  # outside the narrow frustum
    assert m[15, 11, 10] == 1 or method == "rays"  # beside the blocker (too oblique for few rays)
    free = camera_mask(
        SPEC, np.zeros(SPEC.shape, bool), cam.K, 20, 20, cam.T_base_from_cam, 1, method
    )
    assert free[16, 10, 10] == 1 and free[29, 10, 10] == 1  # the same voxels without the blocker


def test_lidar_mask_traversed_and_hit():
    m = lidar_mask(SPEC, np.array([[1.55, 0.05, 1.05]]), np.array([-0.5, 0.05, 1.05]))
    assert {tuple(i) for i in np.argwhere(m)} == {(i, 10, 10) for i in range(16)}
    # a ray that ends before the grid marks nothing; one that passes through marks to the exit
    assert not lidar_mask(SPEC, np.array([[-0.1, 0.05, 1.05]]), np.array([-0.5, 0.05, 1.05])).any()
    far = lidar_mask(SPEC, np.array([[9.0, 0.05, 1.05]]), np.array([-0.5, 0.05, 1.05]))
    assert far.sum() == 30


def test_fuse_frame_states_and_masks():
    occ_map = OccupancyMap(FreeSpaceParams(voxel_size_m=0.1))
    ys, zs = np.meshgrid(np.arange(-0.95, 1.0, 0.1), np.arange(0.05, 2.0, 0.1), indexing="ij")
    wall = np.stack([np.full(ys.size, 2.05), ys.ravel(), zs.ravel()], 1)
    occ_map.insert_scan(wall, np.array([-0.5, 0.05, 1.05]), max_range_m=-1.0, discretize=False)
    labels = np.full(len(wall), OTHER_STRUCTURE, np.uint8)
    g = fuse_frame(
        SPEC,
        np.eye(4),
        static_points_world=wall.astype(np.float32),
        static_labels=labels,
        occupancy=occ_map,
        lidar_points_base=wall,
        lidar_origin_base=np.array([-0.5, 0.05, 1.05]),
        camera=_camera(),
        fusion=FuseSettings(camera_pixel_stride=1),
    )
    np.testing.assert_array_equal(g.occupancy_state, occ_map.query_grid(SPEC, np.eye(4)))
    assert (g.occupancy_state[20] == 1).all() and (g.semantics[20] == OTHER_STRUCTURE).all()
    assert (g.occupancy_state[21:] == -1).all()  # beyond the hit layer: never observed
    assert g.occupancy_state[10, 10, 10] == 0  # on the sensor's rays: free
    assert g.mask_lidar[20, 10, 10] == 1 and g.mask_lidar[21:].sum() == 0
    assert g.mask_camera[20, 10, 10] == 1 and g.mask_camera[21:].sum() == 0
    assert g.velocity.dtype == np.float16 and g.velocity.shape == (*SPEC.shape, 2)


def test_visibility_masks_do_not_depend_on_threads():
    """Rays split over threads share the output (every write stores 1): same masks."""
    rng = np.random.default_rng(5)
    occ = rng.random(SPEC.shape) < 0.03
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_BASE_FROM_CAM, (-0.5, 0.05, 1.05)
    K = np.array([[300.0, 0, 199.5], [0, 300.0, 149.5], [0, 0, 1]])  # 400 x 300: 120k rays
    one = camera_mask(SPEC, occ, K, 400, 300, T, 1, "rays", threads=1)
    assert 0 < one.sum() < SPEC.num_voxels
    np.testing.assert_array_equal(camera_mask(SPEC, occ, K, 400, 300, T, 1, "rays", threads=3), one)
    ends = rng.uniform((-1.0, -1.0, 0.5), (1.5, 1.0, 1.5), (30000, 3))
    origin = np.array([-0.5, 0.05, 1.05])
    lid = lidar_mask(SPEC, ends, origin, threads=1)
    assert 0 < lid.sum() < SPEC.num_voxels
    np.testing.assert_array_equal(lidar_mask(SPEC, ends, origin, threads=3), lid)
