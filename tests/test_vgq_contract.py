"""The shared contract: crop geometry, pose convention, normalisation, model card."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vgq.camera import DEFAULT_INTRINSICS, deproject, project
from vgq.crop import (
    CropGeometry,
    crop,
    crop_window,
    in_training_range,
    pose_uv,
    rotated_crop,
    window_center,
    window_origin,
)
from vgq.normalization import Normalization
from vgq.pose import (
    approach_angle,
    canonical_quaternion,
    matrix_from_quaternion,
    pose_column_indices,
    quaternion_from_matrix,
)

G = CropGeometry(96, 32, 36.0)


def test_image_centre_window_is_pixel_aligned():
    o = window_origin([149.5, 149.5], G)
    assert tuple(o) == (102, 102) and tuple(window_center(o, G)) == (149.5, 149.5)


def test_crop_of_a_ramp_keeps_its_geometry():
    u = np.arange(300, dtype=np.float32)
    ramp = np.tile(u, (300, 1))  # depth = column index
    img, c = crop(ramp, [149.5, 149.5], G)
    # crop pixel j covers source columns 102 + 3j .. 102 + 3j + 2, centre 103 + 3j
    # (Pillow's filter reaches 3 px each way; at the window border it sees only the inside)
    assert np.allclose(img[0, 1:-1], 103 + 3 * np.arange(1, 31), atol=1e-3)
    assert img.shape == (32, 32) and img.dtype == np.float32


def test_pose_uv_is_offset_in_crop_pixels():
    assert np.allclose(pose_uv([[152.5, 140.5]], [149.5, 149.5], G), [[1.0, -3.0]])


def test_window_leaving_the_image_is_edge_padded():
    d = np.arange(100 * 100, dtype=np.float32).reshape(100, 100)
    w = crop_window(d, (-10, -10), G)
    assert w.shape == (96, 96) and w[0, 0] == d[0, 0] and w[10, 10] == d[0, 0] and w[20, 20] == d[10, 10]


def test_training_range_is_kappa_per_axis():
    c = [149.5, 149.5]
    assert in_training_range([[149.5 + 36, 149.5 - 36]], c, G).all()
    assert not in_training_range([[149.5 + 36.5, 149.5]], c, G).any()


def test_rotated_crop_makes_a_diagonal_line_horizontal():
    d = np.full((300, 300), 1.0, np.float32)
    for t in range(-60, 61):
        d[150 + t, 150 + t] = 0.5  # line at +45 deg (towards +v)
    img = rotated_crop(d, [150, 150], np.pi / 4, G)
    row = img[15:17].mean(axis=0)
    col = img[:, 15:17].mean(axis=1)
    assert row[4:28].mean() < col[4:28].mean() - 0.05


def test_project_deproject_round_trip():
    p = np.array([[0.01, -0.02, 0.6], [0.1, 0.05, 0.9]])
    assert np.allclose(deproject(project(p, DEFAULT_INTRINSICS), DEFAULT_INTRINSICS), p)


def test_canonical_quaternion_has_non_negative_w_and_unit_norm():
    q = canonical_quaternion(np.array([[-2.0, 0, 0, 0], [0, -1, 0, 0], [-1, 1, 1, 1]]))
    assert np.allclose(np.linalg.norm(q, axis=1), 1)
    assert np.all(q[:, 0] >= 0) and q[1, 1] == 1.0


def test_canonical_quaternion_rejects_zero():
    with pytest.raises(ValueError, match="zero"):
        canonical_quaternion(np.zeros(4))


def test_quaternion_matrix_round_trip_matches_scipy():
    R = Rotation.random(200, random_state=1)
    q = quaternion_from_matrix(R.as_matrix())
    ref = canonical_quaternion(R.as_quat()[:, [3, 0, 1, 2]])
    assert np.allclose(q, ref, atol=1e-12)
    assert np.allclose(matrix_from_quaternion(q), R.as_matrix(), atol=1e-12)


def test_approach_angle_is_the_angle_between_gripper_z_and_camera_z():
    R = Rotation.random(50, random_state=3)
    q = quaternion_from_matrix(R.as_matrix())
    want = np.arccos(np.clip(R.apply([0.0, 0.0, 1.0])[:, 2], -1, 1))
    np.testing.assert_allclose(approach_angle(q), want, atol=1e-7)
    assert approach_angle(np.array([1.0, 0, 0, 0])) == 0.0  # identity: approaching along the view axis


def test_pose_columns_select_from_the_full_row():
    assert pose_column_indices("vgqcnn") == [2, 3, 4, 5, 6] and pose_column_indices("gqcnn") == [2]
    with pytest.raises(ValueError, match="unknown architecture"):
        pose_column_indices("resnet")


def test_normalisation_leaves_quaternion_columns_and_fixes_zero_std():
    rng = np.random.default_rng(0)
    poses = rng.standard_normal((100, 7)) + 5
    poses[:, 2] = 0.6  # constant column
    n = Normalization.from_data(rng.random((100, 32, 32)), poses, ("u", "v", "z", "qw", "qx", "qy", "qz"))
    assert n.pose_mean[3:] == [0, 0, 0, 0] and n.pose_std[3:] == [1, 1, 1, 1]
    assert n.pose_std[2] == 1.0 and abs(n.pose_mean[0] - poses[:, 0].mean()) < 1e-9
    assert Normalization.from_dict(n.to_dict()) == n
