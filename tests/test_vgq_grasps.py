"""The grasp contract (vgq.grasps, vgq.pose): checked pose rows, errors that name the rows,
one canonical quaternion."""

from __future__ import annotations

import numpy as np
import pytest

from vgq.crop import CropGeometry, pose_uv
from vgq.grasps import MAX_Z_M, GraspError, pose_rows
from vgq.pose import PoseError, canonical_quaternion

GEOM = CropGeometry(96, 32, 36.0)
C = np.array([149.5, 149.5])


def grasps(k=6) -> np.ndarray:
    g = np.zeros((k, 7))
    g[:, :2] = C + np.linspace(-20, 20, k)[:, None]
    g[:, 2] = 0.6
    g[:, 3:] = [0.5, 0.5, 0.5, 0.5]
    return g


@pytest.mark.parametrize(
    "row,col,value,word",
    [
        (2, 0, np.nan, "non-finite"),
        (4, 2, 0.0, "depth z"),
        (1, 2, MAX_Z_M * 2, "depth z"),
        (3, 0, 10.0, "outside the window"),
    ],
)
def test_bad_rows_raise_a_value_error_naming_them(row, col, value, word):
    g = grasps()
    g[row, col] = value
    with pytest.raises(GraspError, match=word) as e:
        pose_rows(g, C, GEOM, 16)
    assert e.value.indices == [row] and isinstance(e.value, ValueError) and isinstance(e.value, PoseError)


def test_zero_quaternion_and_batch_size_are_named():
    g = grasps()
    g[5, 3:] = 1e-300
    with pytest.raises(GraspError, match="zero quaternion") as e:
        pose_rows(g, C, GEOM, 16)
    assert e.value.indices == [5]
    with pytest.raises(GraspError, match="at most 4"):
        pose_rows(grasps(5), C, GEOM, 4)
    with pytest.raises(GraspError, match="k = 0"):
        pose_rows(np.zeros((0, 7)), C, GEOM, 4)


def test_pose_rows_are_crop_offsets_depth_and_canonical_quaternion():
    g = grasps()
    g[:, 3:] *= -3.0  # same rotation, other sign and scale
    rows = pose_rows(g, C, GEOM, 16)
    assert rows.dtype == np.float32
    assert np.allclose(rows[:, :2], pose_uv(g[:, :2], C, GEOM))
    assert np.allclose(rows[:, 2], 0.6) and np.allclose(rows[:, 3:], 0.5)


def test_canonical_quaternion_sign_rule_when_w_is_zero():
    q = canonical_quaternion(np.array([[0.0, -1, 1, 0], [0, 0, -2, 1], [-1e-14, 0, 0, -1], [-0.5, 0.5, 0.5, 0.5]]))
    assert np.allclose(q[0], [0, 1 / np.sqrt(2), -1 / np.sqrt(2), 0])
    assert np.allclose(q[1], [0, 0, 2 / np.sqrt(5), -1 / np.sqrt(5)])
    assert np.allclose(q[2], [0, 0, 0, 1], atol=1e-12)
    assert np.allclose(q[3], [0.5, -0.5, -0.5, -0.5])


def test_canonical_quaternion_scales_without_overflow_and_names_bad_rows():
    q = np.array([[1e300, 1e300, 0, 0], [1.0, 0, 0, 0], [0, 0, 0, 0], [np.inf, 0, 0, 0]])
    assert np.allclose(canonical_quaternion(q[:2]), [[2**-0.5, 2**-0.5, 0, 0], [1, 0, 0, 0]])
    with pytest.raises(PoseError, match="zero norm") as e:
        canonical_quaternion(q[:3])
    assert e.value.indices == [2]
    with pytest.raises(PoseError, match="non-finite") as e:
        canonical_quaternion(q)
    assert e.value.indices == [3]
    assert canonical_quaternion(np.array([0.0, 0, 0, -2])).shape == (4,)
