"""vgq.ood: each out-of-distribution flag fires for its cause and only for it."""

import numpy as np

from vgq.ood import APPROACH_AWAY, CENTER_MISSING, WINDOW_MISSING, Z_OUT_OF_RANGE, approach_away, flag_names, ood_flags
from vgq.pose import quaternion_from_matrix

DEPTH = np.full((40, 50), 0.7, np.float32)
TOWARDS = [1.0, 0.0, 0.0, 0.0]  # identity: approach along the camera's +z, into the scene


def _rot_x(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def test_approach_angle_threshold_is_90_degrees():
    q = quaternion_from_matrix(np.stack([_rot_x(np.radians(a)) for a in (0, 60, 89, 91, 150, 180)]))
    assert approach_away(q).tolist() == [False, False, False, True, True, True]


def test_an_in_distribution_grasp_has_no_flag():
    assert ood_flags(np.array([[10, 20, 0.7, *TOWARDS]]), DEPTH, (0.3, 1.1)).tolist() == [0]


def test_each_cause_sets_its_bit():
    d = DEPTH.copy()
    d[5, 7] = 0.0
    d[6, 8] = np.nan
    away = quaternion_from_matrix(_rot_x(np.radians(120)))
    rows = np.array(
        [
            [10, 20, 0.7, *away],
            [10, 20, 1.5, *TOWARDS],
            [10, 20, 0.2, *TOWARDS],
            [7.2, 4.8, 0.7, *TOWARDS],
            [8, 6, 0.7, *TOWARDS],
        ]
    )
    f = ood_flags(rows, d, (0.3, 1.1))
    assert f.tolist() == [APPROACH_AWAY, Z_OUT_OF_RANGE, Z_OUT_OF_RANGE, CENTER_MISSING, CENTER_MISSING]
    f = ood_flags(rows[:1], d, (0.3, 1.1), window_missing=np.array([True]))
    assert f.tolist() == [APPROACH_AWAY | WINDOW_MISSING]


def test_flag_names_in_bit_order():
    assert flag_names(APPROACH_AWAY | CENTER_MISSING) == ["approach_away_from_camera", "center_on_missing_depth"]
    assert flag_names(0) == []
