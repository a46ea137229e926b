"""Grasp projection into the camera (datagen.project). World frame: table z = 0, z up."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from datagen_fakes import grasp_frame
from scipy import ndimage

from datagen.camera import look_at_table_origin
from datagen.gripper import grasp_frames
from datagen.project import project_grasps
from datagen.render import render_depth
from vgq.camera import DEFAULT_INTRINSICS
from vgq.pose import matrix_from_quaternion

EX, EY, EZ = np.eye(3)


@pytest.mark.parametrize("phi_deg", [0.0, 35.0, 70.0])
def test_rendered_depth_at_a_visible_contact_matches_its_projected_depth(phi_deg):
    """Top/bottom contact pairs on a box: the top contacts are visible from any camera above
    the table; the depth image at their projected (u, v) equals their projected z."""
    rng = np.random.default_rng(int(phi_deg))
    box = trimesh.creation.box(extents=[0.06, 0.05, 0.04])
    box.apply_translation([0, 0, 0.02])
    top = np.column_stack([rng.uniform(-0.025, 0.025, 20), rng.uniform(-0.02, 0.02, 20), np.full(20, 0.04)])
    bottom = top * [1, 1, 0]
    centers, axes = (top + bottom) / 2, top - bottom
    T_contact = grasp_frames(top, axes, rng.uniform(0, 2 * np.pi, 20))  # frames at the top contacts
    for theta in (0.0, 2.5):
        T_wc = look_at_table_origin(0.6, np.radians(phi_deg), theta)[0]
        depth = render_depth(box, T_wc)
        pr = project_grasps(T_contact, T_wc)
        assert np.all(pr["in_image"])
        rendered = ndimage.map_coordinates(depth, [pr["v"], pr["u"]], order=1)
        np.testing.assert_allclose(rendered, pr["z"], atol=5e-4)
        # the TCPs (inside the box) lie behind the rendered surface
        tcp = project_grasps(grasp_frames(centers, axes, 0.0), T_wc)
        assert np.all(ndimage.map_coordinates(depth, [tcp["v"], tcp["u"]], order=1) < tcp["z"])


def test_psi_and_beta_for_an_overhead_camera():
    T_wc = look_at_table_origin(0.7, 0.0, 0.0)[0]
    T = np.stack([grasp_frame([0, 0, 0.02], EX, -EZ), grasp_frame([0, 0, 0.02], EX, EY)])  # top, side
    pr = project_grasps(T, T_wc)
    np.testing.assert_allclose(pr["beta"], [0.0, np.pi / 2], atol=1e-9)
    np.testing.assert_allclose(pr["psi"], [0.0, np.pi / 2], atol=1e-9)


def test_psi_and_beta_for_a_camera_at_70_deg():
    phi = np.radians(70.0)
    T_wc = look_at_table_origin(0.7, phi, 0.0)[0]  # camera on the +x side
    ray = T_wc[:3, 2]
    T = np.stack(
        [
            grasp_frame([0, 0, 0.02], EY, ray),  # approach along the principal ray
            grasp_frame([0, 0, 0.02], EY, EX),  # horizontal, from behind the object
            grasp_frame([0, 0, 0.02], EY, -EX),  # horizontal, from the camera's side
        ]
    )
    pr = project_grasps(T, T_wc)
    np.testing.assert_allclose(pr["beta"], [phi, np.pi / 2, np.pi / 2], atol=1e-9)
    np.testing.assert_allclose(pr["psi"], [0.0, np.pi / 2 + phi, np.pi / 2 - phi], atol=1e-9)


def test_projection_of_the_world_origin_is_the_image_centre():
    T_wc = look_at_table_origin(0.55, np.radians(50), 1.0)[0]
    pr = project_grasps(grasp_frame([0, 0, 0], EX, -EZ)[None], T_wc)
    assert (pr["u"][0], pr["v"][0], pr["z"][0]) == pytest.approx((149.5, 149.5, 0.55))


def test_quaternion_is_canonical_and_is_the_camera_frame_rotation():
    rng = np.random.default_rng(5)
    T = grasp_frames(rng.normal(scale=0.03, size=(200, 3)), rng.normal(size=(200, 3)), rng.uniform(0, 7, 200))
    T_wc = look_at_table_origin(0.8, np.radians(60), 0.3)[0]
    pr = project_grasps(T, T_wc)
    assert pr["q"].shape == (200, 4) and np.all(pr["q"][:, 0] >= 0)
    expected = np.linalg.inv(T_wc)[None, :3, :3] @ T[:, :3, :3]
    np.testing.assert_allclose(matrix_from_quaternion(pr["q"]), expected, atol=1e-9)


def test_jaw_angle_is_measured_from_u_towards_v():
    T_wc = look_at_table_origin(0.7, 0.0, 0.0)[0]  # camera x = world +y, camera y = world +x
    T = np.stack(
        [grasp_frame([0, 0, 0.02], EY, -EZ), grasp_frame([0, 0, 0.02], EX, -EZ), grasp_frame([0, 0, 0.02], -EY, -EZ)]
    )
    np.testing.assert_allclose(project_grasps(T, T_wc)["jaw_angle"], [0.0, np.pi / 2, np.pi], atol=1e-9)


def test_jaw_angle_follows_the_projected_contacts():
    rng = np.random.default_rng(6)
    T = grasp_frames(rng.normal(scale=0.03, size=(50, 3)), rng.normal(size=(50, 3)), 0.0)
    T_wc = look_at_table_origin(0.5, np.radians(65), 2.0)[0]
    pr = project_grasps(T, T_wc)
    ahead = T.copy()
    ahead[:, :3, 3] += 1e-6 * T[:, :3, 0]
    pa = project_grasps(ahead, T_wc)
    np.testing.assert_allclose(np.arctan2(pa["v"] - pr["v"], pa["u"] - pr["u"]), pr["jaw_angle"], atol=1e-4)


def test_grasps_outside_the_view_are_flagged():
    T_wc = look_at_table_origin(0.5, 0.0, 0.0)[0]
    T = np.stack(
        [grasp_frame([0, 0, 0.0], EX, -EZ), grasp_frame([1.0, 0, 0.0], EX, -EZ), grasp_frame([0, 0, 0.8], EX, -EZ)]
    )
    np.testing.assert_array_equal(project_grasps(T, T_wc)["in_image"], [True, False, False])


def test_project_rejects_bad_shapes():
    with pytest.raises(ValueError, match="T_world_grasp"):
        project_grasps(np.zeros((3, 3)), np.eye(4))
    with pytest.raises(ValueError, match="T_world_camera"):
        project_grasps(np.eye(4)[None], np.eye(3))


def test_default_intrinsics_are_used():
    T_wc = look_at_table_origin(0.5, 0.0, 0.0)[0]
    pr = project_grasps(grasp_frame([0, 0.01, 0.0], EY, -EZ)[None], T_wc)  # camera x = world y
    assert pr["u"][0] == pytest.approx(DEFAULT_INTRINSICS.cx + DEFAULT_INTRINSICS.fx * 0.01 / 0.5)
