"""vgq.camera resampling to the model's focal length and vgq.crop's window grid."""

import numpy as np
import pytest

from vgq.camera import (
    CameraMismatch,
    Intrinsics,
    check_client_intrinsics,
    deproject,
    map_pixels,
    project,
    resample_depth,
)
from vgq.crop import CropGeometry, grid_window_centers, in_training_range

MODEL = Intrinsics()  # fx = fy = 525, 300 x 300


def _plane_image(intr: Intrinsics, n=(0.2, -0.1, 1.0), d=0.8) -> np.ndarray:
    """Depth (metres) of the plane n . p = d seen by ``intr`` (exact per pixel centre)."""
    u, v = np.meshgrid(np.arange(intr.width), np.arange(intr.height))
    rays = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u, dtype=float)], -1)
    return (d / (rays @ np.asarray(n))).astype(np.float32)


def test_resampled_image_is_what_the_model_camera_sees():
    cam = Intrinsics(fx=615.0, fy=615.0, cx=170.0, cy=140.0, width=352, height=300)
    out, dst = resample_depth(_plane_image(cam), cam, MODEL)
    assert dst.fx == pytest.approx(525.0, rel=0.005) and dst.fy == pytest.approx(525.0, rel=0.005)
    want = _plane_image(dst)
    inner = (slice(2, -2), slice(2, -2))  # borders average with edge replication
    np.testing.assert_allclose(out[inner], want[inner], atol=2e-4)


def test_pixels_map_along_the_same_ray():
    cam = Intrinsics(fx=450.0, fy=460.0, cx=160.0, cy=120.0, width=320, height=240)
    _, dst = resample_depth(np.ones((240, 320), np.float32), cam, MODEL)
    pts = np.array([[0.05, -0.02, 0.7], [-0.1, 0.08, 0.9]])
    uv = project(pts, cam)[:, :2]
    np.testing.assert_allclose(map_pixels(uv, cam, dst), project(pts, dst)[:, :2], atol=1e-9)
    back = deproject(np.column_stack([map_pixels(uv, cam, dst), pts[:, 2]]), dst)
    np.testing.assert_allclose(back, pts, atol=1e-9)


def test_missing_pixels_stay_missing_and_never_blend():
    cam = Intrinsics(fx=700.0, fy=700.0, cx=149.5, cy=149.5)
    d = np.full((300, 300), 0.8, np.float32)
    d[100:140, 100:140] = 0.0
    d[200, 200] = np.nan
    out, _ = resample_depth(d, cam, MODEL)
    valid = out > 0
    assert np.all(np.abs(out[valid] - 0.8) < 1e-5)  # no value between 0 and 0.8 anywhere
    assert (~valid).sum() > 0.5 * 40 * 40 * (525 / 700) ** 2


def test_model_focal_length_is_left_alone():
    d = np.random.default_rng(0).uniform(0.5, 1.0, (300, 300)).astype(np.float32)
    out, dst = resample_depth(d, MODEL, MODEL)
    assert dst == MODEL and np.array_equal(out, d)


@pytest.mark.parametrize(
    "cam, field",
    [
        (Intrinsics(fx=200.0, fy=525.0), "fx"),
        (Intrinsics(fx=525.0, fy=1200.0), "fy"),
        (Intrinsics(cx=400.0), "cx"),
        (Intrinsics(cy=-3.0), "cy"),
    ],
)
def test_unservable_cameras_name_the_field(cam, field):
    with pytest.raises(CameraMismatch) as e:
        check_client_intrinsics(cam, MODEL)
    assert e.value.field == field and field in str(e.value)


@pytest.mark.parametrize("shape", [(300, 300), (480, 640), (97, 131)])
def test_every_grasp_gets_a_window_within_kappa(shape):
    geom = CropGeometry()
    rng = np.random.default_rng(1)
    uv = rng.uniform([0, 0], [shape[1] - 1, shape[0] - 1], (500, 2))
    c = grid_window_centers(uv, shape, geom)
    assert np.all(in_training_range(uv, c, geom))
    # a real window centre (integer origin) and few distinct windows
    assert np.allclose((c - (geom.window / 2 - 0.5)) % 1, 0)
    assert len(np.unique(c, axis=0)) <= np.prod(np.ceil(np.array(shape) / 72) + 1)


def test_centred_grasps_share_the_central_window():
    geom = CropGeometry()
    c = grid_window_centers([[149.5, 149.5], [160.0, 140.0], [120.0, 180.0]], (300, 300), geom)
    np.testing.assert_array_equal(c, np.tile([149.5, 149.5], (3, 1)))


def test_a_missing_focal_length_follows_the_other_at_the_models_aspect():
    from vgq.camera import Intrinsics, focal_lengths

    model = Intrinsics(fx=500.0, fy=550.0, cx=149.5, cy=149.5, width=300, height=300)
    assert focal_lengths(None, None, model) == (500.0, 550.0)
    assert focal_lengths(600.0, None, model) == (600.0, 660.0)
    assert focal_lengths(None, 660.0, model) == (600.0, 660.0)
    assert focal_lengths(610.0, 620.0, model) == (610.0, 620.0)
