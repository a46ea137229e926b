"""Depth rendering: embree ray casting vs pybullet's TinyRenderer (datagen.render).
World frame: table z = 0, z up; depth in metres along the camera z."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy import ndimage

from datagen.camera import look_at_table_origin
from datagen.render import ray_directions, render_depth, render_depth_pybullet
from vgq.camera import DEFAULT_INTRINSICS, Intrinsics, project


def _scene() -> trimesh.Trimesh:
    """A tilted capsule and a box resting on the table: curved, flat and occluding surfaces."""
    capsule = trimesh.creation.capsule(height=0.06, radius=0.02, count=[24, 24])
    capsule.apply_transform(trimesh.transformations.rotation_matrix(1.1, [1, 0.3, 0]))
    capsule.apply_translation([0.01, -0.02, -capsule.bounds[0, 2]])
    box = trimesh.creation.box(extents=[0.05, 0.03, 0.04])
    box.apply_transform(trimesh.transformations.rotation_matrix(0.5, [0, 0, 1]))
    box.apply_translation([-0.04, 0.03, 0.02])
    return trimesh.util.concatenate([capsule, box])


def _discontinuity_band(depth: np.ndarray, jump: float = 0.002) -> np.ndarray:
    """Pixels within 1 px of a depth discontinuity or crease (second difference > jump)."""
    p = np.pad(depth.astype(np.float64), 1, mode="edge")
    c = p[1:-1, 1:-1]
    d2 = np.maximum(np.abs(p[1:-1, 2:] - 2 * c + p[1:-1, :-2]), np.abs(p[2:, 1:-1] - 2 * c + p[:-2, 1:-1]))
    return ndimage.binary_dilation(d2 > jump, np.ones((3, 3), bool))


@pytest.mark.parametrize("d", [0.4, 0.8, 1.1])
def test_flat_table_seen_from_straight_above_has_depth_d(d):
    depth = render_depth(None, look_at_table_origin(d, 0.0, 1.3)[0])
    assert depth.shape == (300, 300) and depth.dtype == np.float32
    np.testing.assert_allclose(depth, d, rtol=1e-6)


def test_box_top_seen_from_above_is_closer_by_its_height():
    box = trimesh.creation.box(extents=[0.05, 0.05, 0.03])
    box.apply_translation([0, 0, 0.015])
    depth = render_depth(box, look_at_table_origin(0.7, 0.0, 0.0)[0])
    assert depth[149, 149] == pytest.approx(0.67, abs=1e-6)
    assert depth[5, 5] == pytest.approx(0.7, abs=1e-6)


def test_rays_that_miss_everything_get_depth_zero():
    box = trimesh.creation.box(extents=[0.05, 0.05, 0.03])
    depth = render_depth(box, look_at_table_origin(0.7, 0.5, 0.0)[0], table=False)
    assert depth[0, 0] == 0.0 and depth[149, 149] > 0.0
    assert np.all(render_depth(None, look_at_table_origin(0.7, 0.5, 0.0)[0], table=False) == 0.0)


def test_table_depth_matches_the_pinhole_projection_of_table_points():
    """Table points projected with vgq.camera.project land on pixels whose depth equals theirs."""
    T = look_at_table_origin(0.9, np.radians(70), 0.4)[0]
    depth = render_depth(None, T)
    pts = np.array([[0.05, -0.1, 0.0], [-0.12, 0.07, 0.0], [0.0, 0.0, 0.0]])
    uvz = project((pts - T[:3, 3]) @ T[:3, :3])
    for u, v, z in uvz:
        # a plane's depth is smooth: interpolate between pixel centres
        assert ndimage.map_coordinates(depth, [[v], [u]], order=1)[0] == pytest.approx(z, abs=2e-4)


def test_ray_directions_are_unit_and_pass_through_pixel_centres():
    intr = Intrinsics(fx=500.0, fy=480.0, cx=20.5, cy=10.0, width=40, height=30)
    d = ray_directions(intr)
    assert d.shape == (40 * 30, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    uvz = project(d, intr)
    np.testing.assert_allclose(uvz[7 * 40 + 13, :2], [13, 7], atol=1e-9)


@pytest.mark.parametrize("phi_deg, theta", [(0.0, 0.3), (40.0, 2.0), (70.0, 4.0)])
def test_embree_and_pybullet_agree_within_1mm(phi_deg, theta):
    mesh = _scene()
    T = look_at_table_origin(0.5, np.radians(phi_deg), theta)[0]
    a = render_depth(mesh, T)
    b = render_depth_pybullet(mesh, T)
    band = _discontinuity_band(a) | _discontinuity_band(b)
    table = render_depth(None, T)
    on_object = (a < table - 1e-3) & ~band
    assert on_object.sum() > 1000  # the check covers object pixels, not only table
    assert band.mean() < 0.1
    err = np.abs(a.astype(np.float64) - b)[~band]
    assert err.max() < 1e-3


def test_render_rejects_a_bad_camera_pose():
    with pytest.raises(ValueError, match=r"\(4, 4\)"):
        render_depth(None, np.eye(3))
    T = np.eye(4)
    T[0, 0] = 2.0
    with pytest.raises(ValueError, match="rotation"):
        render_depth(None, T)
    with pytest.raises(ValueError, match="trimesh"):
        render_depth("mesh.obj", np.eye(4))


def test_default_intrinsics_give_a_300_px_image():
    box = trimesh.creation.box(extents=[0.05, 0.05, 0.03])
    depth = render_depth(box, look_at_table_origin(0.5, 0.2, 0.0)[0], DEFAULT_INTRINSICS)
    assert depth.shape == (DEFAULT_INTRINSICS.height, DEFAULT_INTRINSICS.width)


def test_moving_a_mesh_after_rendering_it_renders_the_moved_mesh():
    box = trimesh.creation.box(extents=[0.05, 0.05, 0.03])
    box.apply_translation([0, 0, 0.015])
    T = look_at_table_origin(0.7, 0.0, 0.0)[0]
    assert render_depth(box, T)[149, 149] == pytest.approx(0.67, abs=1e-6)
    box.apply_translation([0, 0, 0.01])  # the cached embree scene must not be reused
    assert render_depth(box, T)[149, 149] == pytest.approx(0.66, abs=1e-6)
