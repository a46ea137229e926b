"""datagen.quality: Ferrari-Canny epsilon metric and its robust version."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh

from datagen.grasps import AntipodalGrasps, AntipodalParams, sample_antipodal_grasps
from datagen.quality import (
    QualityParams,
    contact_wrenches,
    ferrari_canny,
    hull_quality,
    resolve_torque_scaling,
    robust_ferrari_canny,
    robust_ferrari_canny_samples,
    rotation_matrices,
)

P = QualityParams()
SCALE = 1 / 0.04

# a 3 cm wide box grasped across its x faces, slightly off the centre of mass
BOX_CONTACTS = np.array([[-0.015, 0.004, -0.003], [0.015, 0.004, -0.003]])
BOX_NORMALS = np.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])


def tilt(n, axis, angle):
    return rotation_matrices(np.asarray(axis, float)[None] * angle)[0] @ n


def test_box_grasp_across_opposite_faces_has_positive_quality():
    q = ferrari_canny(BOX_CONTACTS, BOX_NORMALS, 0.5, P, SCALE)
    assert q > 0
    # two contacts resist torque about their line only by torsion: that bounds the quality
    assert q <= SCALE * np.pi * P.finger_radius**2 * 0.5 + 1e-12


def test_normals_beyond_friction_cone_give_zero():
    n1 = tilt(BOX_NORMALS[1], [0, 0, 1], np.radians(40))  # 40 deg > atan(0.5) = 26.6 deg
    assert ferrari_canny(BOX_CONTACTS, np.array([BOX_NORMALS[0], n1]), 0.5, P, SCALE) == 0.0


def test_normals_inside_friction_cone_give_positive():
    n1 = tilt(BOX_NORMALS[1], [0, 0, 1], np.radians(20))
    assert ferrari_canny(BOX_CONTACTS, np.array([BOX_NORMALS[0], n1]), 0.5, P, SCALE) > 0


def test_hull_quality_is_zero_when_origin_outside():
    rng = np.random.default_rng(0)
    W = rng.standard_normal((20, 6))
    W[:, 0] = np.abs(W[:, 0]) + 0.1  # every wrench pushes along +x: origin outside
    assert hull_quality(W) == 0.0
    W[:10, 0] *= -1
    assert hull_quality(W) > 0.0


def test_hard_fingers_give_degenerate_hull_and_zero():
    hard = dataclasses.replace(P, soft_fingers=False)
    W, ok = contact_wrenches(BOX_CONTACTS[None], BOX_NORMALS[None], 0.5, hard, SCALE)
    assert ok[0] and np.linalg.matrix_rank(W[0], tol=1e-9) == 5
    assert ferrari_canny(BOX_CONTACTS, BOX_NORMALS, 0.5, hard, SCALE) == 0.0


def test_zero_friction_gives_zero():
    assert ferrari_canny(BOX_CONTACTS, BOX_NORMALS, 0.0, P, SCALE) == 0.0


def test_quality_invariant_to_rotation_about_grasp_axis():
    # a grasp whose axis passes through the centre of mass, normals tilted inside the cones:
    # rotating contacts and normals about that axis is a rigid motion of the whole grasp
    c = np.array([[-0.015, 0.0, 0.0], [0.015, 0.0, 0.0]])
    n = np.array([tilt([-1.0, 0, 0], [0, 0, 1], 0.2), tilt([1.0, 0, 0], [0, 1, 1] / np.sqrt(2), 0.3)])
    q0 = ferrari_canny(c, n, 0.5, P, SCALE)
    assert q0 > 0
    for angle in (0.3, 1.0, 2.5, np.pi):
        R = rotation_matrices(np.array([[angle, 0.0, 0.0]]))[0]
        q = ferrari_canny(c @ R.T, n @ R.T, 0.5, P, SCALE)
        assert q == pytest.approx(q0, rel=1e-6)


def test_quality_invariant_to_rigid_rotation_of_offset_grasp():
    n = np.array([BOX_NORMALS[0], tilt(BOX_NORMALS[1], [0, 1, 0], 0.25)])
    q0 = ferrari_canny(BOX_CONTACTS, n, 0.5, P, SCALE)
    R = rotation_matrices(np.array([[0.4, -1.1, 0.7]]))[0]
    assert ferrari_canny(BOX_CONTACTS @ R.T, n @ R.T, 0.5, P, SCALE) == pytest.approx(q0, rel=1e-6)


def test_ferrari_canny_rejects_bad_shapes():
    with pytest.raises(ValueError, match=r"\(2, 3\)"):
        ferrari_canny(np.zeros((3, 3)), np.zeros((3, 3)), 0.5, P, SCALE)


def test_torque_scaling_default_is_dexnet_rule():
    box = trimesh.creation.box(extents=(0.02, 0.04, 0.04))  # max corner (0.01, 0.02, 0.02)
    assert resolve_torque_scaling(box, dataclasses.replace(P, torque_scaling=None)) == pytest.approx(1 / 0.02)


def test_torque_scaling_max_radius_rule():
    box = trimesh.creation.box(extents=(0.02, 0.04, 0.04))
    p = dataclasses.replace(P, torque_scaling=None, torque_scaling_rule="max_radius")
    assert resolve_torque_scaling(box, p) == pytest.approx(1 / np.sqrt(0.01**2 + 0.02**2 + 0.02**2))
    assert resolve_torque_scaling(box, dataclasses.replace(P, torque_scaling=7.0)) == 7.0


def box_grasp(box):
    c = np.array([[-0.015, 0.004, -0.003], [0.015, 0.004, -0.003]])
    return AntipodalGrasps(
        centers=c.mean(axis=0)[None],
        axes=np.array([[1.0, 0.0, 0.0]]),
        contacts=c[None],
        normals=BOX_NORMALS[None],
        widths=np.array([0.03]),
    )


def test_robust_without_noise_equals_nominal_quality():
    box = trimesh.creation.box(extents=(0.03, 0.04, 0.05))
    quiet = QualityParams(
        num_samples=3,
        sigma_grasp_translation=0,
        sigma_grasp_rotation=0,
        sigma_object_translation=0,
        sigma_object_rotation=0,
        sigma_friction=0,
    )
    g = box_grasp(box)
    q = robust_ferrari_canny(box, g, quiet, np.random.default_rng(0))
    nominal = ferrari_canny(g.contacts[0], g.normals[0], 0.5, quiet, resolve_torque_scaling(box, quiet))
    assert q.shape == (1,) and q[0] == pytest.approx(nominal, rel=1e-12) and nominal > 0


def test_robust_quality_of_box_grasp_is_positive_and_not_above_nominal():
    box = trimesh.creation.box(extents=(0.03, 0.04, 0.05))
    g = box_grasp(box)
    samples = robust_ferrari_canny_samples(box, g, P, np.random.default_rng(1))
    nominal = ferrari_canny(g.contacts[0], g.normals[0], 0.5, P, resolve_torque_scaling(box, P))
    assert samples.shape == (1, P.num_samples)
    assert 0 < samples.mean() < nominal  # perturbations only lose quality on a box
    assert np.any(samples == 0)  # some perturbed jaws start inside the box (axis shift)


def test_robust_quality_of_sampled_grasps_is_deterministic_and_bounded():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.02)
    g = sample_antipodal_grasps(sphere, AntipodalParams(num_samples=20), np.random.default_rng(0))
    q1 = robust_ferrari_canny(sphere, g, P, np.random.default_rng(5))
    q2 = robust_ferrari_canny(sphere, g, P, np.random.default_rng(5))
    assert q1.shape == (len(g),) and np.array_equal(q1, q2)
    s = resolve_torque_scaling(sphere, P)
    assert np.all(q1 >= 0) and np.all(q1 <= s * np.pi * P.finger_radius**2 * 1.0)


def test_robust_of_no_grasps_is_empty():
    box = trimesh.creation.box(extents=(0.03, 0.04, 0.05))
    assert robust_ferrari_canny(box, AntipodalGrasps.empty(), P, np.random.default_rng(0)).shape == (0,)


def test_bad_quality_params_raise_value_error():
    with pytest.raises(ValueError, match="num_samples"):
        QualityParams(num_samples=0)
    with pytest.raises(ValueError, match="sigma"):
        QualityParams(sigma_friction=-1.0)


def test_jaw_axis_pushes_equal_contact_line_pushes_for_contacts_on_the_line():
    axes = (BOX_CONTACTS[1] - BOX_CONTACTS[0])[None] / 0.03
    W0, ok0 = contact_wrenches(BOX_CONTACTS[None], BOX_NORMALS[None], 0.5, P, SCALE)
    W1, ok1 = contact_wrenches(BOX_CONTACTS[None], BOX_NORMALS[None], 0.5, P, SCALE, axes=axes)
    np.testing.assert_allclose(W0, W1, atol=1e-12)
    assert ok0[0] and ok1[0]


def test_pads_pushing_along_the_jaw_axis_off_the_contact_line_do_not_slip():
    from datagen.quality import ferrari_canny_batch

    c = np.array([[-0.015, 0.01, 0.0], [0.015, -0.01, 0.0]])  # diagonal: the line leaves both cones
    line = ferrari_canny_batch(c[None], BOX_NORMALS[None], 0.5, P, SCALE)
    pads = ferrari_canny_batch(c[None], BOX_NORMALS[None], 0.5, P, SCALE, axes=np.array([[1.0, 0.0, 0.0]]))
    assert line[0] == 0.0
    assert pads[0] >= 0.0
    W, ok = contact_wrenches(c[None], BOX_NORMALS[None], 0.5, P, SCALE, axes=np.array([[1.0, 0.0, 0.0]]))
    assert ok[0]
