"""Per-voxel velocity from a body's own motion, on analytic moving meshes: a limb (a closed
cylinder) swinging about a hip axis, seen from a robot that moves and turns."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from tasks.conventions import PEDESTRIAN
from tasks.occupancy.fuse import (
    PedestrianMesh,
    fuse_frame,
    mesh_voxel_velocity,
    surface_points,
    voxelize_mesh,
)
from tasks.occupancy.grid import GridSpec
from tasks.track.velocity import track_neighbours, vertex_velocities_in_base

SPEC = GridSpec((0.0, -1.0, 0.0), (3.0, 1.0, 2.0), 0.1)
PIVOT = np.array([1.53, 0.07, 1.46])  # the hip: the limb hangs below it
AXIS = np.array([-np.sin(0.6), np.cos(0.6), 0.0])  # horizontal swing axis, yawed 0.6 rad off y
OMEGA = 2.5  # rad/s


def _rot(axis, angle):
    return o3d.geometry.get_rotation_matrix_from_axis_angle(np.asarray(axis) * angle)


def _limb(angle: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """A closed cylinder (radius 0.07 m, 0.8 m long) hanging from PIVOT, swung ``angle`` rad
    about AXIS."""
    m = o3d.geometry.TriangleMesh.create_cylinder(radius=0.07, height=0.8, resolution=16, split=6)
    v = np.asarray(m.vertices) - [0.0, 0.0, 0.4]  # top cap at the pivot
    return (v @ _rot(AXIS, angle).T) + PIVOT, np.asarray(m.triangles)


def _swing_velocity(points):
    """The rigid swing's velocity field omega x (p - pivot), (N, 3) m/s."""
    return np.cross(OMEGA * AXIS, np.asarray(points) - PIVOT)


def test_rotating_limb_voxels_take_the_mean_velocity_of_their_surface():
    v, f = _limb()
    idx, vel = mesh_voxel_velocity(SPEC, v, f, _swing_velocity(v)[:, :2])
    assert np.array_equal(idx, voxelize_mesh(SPEC, v, f))  # the same voxels as the occupancy
    # the field is linear, so blending vertex velocities is exact: each voxel's value is the swing
    # velocity at the mean of its surface points (computed here the slow way, in numpy)
    pts = surface_points(v, f, 0.5 * SPEC.voxel_size_m)
    flat = SPEC.flat_index(SPEC.index_of(pts))
    for i, vv in zip(SPEC.flat_index(idx), vel):
        here = pts[flat == i]
        expect = _swing_velocity(here)[:, :2].mean(0) if len(here) else None
        if expect is not None:
            np.testing.assert_allclose(vv, expect, atol=1e-9)
    # analytic: within half a voxel's lever of the swing velocity at the voxel centre, and the
    # foot moves fast while the hip hardly moves
    centre_vel = _swing_velocity(SPEC.center_of(idx))[:, :2]
    assert np.abs(vel - centre_vel).max() <= OMEGA * SPEC.voxel_size_m * np.sqrt(3) / 2 + 1e-9
    speed = np.linalg.norm(vel, axis=1)
    depth = PIVOT[2] - SPEC.center_of(idx)[:, 2]
    assert speed[depth > 0.7].min() > 1.6 and speed[depth < 0.1].max() < 0.5
    # vx, vy point along the swing direction, perpendicular to the axis in the ground plane
    assert np.abs(vel @ AXIS[:2]).max() < 1e-9


def test_voxels_without_surface_take_the_nearest_vertex():
    """A thick limb at a fine grid has voxels inside, with no surface point; they take the
    velocity of their nearest vertex. A requested voxel off the mesh does too."""
    v, f = _limb()
    v = (v - PIVOT) * [3.0, 3.0, 1.0] + PIVOT  # radius 0.21 m
    spec = GridSpec(SPEC.range_min, SPEC.range_max, 0.05)
    vel_v = _swing_velocity(v)[:, :2]
    idx, vel = mesh_voxel_velocity(spec, v, f, vel_v)
    pts = spec.index_of(surface_points(v, f, 0.5 * spec.voxel_size_m))
    surface = {tuple(i) for i in pts}
    inner = np.array([k for k, i in enumerate(idx) if tuple(i) not in surface])
    assert len(inner) > 20
    nearest = np.argmin(
        np.linalg.norm(spec.center_of(idx[inner])[:, None] - v[None], axis=2), axis=1
    )
    np.testing.assert_allclose(vel[inner], vel_v[nearest])
    far = np.array([[0, 0, 0]])
    got_idx, got = mesh_voxel_velocity(spec, v, f, vel_v, voxels=far)
    np.testing.assert_array_equal(got_idx, far)
    np.testing.assert_allclose(
        got[0], vel_v[np.argmin(np.linalg.norm(spec.center_of(far) - v, axis=1))]
    )


def test_fuse_frame_writes_per_voxel_velocity_of_a_swinging_limb():
    v, f = _limb()
    vel_v = _swing_velocity(v)[:, :2]
    g = fuse_frame(
        SPEC,
        np.eye(4),
        static_points_world=np.zeros((0, 3), np.float32),
        static_labels=np.zeros(0, np.uint8),
        pedestrians=[PedestrianMesh(3, v, f, np.array([0.4, 0.0]), vel_v)],
        velocity_dtype=np.float32,
    )
    idx, vel = mesh_voxel_velocity(SPEC, v, f, vel_v)
    ped = np.argwhere(g.semantics == PEDESTRIAN)
    np.testing.assert_array_equal(ped, idx)
    np.testing.assert_allclose(g.velocity[tuple(idx.T)], vel, atol=1e-6)
    # per person: every voxel the person's velocity
    g1 = fuse_frame(
        SPEC,
        np.eye(4),
        static_points_world=np.zeros((0, 3), np.float32),
        static_labels=np.zeros(0, np.uint8),
        pedestrians=[PedestrianMesh(3, v, f, np.array([0.5, -0.25]))],
    )
    np.testing.assert_array_equal(g1.velocity[tuple(idx.T)], [[0.5, -0.25]] * len(idx))


def _robot(t):
    """T_world_from_lidar of a robot driving at 1 m/s and turning at 0.5 rad/s."""
    T = np.eye(4)
    T[:3, :3] = _rot([0, 0, 1], 0.5 * t + 0.2)
    T[:3, 3] = [1.0 * t - 4.0, 0.3 * t, 0.8]
    return T


def test_central_difference_of_a_swinging_limb_with_the_robot_moving():
    """The limb in the world swings about the hip; each frame sees it in its own LiDAR frame. The
    vertex velocities in the base frame are the swing velocity (scaled by sin(w dt) / (w dt), the
    central difference of a rotation), rotated into the base axes: the robot's motion is gone."""
    dt, t = 0.2, 1.0
    T_base_from_lidar = np.eye(4)
    T_base_from_lidar[:3, 3] = [0.1, 0.0, 0.9]
    frames = [(t + s * dt, _limb(OMEGA * (t + s * dt))[0]) for s in (-1, 0, 1)]
    lidar = [(np.linalg.inv(_robot(tt)) @ np.c_[w, np.ones(len(w))].T).T[:, :3] for tt, w in frames]
    poses = [_robot(tt) for tt, _ in frames]
    stamps = [tt for tt, _ in frames]
    got = vertex_velocities_in_base(lidar, poses, stamps, T_base_from_lidar, np.zeros(3))
    R_base_from_world = T_base_from_lidar[:3, :3] @ poses[1][:3, :3].T
    exact = _swing_velocity(frames[1][1]) @ R_base_from_world.T
    np.testing.assert_allclose(got, exact * np.sin(OMEGA * dt) / (OMEGA * dt), atol=1e-9)
    # one-sided at a track's end: the chord from this frame to the next
    end = vertex_velocities_in_base(
        [None, lidar[1], lidar[2]], poses, stamps, T_base_from_lidar, np.zeros(3)
    )
    np.testing.assert_allclose(
        end, (frames[2][1] - frames[1][1]) / dt @ R_base_from_world.T, atol=1e-9
    )
    # no neighbour: the fallback (the person's velocity) on every vertex
    alone = vertex_velocities_in_base(
        [None, lidar[1], None], poses, stamps, T_base_from_lidar, [0.5, -0.2, 0.0]
    )
    np.testing.assert_allclose(alone, np.broadcast_to([0.5, -0.2, 0.0], alone.shape))


def test_track_neighbours_are_bounded_in_time():
    ids = np.array([1, 1, 1, 2, 1, 2, 1])
    t = np.array([0.0, 0.2, 0.4, 0.4, 1.0, 0.6, 1.2])  # track 1 misses 0.6 and 0.8
    prev, nxt = track_neighbours(ids, t, max_gap_s=0.25)
    np.testing.assert_array_equal(prev, [-1, 0, 1, -1, -1, 3, 4])
    np.testing.assert_array_equal(nxt, [1, 2, -1, 5, 6, -1, -1])
    prev, nxt = track_neighbours(ids, t)
    np.testing.assert_array_equal(prev, [-1, 0, 1, -1, 2, 3, 4])


def test_tracked_bodies_translate_rigidly_and_fall_back_across_gaps():
    """A procedural body walking rigidly at (1.0, 0.5) m/s in the world, its fits in the LiDAR
    frames of a turning robot: every vertex's velocity is the walk in the base axes; a fit with no
    neighbour within the gap takes the person's velocity."""
    from tasks.body.motion import TrackedBodies
    from tasks.body.procedural import default_body_model

    model = default_body_model()
    stamps = np.arange(6) * 0.2
    poses = np.stack([_robot(tt) for tt in stamps])
    T_base_from_lidar = np.eye(4)
    walk = np.array([1.0, 0.5, 0.0])
    frames = np.array([0, 1, 2, 5])  # frames 3 and 4 not fitted
    betas, pose = np.zeros((4, 10)), np.zeros((4, 69))
    # world pose of the body: upright at (2, 0, 0) + walk * t; in the LiDAR frame of each frame
    # (SMPL rotates about the root joint J0: transl = R_lw (J0 + t_w) + t_lw - J0)
    R_lw = np.stack([np.linalg.inv(poses[p])[:3, :3] for p in frames])
    t_lw = np.stack([np.linalg.inv(poses[p])[:3, 3] for p in frames])
    import torch

    J0 = (
        model.rest_joints(torch.zeros(1, 10))[0, 0].detach().numpy().astype(np.float64)
    )  # root joint
    world_t = np.array([2.0, 0.0, 0.0]) + walk * stamps[frames, None]
    go = np.stack([_axis_angle(R) for R in R_lw])
    transl = np.einsum("kij,kj->ki", R_lw, J0 + world_t) + t_lw - J0

    def tracked(p, relative=False):
        return TrackedBodies(
            model,
            betas,
            go,
            p,
            transl,
            np.full(4, 7),
            frames,
            np.tile([0.3, 0.0], (4, 1)),
            stamps,
            poses,
            T_base_from_lidar,
            max_gap_s=0.25,
            relative=relative,
        )

    bodies = tracked(pose)
    for position in (0, 1, 2):
        rows, _, vel = bodies.frame(position)
        assert rows.tolist() == [position]
        expect = T_base_from_lidar[:3, :3] @ poses[position][:3, :3].T @ walk
        np.testing.assert_allclose(vel[0], np.broadcast_to(expect, vel[0].shape), atol=2e-4)
    rows, _, vel = bodies.frame(5)  # 0.6 s from its previous fit: the person's velocity
    np.testing.assert_allclose(vel[0], np.broadcast_to([0.3, 0.0, 0.0], vel[0].shape))
    assert bodies.frame(3)[0].size == 0

    # fuse.velocity "articulated": the person's velocity (0.3, 0) plus the motion relative to
    # the pelvis, none for a rigid walk; with the right arm swinging, its vertices keep their
    # swing (the same as the central difference's, less the pelvis' walk)
    rows, _, vel = tracked(pose, True).frame(1)
    np.testing.assert_allclose(vel[0], np.broadcast_to([0.3, 0.0, 0.0], vel[0].shape), atol=2e-4)
    swing = pose.copy()
    swing[:, 3 * 16 + 2] = 0.8 * stamps[frames]  # right shoulder (joint 17): 0.8 rad/s
    _, _, art = tracked(swing, True).frame(1)
    _, _, cd = tracked(swing, False).frame(1)
    expect = T_base_from_lidar[:3, :3] @ poses[1][:3, :3].T @ walk
    np.testing.assert_allclose(
        art[0] - cd[0] + expect, np.broadcast_to([0.3, 0, 0], art[0].shape), atol=2e-4
    )
    speed = np.linalg.norm(art[0] - [0.3, 0, 0], axis=1)
    assert speed.max() > 0.3 and np.median(speed) < 1e-3  # the arm moves, most of the body not


def _axis_angle(R):
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()


@pytest.mark.parametrize("dims", [2, 3])
def test_mesh_voxel_velocity_checks_shapes(dims):
    v, f = _limb()
    with pytest.raises(ValueError, match="vertex_velocity"):
        mesh_voxel_velocity(SPEC, v, f, np.zeros((len(v) - 1, dims)))


def test_five_frame_derivative_follows_a_swing_closer_than_the_central_difference():
    """A point swinging as sin(2 pi t) m seen at 5 Hz from a still robot: the slope of the quartic
    through five frames (fuse.velocity_neighbours 2) loses ~7 % of the peak speed, the central
    difference ~24 %; a track's end uses what it has."""
    from tasks.track.velocity import derivative_weights

    h = 0.2
    np.testing.assert_allclose(
        derivative_weights(np.arange(-2, 3) * h), np.array([1, -8, 0, 8, -1]) / (12 * h), atol=1e-9
    )
    t = np.arange(-2, 3) * h
    pts = [np.array([[np.sin(2 * np.pi * x), 0.0, 0.0]]) for x in t]
    T = [np.eye(4)] * 5
    peak = 2 * np.pi
    five = vertex_velocities_in_base(pts, T, t, np.eye(4), np.zeros(3))[0, 0]
    three = vertex_velocities_in_base(pts[1:4], T[1:4], t[1:4], np.eye(4), np.zeros(3))[0, 0]
    assert abs(five / peak - 0.93) < 0.01 and abs(three / peak - 0.757) < 0.01
    # the same five frames with the second previous missing: the cubic through four
    four = vertex_velocities_in_base([None] + pts[1:], T, t, np.eye(4), np.zeros(3))[0, 0]
    assert abs(four / peak - 1) < abs(three / peak - 1)
