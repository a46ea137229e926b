"""planning.level: the world's up direction read from a depth image's table plane (level=table)."""

from math import degrees, radians

import numpy as np
import pytest

from planning.level import MIN_TILT, table_level
from vgq.camera import DEFAULT_INTRINSICS, camera_tilt, level_depth, roll_matrix

pytest.importorskip("trimesh")

from tests.planning_scenes import boxes_scene  # noqa: E402


def _angle_deg(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))


def test_the_table_normal_is_the_cameras_up():
    depth, T_wc, _ = boxes_scene(extents=((0.03, 0.04, 0.05), (0.05, 0.03, 0.04)), at=((0.0, 0.0), (0.08, 0.03)))
    true_up = T_wc[:3, :3].T @ [0.0, 0.0, 1.0]
    found = table_level(depth, DEFAULT_INTRINSICS)
    assert found is not None and found.inlier_fraction > 0.5
    assert _angle_deg(found.up, true_up) < 0.05 and found.roll == 0.0  # a training camera is level


def test_a_rolled_camera_reads_the_roll_that_levels_it():
    depth, T_wc, _ = boxes_scene(phi=0.6)
    beta = radians(30.0)
    rolled, intr = level_depth(depth, DEFAULT_INTRINSICS, beta)  # what the camera rolled by beta sees
    found = table_level(rolled, intr)
    assert _angle_deg(found.up, roll_matrix(beta).T @ (T_wc[:3, :3].T @ [0.0, 0.0, 1.0])) < 0.05
    assert degrees(found.roll) == pytest.approx(-30.0, abs=0.1)


def test_a_camera_nearly_straight_down_reads_as_straight_down():
    depth, _, _ = boxes_scene(phi=MIN_TILT / 2)
    found = table_level(level_depth(depth, DEFAULT_INTRINSICS, radians(40.0))[0], DEFAULT_INTRINSICS)
    assert found.up.tolist() == [0.0, 0.0, -1.0] and found.roll == 0.0 and camera_tilt(found.up) == 0.0


def test_no_plane_no_table():
    scattered = np.random.default_rng(0).uniform(0.4, 1.2, (120, 160)).astype(np.float32)
    assert table_level(scattered, DEFAULT_INTRINSICS) is None
    assert table_level(np.zeros((120, 160), np.float32), DEFAULT_INTRINSICS) is None


def test_the_same_image_reads_the_same_up():
    depth, _, _ = boxes_scene()
    noisy = depth + np.random.default_rng(1).normal(0, 0.002, depth.shape).astype(np.float32)
    a, b = table_level(noisy, DEFAULT_INTRINSICS), table_level(noisy, DEFAULT_INTRINSICS)
    assert a.up.tolist() == b.up.tolist()
