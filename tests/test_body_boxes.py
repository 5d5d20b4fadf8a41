"""Upright pedestrian boxes: heading from the body's forward axis, l along it (regression, issue 19:
the yaw was the footprint's major axis, the shoulder line, ~90 deg off, with l and w swapped)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from tasks.body.boxes import (
    HEADING_FROM_BODY,
    HEADING_FROM_FOOTPRINT,
    HEADING_FROM_VELOCITY,
    body_forward,
    upright_box,
)

#: template (y up, facing +z, left +x) -> base (z up) for a person facing base +x
R_BASE_FROM_TEMPLATE = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def _orient(yaw: float, extra: np.ndarray | None = None) -> np.ndarray:
    R = Rotation.from_euler("z", yaw).as_matrix() @ R_BASE_FROM_TEMPLATE
    if extra is not None:
        R = R @ extra
    return Rotation.from_matrix(R).as_rotvec()


def _cuboid_template(half_x=0.25, y=(-1.2, 0.5), half_z=0.12) -> np.ndarray:
    """Corners + samples of a cuboid in the template frame: shoulders along x, height along y."""
    g = np.stack(
        np.meshgrid(
            np.linspace(-half_x, half_x, 5),
            np.linspace(*y, 7),
            np.linspace(-half_z, half_z, 3),
            indexing="ij",
        ),
        -1,
    )
    return g.reshape(-1, 3)


@pytest.mark.parametrize(
    "yaw", [0.0, 0.7, -2.0, np.pi - 1e-3, -np.pi + 1e-3, 3 * np.pi / 2 - 2 * np.pi]
)
def test_heading_and_size_of_an_upright_cuboid_body(yaw):
    go = _orient(yaw)
    t = np.array([3.0, -1.0, 0.9])
    verts = _cuboid_template() @ Rotation.from_rotvec(go).as_matrix().T + t
    box = upright_box(
        verts, go, velocity_xy=np.array([0.0, -1.5])
    )  # the body wins over the velocity
    assert box.heading_source == HEADING_FROM_BODY
    assert abs(np.angle(np.exp(1j * (box.yaw - yaw)))) < 1e-9
    np.testing.assert_allclose(
        box.size, [0.24, 0.5, 1.7], atol=1e-9
    )  # l = body depth along the heading
    np.testing.assert_allclose(box.center, t + [0.0, 0.0, -0.35], atol=1e-9)
    np.testing.assert_allclose(body_forward(go), [np.cos(yaw), np.sin(yaw), 0.0], atol=1e-12)


def test_forward_axis_pointing_up_falls_back_to_velocity_then_footprint():
    lying = _orient(
        0.3, Rotation.from_euler("x", -np.pi / 2).as_matrix()
    )  # forward axis -> base +z
    assert body_forward(lying)[2] > 0.99
    verts = _cuboid_template() @ Rotation.from_rotvec(lying).as_matrix().T
    box = upright_box(verts, lying, velocity_xy=np.array([-1.0, 1.0]))
    assert box.heading_source == HEADING_FROM_VELOCITY and box.yaw == pytest.approx(3 * np.pi / 4)
    for vel in (None, np.array([np.nan, 1.0]), np.array([0.01, 0.0])):  # unknown or too slow
        box = upright_box(verts, lying, velocity_xy=vel)
        assert box.heading_source == HEADING_FROM_FOOTPRINT
        assert (
            np.isfinite(box.yaw)
            and np.all(np.isfinite(box.size))
            and np.all(np.isfinite(box.center))
        )
        assert box.size[0] <= box.size[1] + 1e-9  # across the footprint's major axis


def test_degenerate_and_bad_input():
    box = upright_box(np.array([[1.0, 2.0, 3.0]]))
    assert box.yaw == 0.0 and np.all(box.size == 0) and np.all(box.center == [1.0, 2.0, 3.0])
    box = upright_box(np.array([[1.0, 2.0, 3.0]]), global_orient=np.array([np.nan, 0, 0]))
    assert np.isfinite(box.yaw)
    with pytest.raises(ValueError, match="non-finite"):
        upright_box(np.array([[0.0, np.nan, 0.0]]))


def test_procedural_body_facing_a_direction_gets_that_heading():
    from tasks.body.procedural import default_body_model

    model = default_body_model()
    for yaw in (0.0, 1.2, -2.5):
        go = _orient(yaw)
        with torch.no_grad():
            out = model(
                torch.zeros(1, 10),
                torch.as_tensor(go[None], dtype=torch.float32),
                torch.zeros(1, 69),
                torch.zeros(1, 3),
            )
        box = upright_box(out.vertices[0].numpy(), go)
        assert abs(np.angle(np.exp(1j * (box.yaw - yaw)))) < 1e-6
        l, w, h = box.size
        assert l < w and 1.5 < h < 2.0  # depth along the heading, arms (T-pose) across


def test_heading_errors_wrap_and_summary():
    from tasks.metrics.heading import heading_errors_deg, heading_summary

    e = heading_errors_deg([np.pi - 0.1, 0.0, np.pi / 2], [-np.pi + 0.1, np.pi, 0.0])
    np.testing.assert_allclose(e, [np.degrees(0.2), 180.0, 90.0], atol=1e-9)
    s = heading_summary(e)
    assert (
        s["boxes"] == 3
        and s["median_deg"] == pytest.approx(90.0)
        and s["axis_off_45_share"] == pytest.approx(1 / 3)
    )
    assert heading_summary([])["boxes"] == 0
