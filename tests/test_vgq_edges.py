"""vgq at its edges, values written out by hand: the out-of-distribution flags at their
thresholds and at the image border, the client-camera checks at the ends of their ranges, the
resampled intrinsics of an off-centre non-square camera, and batched pose conversions.
(Written against the survivors of ./scripts/mutation.sh vgq, see docs/mutation.md.)"""

from __future__ import annotations

import numpy as np
import pytest

from vgq.camera import CameraMismatch, Intrinsics, check_client_intrinsics, resampled_intrinsics
from vgq.ood import (
    APPROACH_AWAY,
    CENTER_MISSING,
    WINDOW_MISSING,
    Z_OUT_OF_RANGE,
    approach_away,
    center_missing,
    ood_flags,
)
from vgq.pose import matrix_from_quaternion, quaternion_from_matrix

MODEL = Intrinsics()  # fx = fy = 525, cx = cy = 149.5, 300 x 300


@pytest.mark.parametrize(
    "q, away",
    [
        ((1.0, 0.0, 0.0, 0.0), False),  # approach along the principal ray
        ((0.0, 0.0, 0.0, 1.0), False),  # a turn about the ray keeps the approach
        ((0.5, 0.5, 0.5, 0.5), True),  # x^2 + y^2 = 1/2 exactly: psi = 90 deg, flagged
        ((0.8, 0.0, 0.6, 0.0), False),  # 1 - 2 * 0.36 = 0.28 > 0: psi = 73.7 deg
        ((0.6, 0.8, 0.0, 0.0), True),  # 1 - 2 * 0.64 < 0
        ((0.0, 0.0, 1.0, 0.0), True),  # half turn about y: approach back at the camera
    ],
)
def test_approach_away_threshold_by_hand(q, away):
    assert approach_away(np.array([q]))[0] == away


def test_all_four_flags_add_up():
    depth = np.ones((10, 10), np.float32)
    depth[5, 5] = 0.0
    g = np.array(
        [
            [5.0, 5.0, 2.0, 0.0, 0.0, 1.0, 0.0],  # every cause at once
            [2.0, 2.0, 0.5, 1.0, 0.0, 0.0, 0.0],  # none
            [2.0, 2.0, 0.3, 1.0, 0.0, 0.0, 0.0],  # z at the range's ends: inside
            [2.0, 2.0, 0.9, 1.0, 0.0, 0.0, 0.0],
        ]
    )
    flags = ood_flags(g, depth, (0.3, 0.9), window_missing=np.array([True, False, False, False]))
    assert flags.tolist() == [APPROACH_AWAY | Z_OUT_OF_RANGE | CENTER_MISSING | WINDOW_MISSING, 0, 0, 0]
    assert ood_flags(g[:1], depth, (0.3, 0.9)).tolist() == [APPROACH_AWAY | Z_OUT_OF_RANGE | CENTER_MISSING]


def test_center_missing_reads_the_nearest_border_pixel_for_points_outside():
    depth = np.ones((5, 6), np.float32)
    depth[:, 0] = depth[:, -1] = depth[0, :] = depth[-1, :] = 0.0  # a missing border
    border = [
        (-3.0, 2.0),
        (0.0, 2.0),
        (0.4, 2.0),
        (5.0, 2.0),
        (8.0, 2.0),
        (2.0, -3.0),
        (2.0, 0.0),
        (2.0, 4.0),
        (2.0, 7.0),
    ]
    inside = [(1.0, 2.0), (0.6, 2.0), (4.0, 2.0), (2.0, 1.0), (2.0, 3.0), (3.4, 2.6)]
    assert center_missing(np.array(border), depth).all()
    assert not center_missing(np.array(inside), depth).any()
    depth[2, 3] = np.nan
    assert center_missing(np.array([[3.0, 2.0]]), depth)[0]


def cam(**kw) -> Intrinsics:
    return Intrinsics(**{**MODEL.to_dict(), **kw})


@pytest.mark.parametrize("field, size", [("cx", 300), ("cy", 300)])
def test_principal_point_may_lie_anywhere_on_the_image_and_no_further(field, size):
    for ok in (-0.5, 0.0, size - 1.0, size - 0.5):
        assert check_client_intrinsics(cam(**{field: ok}), MODEL) == (1.0, 1.0)
    for bad in (-0.6, size - 0.4):
        with pytest.raises(CameraMismatch, match=rf"{field} = .* outside the image \(0 to {size - 1} px\)") as e:
            check_client_intrinsics(cam(**{field: bad}), MODEL)
        assert e.value.field == field


def test_focal_ratio_range_is_inclusive_and_named_in_pixels():
    assert check_client_intrinsics(cam(fx=1050.0, fy=262.5), MODEL) == (0.5, 2.0)
    for fx in (1051.0, 262.0):
        with pytest.raises(CameraMismatch, match=r"fx = .* outside the range this model serves: 262.5 to 1050 px"):
            check_client_intrinsics(cam(fx=fx), MODEL)


def test_focal_lengths_within_tolerance_are_used_as_they_are_each_axis_its_own():
    sx, sy = check_client_intrinsics(cam(fx=525.0 / 1.004, fy=600.0), MODEL)
    assert sx == 1.0 and sy == pytest.approx(525.0 / 600.0)
    sx, sy = check_client_intrinsics(cam(fx=600.0, fy=525.0 / 0.996), MODEL)
    assert sx == pytest.approx(525.0 / 600.0) and sy == 1.0


def test_resampled_intrinsics_of_an_off_centre_non_square_camera():
    c = Intrinsics(fx=400.0, fy=450.0, cx=100.3, cy=80.7, width=210, height=170)
    r = resampled_intrinsics(c, 1.3, 0.8)
    w, h = round(210 * 1.3), round(170 * 0.8)  # 273, 136
    sx, sy = w / 210, h / 170
    assert (r.width, r.height) == (w, h)
    assert r.fx == pytest.approx(400.0 * sx) and r.fy == pytest.approx(450.0 * sy)
    assert r.cx == pytest.approx((100.3 + 0.5) * sx - 0.5) and r.cy == pytest.approx((80.7 + 0.5) * sy - 0.5)
    tiny = resampled_intrinsics(Intrinsics(fx=10.0, fy=10.0, cx=0.0, cy=0.0, width=1, height=1), 0.4, 0.4)
    assert (tiny.width, tiny.height) == (1, 1)


def test_pose_conversions_keep_batch_shapes():
    rng = np.random.default_rng(3)
    q = rng.standard_normal((2, 3, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q *= np.where(q[..., :1] < 0, -1.0, 1.0)
    R = matrix_from_quaternion(q)
    assert R.shape == (2, 3, 3, 3)
    for i in range(2):
        for j in range(3):
            np.testing.assert_allclose(R[i, j], matrix_from_quaternion(q[i, j]), atol=1e-12)
    np.testing.assert_allclose(quaternion_from_matrix(R), q, atol=1e-12)
    np.testing.assert_allclose(
        matrix_from_quaternion(np.array([0.0, 0.0, 0.0, 1.0])), np.diag([-1.0, -1.0, 1.0]), atol=1e-12
    )
