"""Camera poses on the sphere around the world origin (datagen.camera)."""

from __future__ import annotations

import numpy as np
import pytest

from datagen.camera import CameraParams, look_at_table_origin, sample_cameras
from vgq.camera import DEFAULT_INTRINSICS, project

PHI_70 = np.radians(70.0)


def _to_camera(T: np.ndarray, p_world) -> np.ndarray:
    return (np.asarray(p_world, dtype=np.float64) - T[:3, 3]) @ T[:3, :3]


@pytest.mark.parametrize("phi", [0.0, np.radians(35.0), PHI_70])
def test_principal_ray_passes_through_world_origin(phi):
    for theta in np.linspace(0, 2 * np.pi, 7, endpoint=False):
        T = look_at_table_origin(0.7, phi, theta)[0]
        np.testing.assert_allclose(_to_camera(T, [0, 0, 0]), [0, 0, 0.7], atol=1e-12)


@pytest.mark.parametrize("phi", [0.0, np.radians(35.0), PHI_70])
def test_camera_frames_are_proper_rotations(phi):
    T = look_at_table_origin(np.full(5, 0.5), phi, np.linspace(0, 6, 5))
    R = T[:, :3, :3]
    np.testing.assert_allclose(R.transpose(0, 2, 1) @ R, np.tile(np.eye(3), (5, 1, 1)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_allclose(T[:, 3], np.tile([0, 0, 0, 1.0], (5, 1)))


def test_camera_position_follows_spherical_coordinates_at_phi_70():
    d, theta = 0.9, np.radians(200.0)
    T = look_at_table_origin(d, PHI_70, theta)[0]
    expected = d * np.array([np.sin(PHI_70) * np.cos(theta), np.sin(PHI_70) * np.sin(theta), np.cos(PHI_70)])
    np.testing.assert_allclose(T[:3, 3], expected, atol=1e-12)


def test_overhead_camera_looks_straight_down_without_degenerate_frame():
    for theta in (0.0, 1.0, 4.0):
        T = look_at_table_origin(0.6, 0.0, theta)[0]
        np.testing.assert_allclose(T[:3, 2], [0, 0, -1], atol=1e-12)
        np.testing.assert_allclose(T[:3, 3], [0, 0, 0.6], atol=1e-12)
        np.testing.assert_allclose(T[:3, 0], [-np.sin(theta), np.cos(theta), 0], atol=1e-12)


@pytest.mark.parametrize("phi", [0.0, np.radians(35.0), PHI_70])
def test_camera_x_axis_is_parallel_to_the_table(phi):
    T = look_at_table_origin(np.full(8, 0.8), phi, np.linspace(0, 2 * np.pi, 8, endpoint=False))
    np.testing.assert_allclose(T[:, 2, 0], 0.0, atol=1e-12)


@pytest.mark.parametrize("phi", [np.radians(10.0), np.radians(45.0), PHI_70])
def test_objects_appear_upright(phi):
    """A point above the world origin projects above the image centre (smaller v), in the same
    column: the table is level and world up points up in the image."""
    T = look_at_table_origin(0.8, phi, 2.3)[0]
    u, v, _ = project(_to_camera(T, [0, 0, 0.1])[None], DEFAULT_INTRINSICS)[0]
    assert v < DEFAULT_INTRINSICS.cy - 1
    assert u == pytest.approx(DEFAULT_INTRINSICS.cx, abs=1e-9)


def test_sample_cameras_stays_within_ranges_and_is_reproducible():
    params = CameraParams(d_range=(0.5, 0.6), phi_range=(0.1, 0.2), theta_range=(1.0, 2.0))
    a = sample_cameras(200, params, np.random.default_rng(3))
    b = sample_cameras(200, params, np.random.default_rng(3))
    assert len(a) == 200
    assert np.all((a.d >= 0.5) & (a.d <= 0.6))
    assert np.all((a.phi >= 0.1) & (a.phi <= 0.2))
    assert np.all((a.theta >= 1.0) & (a.theta <= 2.0))
    np.testing.assert_array_equal(a.T_world_camera, b.T_world_camera)
    np.testing.assert_allclose(np.linalg.norm(a.T_world_camera[:, :3, 3], axis=1), a.d, atol=1e-12)


def test_default_ranges_match_the_paper():
    p = CameraParams()
    assert p.d_range == (0.4, 1.1)
    assert p.phi_range == pytest.approx((0.0, np.radians(70)))
    assert p.theta_range == pytest.approx((0.0, 2 * np.pi))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"d_range": (0.0, 1.0)}, "d_range"),
        ({"d_range": (1.0, 0.5)}, "low <= high"),
        ({"phi_range": (0.0, np.pi / 2)}, "phi_range"),
        ({"theta_range": (0.0, float("nan"))}, "finite"),
    ],
)
def test_bad_camera_params_are_rejected(kwargs, match):
    with pytest.raises(ValueError, match=match):
        CameraParams(**kwargs)


def test_look_at_rejects_a_camera_below_the_table():
    with pytest.raises(ValueError, match="phi"):
        look_at_table_origin(0.5, np.radians(95), 0.0)
    with pytest.raises(ValueError, match="d must be > 0"):
        look_at_table_origin(-0.5, 0.2, 0.0)
