"""Ferrari-Canny values pinned by hand: hull distances of wrench sets with known answers, a
closed form for the symmetric two-contact soft-finger grasp, monotonicity in friction, and a
graspable object that yields both labels.

Closed form of the symmetric grasp (contacts at (-a, 0, 0) and (a, 0, 0) on outward normals
-x and +x, both pushes along the normals, torque scaling s, friction mu, k cone faces, finger
radius r). The wrenches split into two orthogonal parts: the torsional ones
(0, 0, 0, +-g, 0, 0) with g = s pi r^2 mu, and the friction-cone edges, which have no tau_x.
For a unit direction w = (cos t) e_taux + (sin t) w', the support is max(g |cos t|, sin t H(w')),
so epsilon = g H / sqrt(g^2 + H^2), with H the epsilon of the cone edges in their own five
dimensions (f_x, f_y, f_z, tau_y, tau_z). Contact 0's edges are (1, mu d, s a mu J d), contact
1's (-1, mu e, -s a mu J e) (d, e: the k cone directions, J: a quarter turn). Write w' as
(w_x, (A + B) / 2, J (A - B) / (2 s a)): the support is max(w_x + mu m(A), -w_x + mu m(B)), m(v)
the largest projection of v on a cone direction, at least |v| cos(pi / k). The least is at
A = 0, B along the worst direction, w_x = mu c |B| / 2 (c = cos(pi / k), sigma = s a):

    H = mu c sigma / sqrt(1 + sigma^2 + (mu c sigma)^2)
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest
import trimesh

from datagen.grasps import AntipodalParams, sample_antipodal_grasps
from datagen.quality import (
    QualityParams,
    ferrari_canny,
    ferrari_canny_batch,
    hull_quality,
    robust_ferrari_canny,
    rotation_matrices,
)

P = QualityParams()


def symmetric_epsilon(a: float, s: float, mu: float, k: int, r: float) -> float:
    """The closed form of the module docstring."""
    sigma, c, g = s * a, np.cos(np.pi / k), s * np.pi * r**2 * mu
    h = mu * c * sigma / np.sqrt(1 + sigma**2 + (mu * c * sigma) ** 2)
    return g * h / np.hypot(g, h)


def symmetric_grasp(a: float) -> tuple[np.ndarray, np.ndarray]:
    return np.array([[-a, 0.0, 0.0], [a, 0.0, 0.0]]), np.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])


def test_hull_distance_of_the_cross_polytope_is_r_over_sqrt6():
    """conv(+-r e_i) in 6-D: every facet x . (+-1, ..., +-1) = r lies r / sqrt(6) from the origin."""
    for r in (1.0, 0.02, 3.5):
        W = np.concatenate([np.eye(6), -np.eye(6)]) * r
        assert hull_quality(W) == pytest.approx(r / np.sqrt(6), rel=1e-6)


def test_hull_distance_of_a_shifted_box_is_its_nearest_face():
    """The box [-1, 2] x [-1, 1]^4 x [-0.25, 3]: the nearest face is x_6 = -0.25."""
    lo, hi = np.array([-1, -1, -1, -1, -1, -0.25]), np.array([2, 1, 1, 1, 1, 3.0])
    corners = np.array([np.where(bits, hi, lo) for bits in itertools.product([0, 1], repeat=6)])
    assert hull_quality(corners) == pytest.approx(0.25, rel=1e-6)
    assert hull_quality(corners * 0.004) == pytest.approx(0.001, rel=1e-6)


@pytest.mark.parametrize(
    "a, s, mu, k, r",
    [
        (0.015, 25.0, 0.5, 8, 0.01),  # the defaults: torsion-limited, epsilon just below g = 0.003927
        (0.015, 10.0, 0.5, 8, 0.01),
        (0.03, 50.0, 0.8, 4, 0.005),
        (0.01, 25.0, 0.3, 12, 0.05),  # a wide finger pad: the cone edges limit it, not torsion
    ],
)
def test_symmetric_soft_finger_grasp_has_its_closed_form_epsilon(a, s, mu, k, r):
    c, n = symmetric_grasp(a)
    p = dataclasses.replace(P, num_cone_faces=k, finger_radius=r)
    assert ferrari_canny(c, n, mu, p, s) == pytest.approx(symmetric_epsilon(a, s, mu, k, r), rel=1e-6)


def test_symmetric_grasp_at_the_defaults_is_pinned():
    c, n = symmetric_grasp(0.015)
    assert ferrari_canny(c, n, 0.5, P, 25.0) == pytest.approx(0.0039258101, rel=1e-6)


def test_closed_form_holds_for_the_same_grasp_rotated_about_the_centre_of_mass():
    c, n = symmetric_grasp(0.02)
    R = rotation_matrices(np.array([[0.3, -0.9, 1.7]]))[0]
    want = symmetric_epsilon(0.02, 25.0, 0.5, 8, P.finger_radius)
    assert ferrari_canny(c @ R.T, n @ R.T, 0.5, P, 25.0) == pytest.approx(want, rel=1e-6)


def test_torque_scaling_changes_quality_as_the_closed_form_says():
    c, n = symmetric_grasp(0.015)
    got = np.array([ferrari_canny(c, n, 0.5, P, s) for s in (5.0, 10.0, 25.0, 50.0, 100.0)])
    want = np.array([symmetric_epsilon(0.015, s, 0.5, 8, P.finger_radius) for s in (5.0, 10.0, 25.0, 50.0, 100.0)])
    np.testing.assert_allclose(got, want, rtol=1e-6)
    assert np.all(np.diff(got) > 0)  # here torsion limits the quality, and it grows with s


def test_more_friction_never_lowers_quality():
    """The cone of mu lies in the cone of any larger mu (its edges are convex combinations of the
    wider cone's edges and their mean, the normal), and torsion grows with mu: the hull only grows."""
    rng = np.random.default_rng(4)
    m = 60
    c = rng.normal(0, 0.02, (m, 2, 3))
    axis = c[:, 1] - c[:, 0]
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    tilt = rotation_matrices(rng.normal(0, 0.35, (2 * m, 3))).reshape(m, 2, 3, 3)
    n = np.stack([np.einsum("mij,mj->mi", tilt[:, 0], -axis), np.einsum("mij,mj->mi", tilt[:, 1], axis)], 1)
    mus = np.linspace(0.0, 1.5, 16)
    q = np.stack([ferrari_canny_batch(c, n, mu, P, 25.0) for mu in mus], 1)  # (m, len(mus))
    assert np.all(np.diff(q, axis=1) >= -1e-9), np.diff(q, axis=1).min()
    assert (q[:, -1] > 0).sum() >= m // 3 and (q[:, 0] == 0).all()  # the check has grasps to compare


def test_a_box_yields_positive_and_negative_robust_labels():
    """A 3 x 4 x 5 cm box is graspable: about half its antipodal grasps pass label_threshold, the
    others (near edges, off the centre of mass) do not."""
    box = trimesh.creation.box(extents=(0.03, 0.04, 0.05))
    g = sample_antipodal_grasps(box, AntipodalParams(num_samples=40), np.random.default_rng(0))
    q = robust_ferrari_canny(box, g, P, np.random.default_rng(1))
    positive = q > P.label_threshold
    assert len(g) >= 30 and 0.3 <= positive.mean() <= 0.9, (len(g), positive.mean())
    assert np.ptp(q) > 0.003  # qualities spread: not one value for every grasp
