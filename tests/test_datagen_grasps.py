"""datagen.grasps: antipodal sampler and jaw-closing contact search."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from datagen.grasps import (
    AntipodalParams,
    find_contacts,
    in_friction_cones,
    sample_antipodal_grasps,
    sample_in_cone,
)

PARAMS = AntipodalParams(num_samples=60)


@pytest.fixture(scope="module")
def box():
    return trimesh.creation.box(extents=(0.03, 0.04, 0.06))


@pytest.fixture(scope="module")
def sphere():
    return trimesh.creation.icosphere(subdivisions=3, radius=0.02)


@pytest.fixture(scope="module")
def box_grasps(box):
    return sample_antipodal_grasps(box, PARAMS, np.random.default_rng(0))


def test_sampler_returns_requested_number_on_graspable_box(box_grasps):
    assert len(box_grasps) == PARAMS.num_samples


def test_sampler_widths_within_opening(box_grasps):
    assert np.all(box_grasps.widths <= PARAMS.max_width + 1e-12)
    assert np.all(box_grasps.widths >= PARAMS.min_contact_distance)
    # a 6 cm side cannot be grasped with a 5 cm opening: no grasp along z
    assert np.all(np.abs(box_grasps.axes[:, 2]) < 0.99)


def test_sampler_contacts_lie_on_surface(box, box_grasps):
    _, dist, _ = trimesh.proximity.closest_point(box, box_grasps.contacts.reshape(-1, 3))
    assert np.max(dist) < 1e-9


def test_sampler_geometry_is_consistent(box_grasps):
    g = box_grasps
    d = g.contacts[:, 1] - g.contacts[:, 0]
    assert np.allclose(np.linalg.norm(g.axes, axis=1), 1.0)
    assert np.allclose(d, g.widths[:, None] * g.axes, atol=1e-12)
    assert np.allclose(g.centers, g.contacts.mean(axis=1), atol=1e-12)


def test_sampler_grasps_satisfy_friction_cone_condition(sphere):
    g = sample_antipodal_grasps(sphere, PARAMS, np.random.default_rng(1))
    assert len(g) > 0
    half_angle = np.arctan(PARAMS.friction_coef)
    ang0 = np.arccos(np.clip(np.einsum("ij,ij->i", g.axes, -g.normals[:, 0]), -1, 1))
    ang1 = np.arccos(np.clip(np.einsum("ij,ij->i", -g.axes, -g.normals[:, 1]), -1, 1))
    assert np.all(ang0 <= half_angle + 1e-9) and np.all(ang1 <= half_angle + 1e-9)
    assert np.all(in_friction_cones(g.axes, g.normals, PARAMS.friction_coef))


def test_sampler_drops_near_duplicates(box_grasps):
    c, a = box_grasps.centers, box_grasps.axes
    dc = np.linalg.norm(c[:, None] - c[None], axis=2)
    da = (2 / np.pi) * np.arccos(np.clip(np.abs(a @ a.T), 0, 1))
    d = dc + PARAMS.dedupe_axis_weight * da
    np.fill_diagonal(d, np.inf)
    assert d.min() >= PARAMS.dedupe_distance


def test_sampler_is_deterministic_for_a_seed(box):
    g1 = sample_antipodal_grasps(box, PARAMS, np.random.default_rng(7))
    g2 = sample_antipodal_grasps(box, PARAMS, np.random.default_rng(7))
    assert np.array_equal(g1.contacts, g2.contacts)


def test_sampler_finds_nothing_on_object_wider_than_opening():
    big = trimesh.creation.box(extents=(0.08, 0.09, 0.1))
    g = sample_antipodal_grasps(big, AntipodalParams(num_samples=10, max_attempts_factor=5), np.random.default_rng(0))
    assert len(g) == 0 and g.contacts.shape == (0, 2, 3)


def test_find_contacts_closes_jaws_on_box_faces(box):
    ok, contacts, normals = find_contacts(box, np.array([[0.0, 0.005, 0.01]]), np.array([[1.0, 0.0, 0.0]]), 0.05)
    assert ok[0]
    assert np.allclose(contacts[0], [[-0.015, 0.005, 0.01], [0.015, 0.005, 0.01]], atol=1e-12)
    assert np.allclose(normals[0], [[-1, 0, 0], [1, 0, 0]])


def test_find_contacts_fails_when_a_jaw_starts_inside(box):
    # centred 2 cm off along the axis: jaw 0 starts inside the 3 cm box
    ok, _, _ = find_contacts(box, np.array([[0.02, 0.0, 0.0]]), np.array([[1.0, 0.0, 0.0]]), 0.05)
    assert not ok[0]


def test_find_contacts_fails_when_line_misses(box):
    ok, _, _ = find_contacts(box, np.array([[0.0, 0.5, 0.0]]), np.array([[1.0, 0.0, 0.0]]), 0.05)
    assert not ok[0]


def test_cone_samples_stay_inside_friction_cone():
    rng = np.random.default_rng(3)
    n = rng.standard_normal((500, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    d = sample_in_cone(n, 0.5, 8, rng)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    assert np.all(np.einsum("ij,ij->i", d, n) >= np.cos(np.arctan(0.5)) - 1e-12)


def test_bad_sampler_params_raise_value_error():
    with pytest.raises(ValueError, match="min_contact_distance"):
        AntipodalParams(max_width=0.01, min_contact_distance=0.02)
    with pytest.raises(ValueError, match="friction_coef"):
        AntipodalParams(friction_coef=-0.1)
