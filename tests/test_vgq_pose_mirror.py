"""vgq.pose.mirror_poses: a grasp's pose row in the left-right mirror image of its scene."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vgq.pose import POSE_COLUMNS, matrix_from_quaternion, mirror_poses

COLS = POSE_COLUMNS["fast_vgqcnn"]
M = np.diag([-1.0, 1.0, 1.0])  # the camera frame's mirror x -> -x


def _rows(n=50, seed=0):
    rng = np.random.default_rng(seed)
    q = Rotation.random(n, random_state=seed).as_quat()[:, [3, 0, 1, 2]]  # (w, x, y, z)
    q[q[:, 0] < 0] *= -1
    uv = rng.uniform(-12, 12, (n, 2))
    z = rng.uniform(0.4, 1.1, (n, 1))
    return np.hstack([uv, z, q])


def test_the_mirrored_grasp_touches_the_mirrored_contacts_and_approaches_along_the_mirrored_axis():
    rows = _rows()
    mir = mirror_poses(rows, COLS)
    R, Rm = matrix_from_quaternion(rows[:, 3:]), matrix_from_quaternion(mir[:, 3:])
    p = np.column_stack([rows[:, :2], rows[:, 2]])  # a stand-in TCP; only its mirror matters here
    half = 0.025
    for i in range(len(rows)):
        contacts = {tuple(np.round(M @ (p[i] + s * half * R[i][:, 0]), 9)) for s in (-1, 1)}
        pm = M @ p[i]
        contacts_m = {tuple(np.round(pm + s * half * Rm[i][:, 0], 9)) for s in (-1, 1)}
        assert contacts == contacts_m  # the jaws close on the same (mirrored) points
        np.testing.assert_allclose(Rm[i][:, 2], M @ R[i][:, 2], atol=1e-12)  # approach mirrored
        assert np.linalg.det(Rm[i]) == pytest.approx(1.0)  # a proper rotation, not a reflection
    np.testing.assert_array_equal(mir[:, 0], -rows[:, 0])  # u mirrored, v and z kept
    np.testing.assert_array_equal(mir[:, 1:3], rows[:, 1:3])
    assert (mir[:, 3] >= 0).all()


def test_mirroring_twice_is_the_identity():
    rows = _rows(seed=1)
    np.testing.assert_allclose(mirror_poses(mirror_poses(rows, COLS), COLS), rows, atol=1e-12)


def test_architectures_without_u_or_a_quaternion_keep_what_they_have():
    rows = _rows(seed=2)
    vgq = mirror_poses(rows[:, 2:], POSE_COLUMNS["vgqcnn"])
    np.testing.assert_allclose(vgq, mirror_poses(rows, COLS)[:, 2:], atol=1e-12)
    np.testing.assert_array_equal(mirror_poses(rows[:, 2:3], POSE_COLUMNS["gqcnn"]), rows[:, 2:3])
    with pytest.raises(ValueError, match="pose rows"):
        mirror_poses(rows[:, :5], COLS)
