"""datagen.pads: where the flat pads first touch the object, and the quality there.
Object frame = grasp frame offsets in metres."""

from __future__ import annotations

import numpy as np
import trimesh
from datagen_fakes import grasp_frame

from datagen.gripper import GripperGeometry
from datagen.pads import pad_contacts, pad_quality
from datagen.quality import QualityParams, ferrari_canny

EX, EY, EZ = np.eye(3)
G = GripperGeometry()


def test_pads_on_a_box_rotated_in_the_jaws_touch_where_the_pad_edge_meets_the_face():
    theta = np.radians(20)
    box = trimesh.creation.box(extents=[0.03, 0.08, 0.05])
    box.apply_transform(trimesh.transformations.rotation_matrix(theta, [0, 0, 1]))
    T = grasp_frame([0, 0, 0], EX, -EZ)  # top grasp, jaws along x, pads span y in [-1, 1] cm
    ok, c, n = pad_contacts(box, T[None], G)
    assert ok[0]
    # analytic: the rotated face n.p = -0.015 (n = (cos, sin, 0)) cut by the pad edge y = +0.01;
    # along z the pad spans [-0.01, 0.04] (approach -z, tip 1 cm past the TCP), the box [-0.025, 0.025]
    x0 = (-0.015 - 0.01 * np.sin(theta)) / np.cos(theta)
    np.testing.assert_allclose(c[0, 0], [x0, 0.01, 0.0075], atol=1e-6)
    np.testing.assert_allclose(c[0, 1], [-x0, -0.01, 0.0075], atol=1e-6)
    np.testing.assert_allclose(n[0], [-EX, EX], atol=1e-12)


def test_a_face_flat_against_the_pad_touches_at_the_centre_of_the_overlap():
    box = trimesh.creation.box(extents=[0.03, 0.08, 0.05])
    T = grasp_frame([0, 0.005, 0], EX, -EZ)
    ok, c, _ = pad_contacts(box, T[None], G)
    assert ok[0]
    np.testing.assert_allclose(c[0], [[-0.015, 0.005, 0.0075], [0.015, 0.005, 0.0075]], atol=1e-6)


def test_pads_report_no_contact_off_the_object_or_when_it_is_wider_than_the_opening():
    box = trimesh.creation.box(extents=[0.03, 0.08, 0.05])
    off = grasp_frame([0.0, 0.2, 0.0], EX, -EZ)
    wide = grasp_frame([0, 0, 0], EY, -EZ)  # 8 cm across the jaws
    ok, _, _ = pad_contacts(box, np.stack([off, wide]), G)
    np.testing.assert_array_equal(ok, [False, False])


def test_pad_quality_on_an_aligned_box_equals_point_contact_quality_at_the_pad_contacts():
    P = QualityParams()
    box = trimesh.creation.box(extents=[0.03, 0.08, 0.05])
    T = grasp_frame([0, 0.005, 0], EX, -EZ)
    q, ok, c = pad_quality(box, T[None], G, P, 25.0)
    expected = ferrari_canny(c[0], np.array([-EX, EX]), 0.5, P, 25.0)
    assert ok[0] and q[0] > 0
    assert q[0] == expected
