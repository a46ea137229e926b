"""vgq.camera's level camera: the roll that turns a camera's rows level from the world's up
direction in its frame, the depth image and the pixels of the camera so turned, and
vgq.pose's orientations in the turned frame."""

from math import radians

import numpy as np
import pytest

from vgq.camera import (
    DEFAULT_INTRINSICS,
    Intrinsics,
    camera_tilt,
    footprint,
    level_depth,
    level_roll,
    leveled_intrinsics,
    map_pixels,
    roll_matrix,
    tilt_outside_training,
)
from vgq.pose import canonical_quaternion, matrix_from_quaternion, roll_quaternions

LEVEL_UP = np.array([0.0, -np.sin(radians(40)), -np.cos(radians(40))])  # a training camera at phi = 40 deg


def _plane_image(intr: Intrinsics, n, d=0.8) -> np.ndarray:
    """Depth (metres) of the plane n . p = d seen by ``intr`` (exact per pixel centre)."""
    u, v = np.meshgrid(np.arange(intr.width), np.arange(intr.height))
    rays = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u, dtype=float)], -1)
    return (d / (rays @ np.asarray(n))).astype(np.float32)


def test_a_training_camera_is_level_and_its_tilt_is_its_elevation():
    from datagen.camera import look_at_table_origin

    T = look_at_table_origin(0.7, radians(40), 1.1)[0]
    up = T[:3, :3].T @ [0.0, 0.0, 1.0]
    assert level_roll(up) == 0.0
    assert np.degrees(camera_tilt(up)) == pytest.approx(40.0)


@pytest.mark.parametrize("beta", [0.5, -1.2, np.pi / 2, 3.0])
def test_the_roll_that_levels_a_rolled_camera_undoes_its_roll(beta):
    up_rolled = roll_matrix(beta).T @ LEVEL_UP  # the same up, seen by the camera rolled by beta
    assert level_roll(up_rolled) == pytest.approx(-beta)
    assert level_roll(5.0 * up_rolled) == pytest.approx(-beta)  # any length


def test_a_tilt_beyond_the_training_range_is_outside_it():
    tilted = [0.0, -np.sin(radians(75)), -np.cos(radians(75))]
    assert tilt_outside_training(tilted) and not tilt_outside_training(LEVEL_UP)
    assert not tilt_outside_training(tilted, (0.0, radians(80))) and not tilt_outside_training(None)
    assert tilt_outside_training([0.0, 0.0, 1.0])  # looking up


def test_a_camera_looking_straight_down_or_rolled_a_hair_is_served_as_it_is():
    assert level_roll([0.0, 0.0, -1.0]) == 0.0
    assert level_roll(roll_matrix(radians(0.2)).T @ LEVEL_UP) == 0.0


@pytest.mark.parametrize("turns", [1, -1, 2])
def test_a_roll_a_hair_off_a_quarter_or_half_turn_is_that_turn(turns):
    for off in (0.3, -0.3):
        assert abs(level_roll(roll_matrix(radians(turns * 90 + off)).T @ LEVEL_UP)) == pytest.approx(
            abs(turns) * np.pi / 2, abs=1e-15
        )
    assert level_roll(roll_matrix(radians(90.8)).T @ LEVEL_UP) == pytest.approx(-radians(90.8))


@pytest.mark.parametrize("up", [[0.0, 0.0, 0.0], [np.nan, -1.0, 0.0], [1.0, 2.0]])
def test_a_zero_non_finite_or_short_up_is_refused(up):
    with pytest.raises(ValueError, match="up"):
        level_roll(up)


def test_a_quarter_turn_moves_pixels_exactly():
    d = np.random.default_rng(0).uniform(0.5, 1.0, (300, 300)).astype(np.float32)
    out, intr = level_depth(d, DEFAULT_INTRINSICS, np.pi / 2)
    assert intr == DEFAULT_INTRINSICS  # a square image about its centre: the same canvas
    np.testing.assert_array_equal(out, np.rot90(d, 1))
    uv = np.array([[10.0, 20.0], [200.0, 50.0]])
    moved = map_pixels(uv, DEFAULT_INTRINSICS, intr, np.pi / 2)
    np.testing.assert_allclose(
        out[moved[:, 1].round().astype(int), moved[:, 0].round().astype(int)], d[[20, 50], [10, 200]]
    )
    np.testing.assert_allclose(map_pixels(moved, intr, DEFAULT_INTRINSICS, -np.pi / 2), uv, atol=1e-9)


def test_a_turned_image_is_what_the_turned_camera_sees():
    cam = Intrinsics(fx=600.0, fy=590.0, cx=330.0, cy=230.0, width=640, height=480)
    n, roll = np.array([0.2, -0.3, 1.0]), radians(30)
    out, intr = level_depth(_plane_image(cam, n), cam, roll)
    assert intr.width > cam.width and intr.height > cam.height  # the whole image on a larger canvas
    want = _plane_image(intr, roll_matrix(roll).T @ n)  # the plane in the turned camera's frame
    inside = footprint(intr, cam, roll)
    assert 0.5 < inside.mean() < 1.0
    inner = inside & np.roll(inside, 2, 0) & np.roll(inside, -2, 0) & np.roll(inside, 2, 1) & np.roll(inside, -2, 1)
    np.testing.assert_allclose(out[inner], want[inner], atol=2e-4)
    assert (out[~inside] == 0).all()  # outside the image: no reading, never a made-up depth


def test_missing_readings_stay_missing_when_turned():
    d = np.full((300, 300), 0.7, np.float32)
    d[100:140, 100:140] = 0.0
    out, intr = level_depth(d, DEFAULT_INTRINSICS, radians(20))
    c = map_pixels([[119.5, 119.5]], DEFAULT_INTRINSICS, intr, radians(20))[0]
    assert out[int(round(c[1])), int(round(c[0]))] == 0.0
    read = out[out > 0]
    np.testing.assert_allclose(read, 0.7, rtol=1e-6)  # nothing blended between a reading and a hole


def test_leveled_canvas_holds_every_corner_of_the_image():
    cam = Intrinsics(fx=500.0, fy=500.0, cx=100.0, cy=300.0, width=400, height=360)
    for roll in (radians(10), radians(-75), np.pi):
        intr = leveled_intrinsics(cam, roll)
        corners = np.array([[-0.5, -0.5], [399.5, -0.5], [-0.5, 359.5], [399.5, 359.5]])
        c = map_pixels(corners, cam, intr, roll)
        assert (c >= -0.5 - 1e-6).all() and (c[:, 0] <= intr.width - 0.5 + 1e-6).all()
        assert (c[:, 1] <= intr.height - 0.5 + 1e-6).all()


def test_orientations_turn_with_the_camera():
    q = canonical_quaternion(np.random.default_rng(1).normal(size=(6, 4)))
    for roll in (0.3, -2.0, np.pi / 2):
        turned = matrix_from_quaternion(roll_quaternions(q, roll))
        np.testing.assert_allclose(turned, roll_matrix(roll).T @ matrix_from_quaternion(q), atol=1e-12)
        np.testing.assert_allclose(
            canonical_quaternion(roll_quaternions(roll_quaternions(q, roll), -roll)), q, atol=1e-12
        )
