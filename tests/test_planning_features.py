"""planning.features: what the planner knows of a candidate, measured against the scene it rendered."""

import dataclasses

import numpy as np
import pytest

pytest.importorskip("trimesh")

from planning.features import PLAN_FEATURES, plan_features
from planning.sampler import Candidates, analyse_scene
from planning.types import PlanParams
from tests.planning_scenes import boxes_scene
from vgq.camera import DEFAULT_INTRINSICS
from vgq.gripper import GripperGeometry, box_corners, gripper_boxes


def _top_down(T_wc, height: float, width: float = 0.03, at=(0.0, 0.0)):
    """A grasp straight down onto the table at world (x, y, height), jaws along world x, in the camera frame."""
    T = np.eye(4)
    T[:3, :3] = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])  # x = world x, z = down
    T[:3, 3] = [*at, height]
    F = np.linalg.inv(T_wc) @ T
    c = F[:3, 3] + np.outer([-0.5, 0.5], width * F[:3, 0])
    return Candidates(F[None], c[None], np.array([width]), np.array([True]))


def test_features_of_a_top_down_grasp_match_the_true_table():
    depth, T_wc, _ = boxes_scene()  # a 3 x 4 x 5 cm box on the table z = 0
    scene = analyse_scene(depth, DEFAULT_INTRINSICS, PlanParams(), np.random.default_rng(0))
    g = GripperGeometry()
    cand = _top_down(T_wc, 0.035)
    f = plan_features(cand, np.array([0.7]), scene, g)
    assert list(f) == list(PLAN_FEATURES) and all(v.shape == (1,) for v in f.values())
    assert f["score"][0] == pytest.approx(0.7) and f["width"][0] == pytest.approx(0.03) and f["seen"][0] == 1.0
    assert f["approach_tilt"][0] < 2.0 and f["axis_tilt"][0] > 88.0  # the estimated table is ~level
    assert f["tcp_height"][0] == pytest.approx(0.035, abs=0.003)
    lowest = (box_corners(*gripper_boxes(g, swept=False)) @ np.diag([1.0, -1.0, -1.0]))[:, 2].min() + 0.035
    assert f["table_clearance"][0] == pytest.approx(lowest, abs=0.003)


def test_without_a_table_the_table_features_are_missing():
    depth, T_wc, _ = boxes_scene()
    scene = analyse_scene(depth, DEFAULT_INTRINSICS, PlanParams(), np.random.default_rng(0))
    f = plan_features(
        _top_down(T_wc, 0.035), np.array([0.5]), dataclasses.replace(scene, table=None), GripperGeometry()
    )
    assert np.isnan(f["table_clearance"][0]) and np.isnan(f["tcp_height"][0])
    assert np.isfinite(f["approach_tilt"][0])  # measured against the camera's up instead


def test_centre_offset_is_the_tcp_distance_from_the_object_centre_along_the_table():
    depth, T_wc, _ = boxes_scene()  # the box's centre of mass is above world (0, 0)
    scene = analyse_scene(depth, DEFAULT_INTRINSICS, PlanParams(), np.random.default_rng(0))
    g = GripperGeometry()
    off = [
        plan_features(_top_down(T_wc, 0.035, at=(0.0, y)), np.array([0.5]), scene, g)["centre_offset"][0]
        for y in (0.0, 0.015)
    ]
    assert off[0] < 0.006 and off[1] == pytest.approx(0.015, abs=0.006)  # the visible sides bias the centre a little
    # a grasp whose first contact lies on no object (the bare table) has no object centre
    assert np.isnan(plan_features(_top_down(T_wc, 0.0, at=(0.15, 0.0)), np.array([0.5]), scene, g)["centre_offset"][0])
