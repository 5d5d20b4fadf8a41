"""Surfaces in the static map's voxels (tasks/occupancy/surface.py): analytic planes."""

from __future__ import annotations

import numpy as np
import pytest

from tasks.occupancy.static_map import pack_keys
from tasks.occupancy.surface import (
    FACE_TOLERANCE_M,
    SurfaceError,
    group_sum,
    point_moments,
    surface_fit,
    surface_samples,
)

VS = 0.2


def _ground(n: int, z0: float, noise: float, seed: int = 0):
    """Noisy returns of the plane z = z0 over x in [2, 4), y in [-1, 1), seen from (0, 0, 0.9)."""
    rng = np.random.default_rng(seed)
    p = np.column_stack([rng.uniform(2, 4, n), rng.uniform(-1, 1, n), np.full(n, z0)])
    origin = np.array([0.0, 0.0, 0.9])
    d = (p - origin) / np.linalg.norm(p - origin, axis=1, keepdims=True)
    return (p + d * rng.normal(0.0, noise, n)[:, None]).astype(np.float32), origin


def _fit(points, origin, noise=0.01, min_points=8):
    keys = np.floor(points.astype(np.float64) / VS).astype(np.int64)
    packed, moments = group_sum(pack_keys(keys), point_moments(points, keys, origin, VS))
    return packed, surface_fit(packed, moments, VS, noise, min_points)


def test_moments_of_any_split_add_to_the_same_integers():
    pts, origin = _ground(5000, 0.0, 0.01)
    keys = np.floor(pts.astype(np.float64) / VS).astype(np.int64)
    rows = point_moments(pts, keys, origin, VS)
    whole = group_sum(pack_keys(keys), rows)
    halves = [group_sum(pack_keys(keys[s]), rows[s]) for s in (slice(0, 1234), slice(1234, None))]
    again = group_sum(
        np.concatenate([k for k, _ in halves]), np.concatenate([m for _, m in halves])
    )
    assert np.array_equal(whole[0], again[0]) and np.array_equal(whole[1], again[1])
    assert whole[1].dtype == np.int64 and whole[1][:, 0].sum() == 5000


def test_ground_on_a_voxel_face_keeps_only_the_layer_below():
    """The ground at z = 0, a voxel face: about half the returns fall in the layer above; the
    surface belongs to the layer below (the earth's side), the layer above is noise."""
    pts, origin = _ground(40000, 0.0, 0.01)
    packed, fit = _fit(pts, origin)
    z = (packed & ((1 << 21) - 1)) - (1 << 20)
    assert set(z[fit.keep].tolist()) == {-1}
    assert (z == 0).sum() > 20  # the noise did put points above
    # the kept voxels resample to points of their plane, just below z = 0 (moved 2 mm into the
    # earth, and the centroid of a voxel's own points lies ~2 mm lower: the returns above z = 0
    # are in the voxel above), inside their cubes
    from tasks.occupancy.static_map import unpack_keys

    keys = unpack_keys(packed[fit.keep])
    sp, rows = surface_samples(keys, fit.surface[fit.keep], VS, VS / 4)
    assert len(np.unique(rows)) == len(keys)
    assert np.all((sp[:, 2] < -FACE_TOLERANCE_M / 2) & (sp[:, 2] > -3 * FACE_TOLERANCE_M))
    assert np.all(np.floor(sp / VS).astype(np.int64) == keys[rows])


def test_ground_inside_a_voxel_is_not_dropped_and_noise_zero_keeps_everything():
    pts, origin = _ground(20000, 0.1, 0.01)  # the middle of the layer [0, 0.2)
    packed, fit = _fit(pts, origin)
    from tasks.occupancy.static_map import unpack_keys

    x = unpack_keys(packed)[:, 0]
    # the patch ends at x = 2.0, a voxel face: the few returns that the range noise throws across
    # it (x key 9) hug that face and are its tail; every voxel of the patch keeps its surface
    assert fit.keep[x >= 10].all() and fit.planar[x >= 10].mean() > 0.9
    assert not fit.keep[x == 9].any()
    pts, origin = _ground(20000, 0.0, 0.01)
    _, fit = _fit(pts, origin, noise=0.0)
    assert fit.keep.all()


def test_bad_moments_are_refused():
    with pytest.raises(SurfaceError, match="moments"):
        surface_fit(np.zeros(2, np.int64), np.zeros((3, 13), np.int64), VS, 0.01, 8)
    with pytest.raises(SurfaceError, match="min_points"):
        surface_fit(np.zeros(0, np.int64), np.zeros((0, 13), np.int64), VS, 0.01, 2)


def _pole(x_front: float, sweeps: int, seed: int = 0, arc: float = 1.3, side_m: float = 0.0):
    """Noisy returns of a vertical pole (radius 0.08 m, axis at y = 0.1, the middle of a voxel
    column) whose nearest point to the sensor lies at x = x_front, z in [0.2, 1.0), seen over many
    sweeps from positions along x < 0 at height 0.9 (the robot driving towards it)."""
    rng = np.random.default_rng(seed)
    r, cx, cy = 0.08, x_front + 0.08, 0.1
    pts, origin = [], None
    for k in range(sweeps):
        origin = np.array([-6.0 + 0.1 * k, side_m, 0.9])
        a = rng.uniform(-arc, arc, 400)  # the visible arc, facing -x
        z = rng.uniform(0.2, 1.0, 400)
        p = np.column_stack([cx - r * np.cos(a), cy + r * np.sin(a), z])
        d = (p - origin) / np.linalg.norm(p - origin, axis=1, keepdims=True)
        pts.append(p + d * rng.normal(0.0, 0.01, 400)[:, None])
    return np.concatenate(pts).astype(np.float32), origin


@pytest.mark.parametrize(
    ("x_front", "sweeps", "arc", "side_m", "front_kept"),
    [(2.02, 40, 1.3, 0.0, False), (1.96, 40, 1.3, 0.0, True), (1.995, 40, 1.3, 0.0, True)],
)
def test_a_pole_just_behind_a_voxel_face_does_not_fill_the_voxel_in_front(
    x_front, sweeps, arc, side_m, front_kept
):
    """Found on the 4-sequence benchmark with exact inputs (sequence 1: pole IoU 52.0, 160 of 185
    false pole voxels one voxel in front of a true one, on the sensor side): a pole's front 2 cm
    behind a voxel face throws a few % of its returns into the voxel in front, over a sequence
    more than surface_min_points; its arc fits no plane, so only sparse tails were dropped. A
    voxel without a plane whose points hug the face of a voxel with more points behind it (its
    centroid within 1 sigma of that face) is that surface's tail; a pole reaching 4 cm into
    the voxel keeps it, and so does one reaching 5 mm into it (sequence 0's kerb pole across a
    voxel face: its front voxel holds ~25 % of the points of the one behind, a tail 1-8 %)."""
    pts, origin = _pole(x_front, sweeps, arc=arc, side_m=side_m)
    packed, fit = _fit(pts, origin)
    from tasks.occupancy.static_map import unpack_keys

    keys = unpack_keys(packed)
    along = (keys[:, 2] >= 1) & (keys[:, 2] <= 4)  # z in [0.2, 1.0), the pole's length
    front = along & (keys[:, 0] == 9)  # x in [1.8, 2.0)
    behind = along & (keys[:, 0] == 10)
    assert front.sum() >= 3 and behind.sum() >= 4  # the noise put points in front either way
    assert fit.keep[behind].all()
    assert fit.keep[front].all() if front_kept else not fit.keep[front].any()


def _crown(apex_y: float, sweeps: int = 30, seed: int = 0, radius: float = 1.5):
    """Noisy returns of a tree crown (a sphere of radius radius) whose point nearest the path
    (y = 0) lies at y = apex_y, x = 1.1, z = 3.1 (mid-voxel), seen from a LiDAR passing along x
    at 0.9 m height: the visible part of the cap within 0.4 m of the apex across it."""
    rng = np.random.default_rng(seed)
    c = np.array([1.1, apex_y + radius, 3.1])
    pts, origin = [], None
    for k in range(sweeps):
        origin = np.array([-8.0 + 0.25 * k, 0.0, 0.9])
        u = rng.uniform(-0.4, 0.4, (600, 2))
        p = np.column_stack(
            [c[0] + u[:, 0], c[1] - np.sqrt(radius**2 - (u**2).sum(1)), c[2] + u[:, 1]]
        )
        d = (p - origin) / np.linalg.norm(p - origin, axis=1, keepdims=True)
        seen = np.einsum("ka,ka->k", (p - c) / radius, -d) > 0
        pts.append(p[seen] + d[seen] * rng.normal(0.0, 0.01, int(seen.sum()))[:, None])
    return np.concatenate(pts).astype(np.float32), origin, c


@pytest.mark.parametrize(("apex_y", "reaches"), [(4.19, True), (4.21, False), (4.22, False)])
def test_a_curved_crown_keeps_the_voxels_it_reaches_into(apex_y, reaches):
    """Found on the 4-sequence benchmark with exact inputs (sequence 1: vegetation IoU 80.3, 247
    of 248 missed vegetation voxels one voxel in front of a true one, on the sensor side): a
    crown's front bulging a centimetre across a voxel face puts a few % of the returns of the
    voxel behind into the voxel in front, at the face, like a tail; they were dropped as noise.
    The plane of the voxel behind (flat, as wide as the voxel) reaches into the voxel in front:
    there the crown curves on, so it is kept; a crown 1-2 cm behind the face still leaves no
    voxel in front of it."""
    pts, origin, c = _crown(apex_y)
    packed, fit = _fit(pts, origin)
    from tasks.occupancy.static_map import unpack_keys

    keys = unpack_keys(packed)
    lo = keys * VS
    # the 3 x 3 voxels around the apex in the layer y in [4.0, 4.2), and which of them the
    # sphere meets
    layer = (keys[:, 1] == 20) & (np.abs(lo[:, 0] + VS / 2 - c[0]) < 0.3)
    layer &= np.abs(lo[:, 2] + VS / 2 - c[2]) < 0.3
    meets = np.linalg.norm(np.clip(c, lo, lo + VS) - c, axis=1) < 1.5
    assert layer.sum() >= 1  # the noise put points in front either way
    if reaches:
        assert (layer & meets).sum() == 9
        assert (layer & meets & fit.keep).sum() >= 6
    else:
        assert not (layer & meets).any()
        assert not fit.keep[layer].any()
