"""Gripper frames, the beta flip and swept-gripper collision checks (datagen.gripper,
datagen.collision). World frame: table z = 0, z up; metres."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from datagen_fakes import grasp_frame

from datagen.collision import CollisionChecker
from datagen.gripper import (
    GripperGeometry,
    align_to_table,
    beta_angles,
    grasp_frames,
    gripper_boxes,
    rotation_about_x,
)

EX, EY, EZ = np.eye(3)


def _box_on_table(extents) -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=extents)
    box.apply_translation([0, 0, extents[2] / 2])
    return box


FAR = GripperGeometry(approach_distance=0.3)  # a long straight approach


# ----------------------------------------------------------------------------- frames


def test_grasp_frames_put_x_on_the_jaw_axis_and_are_right_handed():
    rng = np.random.default_rng(0)
    axes = rng.normal(size=(50, 3))
    T = grasp_frames(rng.normal(size=(50, 3)), axes, rng.uniform(0, 2 * np.pi, 50))
    R = T[:, :3, :3]
    np.testing.assert_allclose(R[:, :, 0], axes / np.linalg.norm(axes, axis=1, keepdims=True), atol=1e-12)
    np.testing.assert_allclose(R.transpose(0, 2, 1) @ R, np.tile(np.eye(3), (50, 1, 1)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)


def test_omega_rotates_the_frame_about_its_jaw_axis():
    c, a = np.array([[0.1, 0.2, 0.3]]), np.array([[1.0, 2.0, 0.5]])
    T0, T1 = grasp_frames(c, a, 0.0), grasp_frames(c, a, 0.7)
    np.testing.assert_allclose(T1[0, :3, :3], T0[0, :3, :3] @ rotation_about_x(0.7)[0], atol=1e-12)
    np.testing.assert_allclose(T1[:, :3, 3], c)


def test_beta_is_zero_for_a_top_grasp_and_90_deg_for_a_side_grasp():
    T = np.stack(
        [grasp_frame([0, 0, 0.02], EX, -EZ), grasp_frame([0, 0, 0.02], EX, EY), grasp_frame([0, 0, 0.02], EX, EZ)]
    )
    np.testing.assert_allclose(beta_angles(T), [0.0, np.pi / 2, np.pi], atol=1e-12)


def test_beta_flip_keeps_beta_at_most_90_deg():
    rng = np.random.default_rng(1)
    T0 = grasp_frames(rng.normal(size=(500, 3)), rng.normal(size=(500, 3)), 0.0)
    drawn = rng.uniform(0, 2 * np.pi, 500)
    raw = beta_angles(T0 @ _homogeneous(rotation_about_x(drawn)))
    T, _, beta = align_to_table(T0, omega=drawn)
    assert np.any(raw > np.pi / 2)  # some grasps needed the flip
    assert np.all(beta <= np.pi / 2 + 1e-12)
    np.testing.assert_allclose(beta, np.minimum(raw, np.pi - raw), atol=1e-9)
    # the flip moves neither the TCP nor the jaw axis
    np.testing.assert_allclose(T[:, :3, 3], T0[:, :3, 3])
    np.testing.assert_allclose(T[:, :3, 0], T0[:, :3, 0], atol=1e-12)


def test_align_to_table_reports_the_total_omega_it_applied():
    rng = np.random.default_rng(2)
    T0 = grasp_frames(rng.normal(size=(100, 3)), rng.normal(size=(100, 3)), 0.0)
    T, omega, _ = align_to_table(T0, rng)
    assert np.all((omega >= 0) & (omega < 2 * np.pi))
    np.testing.assert_allclose(T[:, :3, :3], T0[:, :3, :3] @ rotation_about_x(omega), atol=1e-12)


def test_align_to_table_flips_an_approach_from_below():
    T0 = grasp_frame([0, 0, 0.02], EX, EZ)[None]  # approach pointing up: beta = 180 deg
    T, omega, beta = align_to_table(T0, omega=0.0)
    np.testing.assert_allclose(T[0, :3, 2], -EZ, atol=1e-12)
    assert beta[0] == pytest.approx(0.0)
    assert omega[0] == pytest.approx(np.pi)


def _homogeneous(R: np.ndarray) -> np.ndarray:
    T = np.tile(np.eye(4), (len(R), 1, 1))
    T[:, :3, :3] = R
    return T


def test_swept_boxes_cover_the_approach_and_leave_the_jaw_gap_open():
    g = GripperGeometry()
    c, h = gripper_boxes(g, swept=True)
    lo, hi = c - h, c + h
    assert lo[:, 2].min() == pytest.approx(g.tip_offset - g.finger_length - g.palm_thickness - g.approach_distance)
    assert hi[:2, 2].max() == pytest.approx(g.tip_offset)
    assert hi[0, 0] == pytest.approx(-g.max_width / 2) and lo[1, 0] == pytest.approx(g.max_width / 2)


# ----------------------------------------------------------------------------- collisions


def test_gripper_closing_sideways_on_a_narrow_box_from_far_away_does_not_collide():
    checker = CollisionChecker(_box_on_table([0.04, 0.04, 0.04]), FAR)
    T = grasp_frame([0, 0, 0.02], EX, EY)  # jaws along x, horizontal approach along +y
    assert not checker.collides(T[None])[0]


def test_fingers_inside_a_wide_box_collide():
    checker = CollisionChecker(_box_on_table([0.08, 0.04, 0.04]), FAR)
    T = grasp_frame([0, 0, 0.02], EX, EY)
    assert checker.collides(T[None])[0]


def test_finger_slicing_a_face_without_enclosing_a_vertex_collides_by_the_surface_test():
    checker = CollisionChecker(_box_on_table([0.04, 0.04, 0.04]), FAR)
    T = grasp_frame([0.02, 0, 0.02], EX, EY)[None]  # -x finger cuts through the box's middle
    assert not checker.contains_vertex(T)[0]
    assert checker.collides_object_fcl(T)[0]
    assert checker.collides(T)[0]


def test_object_wholly_inside_the_swept_palm_collides():
    g = GripperGeometry()
    crumb = trimesh.creation.box(extents=[0.004] * 3)
    crumb.apply_translation([0, 0, 0.1 - g.tip_offset - g.finger_length - g.palm_thickness / 2 - 0.03])
    checker = CollisionChecker(crumb, g, table=False)
    T = grasp_frame([0, 0, 0.1], EX, EZ)  # approach up along +z, palm sweeps through the crumb
    assert checker.collides(T[None])[0]


def test_approach_through_the_table_collides():
    far_object = trimesh.creation.box(extents=[0.01] * 3)
    far_object.apply_translation([5, 5, 0.005])
    z = [0, np.cos(np.radians(30)), np.sin(np.radians(30))]  # from below the table, 30 deg up
    T = grasp_frame([0, 0, 0.02], EX, z)[None]
    assert CollisionChecker(far_object, FAR, table=True).collides(T)[0]
    assert not CollisionChecker(far_object, FAR, table=False).collides(T)[0]


def test_fingertips_below_the_table_collide():
    g = GripperGeometry()
    checker = CollisionChecker(_box_on_table([0.04, 0.04, 0.04]), g)
    low = grasp_frame([0.2, 0, g.tip_offset - 0.001], EX, -EZ)  # top grasp, tips 1 mm under the table
    high = grasp_frame([0.2, 0, g.tip_offset + 0.001], EX, -EZ)
    np.testing.assert_array_equal(checker.collides(np.stack([low, high])), [True, False])


def test_collides_matches_the_component_checks_on_random_grasps():
    rng = np.random.default_rng(4)
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.03)
    mesh.apply_translation([0, 0, 0.03])
    checker = CollisionChecker(mesh, GripperGeometry())
    T0 = grasp_frames(mesh.centroid + rng.normal(scale=0.02, size=(300, 3)), rng.normal(size=(300, 3)), 0.0)
    T, _, _ = align_to_table(T0, rng)
    expected = checker.collides_table(T) | checker.contains_vertex(T) | checker.collides_object_fcl(T)
    np.testing.assert_array_equal(checker.collides(T), expected)
    assert 0 < expected.sum() < len(T)


def test_collision_checker_rejects_bad_input():
    checker = CollisionChecker(_box_on_table([0.04, 0.04, 0.04]), GripperGeometry())
    with pytest.raises(ValueError, match=r"\(n, 4, 4\)"):
        checker.collides(np.eye(3))
    bad = np.eye(4)
    bad[0, 3] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        checker.collides(bad[None])
    with pytest.raises(ValueError, match="trimesh"):
        CollisionChecker("box.obj", GripperGeometry())


def test_gripper_geometry_rejects_non_positive_sizes():
    with pytest.raises(ValueError, match="finger_length"):
        GripperGeometry(finger_length=0.0)


# ----------------------------------------------------------------------------- robust collision


def test_robust_collision_flags_fingertips_2mm_above_the_table():
    from datagen.collision import RobustCollisionParams, collision_free_probability

    g = GripperGeometry()
    mesh = _box_on_table([0.04, 0.04, 0.04])
    T = grasp_frame([0.2, 0, g.tip_offset + 0.002], EX, -EZ)[None]  # top grasp, tips 2 mm above the table
    assert not CollisionChecker(mesh, g).collides(T)[0]  # the paper's check: nominal pose, no clearance
    robust = RobustCollisionParams(num_samples=64)
    checker = CollisionChecker(mesh, g, clearance=robust.clearance)
    high = grasp_frame([0.2, 0, g.tip_offset + 0.03], EX, -EZ)[None]
    p = collision_free_probability(checker, np.concatenate([T, high]), robust, np.random.default_rng(0))
    assert p[0] < 0.75 and p[1] == 1.0  # 5 mm of noise per axis plus the clearance: many executions hit the table
    assert CollisionChecker(mesh, g, clearance=0.003).collides(T)[0]  # a 3 mm clearance alone flags it


def test_robust_collision_keeps_a_grasp_with_room_to_spare():
    from datagen.collision import RobustCollisionParams, collision_free_probability

    g = GripperGeometry()
    mesh = _box_on_table([0.02, 0.04, 0.06])  # 2 cm wide in a 5 cm opening
    T = grasp_frame([0, 0, 0.045], EX, -EZ)[None]
    robust = RobustCollisionParams(num_samples=32)
    checker = CollisionChecker(mesh, g, clearance=robust.clearance)
    p = collision_free_probability(checker, T, robust, np.random.default_rng(0))
    assert p[0] == 1.0
    p2 = collision_free_probability(checker, T, robust, np.random.default_rng(0))
    np.testing.assert_array_equal(p, p2)


def test_clearance_grows_the_gripper_towards_the_object():
    g = GripperGeometry()
    mesh = _box_on_table([0.046, 0.04, 0.04])  # 2 mm gap on each side of the open jaws
    T = grasp_frame([0, 0, 0.03], EX, -EZ)[None]
    assert not CollisionChecker(mesh, g).collides(T)[0]
    assert not CollisionChecker(mesh, g, clearance=0.001).collides(T)[0]
    assert CollisionChecker(mesh, g, clearance=0.003).collides(T)[0]
    with pytest.raises(ValueError, match="clearance"):
        CollisionChecker(mesh, g, clearance=-0.001)
