"""vgq.turns: the turn a grasp's window is cut from, one definition for datagen and the service."""

from __future__ import annotations

import numpy as np
import pytest

from vgq.camera import DEFAULT_INTRINSICS, leveled_intrinsics, map_pixels
from vgq.crop import CropGeometry
from vgq.pose import canonical_quaternion, roll_quaternions
from vgq.turns import pose_jaw_angles, turn_index, turn_roll


def _random_poses(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    uv = rng.uniform([20, 20], [280, 280], (n, 2))
    z = rng.uniform(0.4, 1.1, n)
    q = canonical_quaternion(rng.standard_normal((n, 4)))
    return uv, z, q


def test_turn_index_is_the_nearest_step_modulo_half_a_turn():
    deg = np.radians([0.0, 17.0, 23.0, 90.0, 134.0, 179.0, 180.0, -44.0, -46.0, -90.0, 359.0])
    assert turn_index(deg, 4).tolist() == [0, 0, 1, 2, 3, 0, 0, 3, 3, 2, 0]
    assert turn_index(deg, 2).tolist() == [0, 0, 0, 1, 1, 0, 0, 0, 1, 1, 0]
    assert turn_roll(3, 4) == pytest.approx(np.radians(135.0))
    assert turn_index(np.radians([-180.0, 180.0, 360.0]), 3).tolist() == [0, 0, 0]


def test_pose_jaw_angles_are_datagens_jaw_angles_of_the_projected_grasps():
    from datagen.project import project_grasps

    rng = np.random.default_rng(3)
    frames = np.tile(np.eye(4), (50, 1, 1))
    frames[:, :3, :3] = np.linalg.qr(rng.standard_normal((50, 3, 3)))[0]
    frames[:, :3, :3] *= np.sign(np.linalg.det(frames[:, :3, :3]))[:, None, None]
    frames[:, :3, 3] = rng.uniform([-0.1, -0.1, 0.6], [0.1, 0.1, 0.9], (50, 3))
    p = project_grasps(frames, np.eye(4))
    uv = np.stack([p["u"], p["v"]], axis=1)
    np.testing.assert_allclose(pose_jaw_angles(uv, p["z"], p["q"], DEFAULT_INTRINSICS), p["jaw_angle"], atol=1e-9)


@pytest.mark.parametrize("turns", [2, 3, 4, 8])
def test_the_turned_camera_sees_each_jaw_axis_within_half_a_step_of_horizontal(turns):
    uv, z, q = _random_poses(400, seed=turns)
    before = pose_jaw_angles(uv, z, q, DEFAULT_INTRINSICS)
    index = turn_index(before, turns)
    after = np.empty_like(before)
    for t in range(turns):
        sel = index == t
        roll = turn_roll(t, turns)
        canvas = leveled_intrinsics(DEFAULT_INTRINSICS, roll)
        uv_t = map_pixels(uv[sel], DEFAULT_INTRINSICS, canvas, roll)
        after[sel] = pose_jaw_angles(uv_t, z[sel], roll_quaternions(q[sel], roll), canvas)
    off = np.abs((after + np.pi / 2) % np.pi - np.pi / 2)  # from horizontal, either way along the axis
    assert off.max() <= np.pi / (2 * turns) + 1e-9
    assert np.abs((before + np.pi / 2) % np.pi - np.pi / 2).max() > np.pi / 4  # unturned, they were not


def test_jaw_turns_is_0_or_at_least_2_and_reads_back_only_when_set():
    assert "jaw_turns" not in CropGeometry().to_dict()  # older datasets and cards read alike
    g = CropGeometry(jaw_turns=4)
    assert CropGeometry.from_dict(g.to_dict()) == g and g.to_dict()["jaw_turns"] == 4
    for bad in (1, -2, 2.5):
        with pytest.raises(ValueError, match="jaw_turns"):
            CropGeometry(jaw_turns=bad)
    with pytest.raises(ValueError, match="exclude each other"):
        CropGeometry(kappa_px=0.0, align_jaw=True, jaw_turns=2)
    assert CropGeometry(jaw_turns=4).turning() == "turned in 4 steps" and CropGeometry().turning() == "not turned"
