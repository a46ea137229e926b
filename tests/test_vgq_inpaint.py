"""The shared missing-depth fill (vgq.inpaint): nearest valid pixel, window plus margin."""

from __future__ import annotations

import numpy as np
import pytest

from vgq import crop as vcrop
from vgq.inpaint import (
    MARGIN_PX,
    NoValidDepth,
    crop_filled,
    fill_nearest,
    filled_window,
    missing_mask,
)

GEOM = vcrop.CropGeometry(96, 32, 36.0)


def step_image() -> np.ndarray:
    """60 x 80: left half 0.60 m, right half 0.70 m."""
    d = np.full((60, 80), 0.70, np.float32)
    d[:, :40] = 0.60
    return d


def test_missing_means_zero_negative_or_not_finite():
    d = np.array([[0.5, 0.0, -0.1, np.nan, np.inf, -np.inf, 1e-6]], np.float32)
    assert missing_mask(d).tolist() == [[False, True, True, True, True, True, False]]


def test_holes_take_the_depth_of_the_nearest_valid_pixel():
    d = step_image()
    holed = d.copy()
    holed[20:30, 30:50] = 0.0  # straddles the step: columns 30..39 nearer the 0.60 side
    holed[5, 5] = np.nan
    out = fill_nearest(holed)
    assert out.dtype == np.float32 and np.all(np.isfinite(out)) and np.all(out > 0)
    np.testing.assert_array_equal(out[20:30, 30:39], np.float32(0.60))
    np.testing.assert_array_equal(out[20:30, 41:50], np.float32(0.70))
    assert out[5, 5] == np.float32(0.60)


def test_the_fill_takes_each_missing_pixel_from_the_valid_pixel_its_label_names():
    """fill_nearest relies on OpenCV numbering the valid pixels 1, 2, ... in raster order; this
    checks it against the labels themselves (each missing pixel's label is some valid pixel's)."""
    import cv2

    rng = np.random.default_rng(3)
    for _ in range(50):
        d = rng.uniform(0.3, 1.0, (int(rng.integers(20, 130)), int(rng.integers(20, 130)))).astype(np.float32)
        miss = rng.random(d.shape) < rng.uniform(0.01, 0.9)
        miss.flat[int(rng.integers(miss.size))] = False
        _, labels = cv2.distanceTransformWithLabels(
            miss.view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_5, labelType=cv2.DIST_LABEL_PIXEL
        )
        table = np.zeros(int(labels.max()) + 1, np.float32)
        table[labels[~miss]] = d[~miss]
        np.testing.assert_array_equal(fill_nearest(d * ~miss, miss), table[labels])


def test_valid_pixels_are_left_bit_for_bit():
    rng = np.random.default_rng(0)
    d = (0.6 + 0.05 * rng.random((50, 50))).astype(np.float32)
    holed = d.copy()
    holes = rng.random(d.shape) < 0.2
    holed[holes] = 0
    out = fill_nearest(holed)
    np.testing.assert_array_equal(out[~holes], d[~holes])
    np.testing.assert_array_equal(fill_nearest(d), d)


def test_a_region_without_valid_pixels_raises():
    with pytest.raises(NoValidDepth):
        fill_nearest(np.zeros((10, 10), np.float32))


def test_margin_supplies_the_neighbours_of_a_hole_at_the_window_border():
    d = np.full((300, 300), 0.70, np.float32)
    origin = (100, 100)
    d[:, :100] = 0.50  # everything left of the window (the margin) is nearer
    d[120:140, 100:103] = 0.0  # hole touching the window's left border
    win, frac = filled_window(d, origin, GEOM)
    np.testing.assert_array_equal(win[22:38, 0], np.float32(0.50))  # from the margin, 1 px away (no ties)
    win0, _ = filled_window(d, origin, GEOM, margin=0)
    np.testing.assert_array_equal(win0[22:38, 0], np.float32(0.70))  # without a margin: from inside only
    assert frac == pytest.approx(60 / 96**2)


def test_missing_fraction_counts_the_window_not_the_margin():
    d = np.full((300, 300), 0.70, np.float32)
    origin = (100, 100)
    d[100 - MARGIN_PX : 100, 100:196] = 0.0  # holes in the margin only
    _, frac = filled_window(d, origin, GEOM)
    assert frac == 0.0
    d[150:160, 150:160] = 0.0
    img, centre, frac = crop_filled(d, origin, GEOM)
    assert frac == pytest.approx(100 / 96**2)
    assert np.all(img > 0) and img.shape == (32, 32)
    np.testing.assert_allclose(centre, vcrop.window_center(origin, GEOM))


def test_complete_image_gives_exactly_vgq_crop():
    rng = np.random.default_rng(1)
    d = (0.6 + 0.1 * rng.random((300, 300))).astype(np.float32)
    for centre in [(149.5, 149.5), (10.0, 290.0), (-5.0, 3.0)]:  # inside, at, beyond the border
        origin = vcrop.window_origin(centre, GEOM)
        expected, c = vcrop.crop(d, centre, GEOM)
        got, c2, frac = crop_filled(d, origin, GEOM)
        np.testing.assert_array_equal(got, expected)
        np.testing.assert_array_equal(c, c2)
        assert frac == 0.0


def test_window_partly_outside_the_image_is_filled_from_replicated_edges():
    d = np.full((120, 120), 0.70, np.float32)
    d[:, :3] = 0.0  # missing first columns; the window hangs over the left edge
    img, _, frac = crop_filled(d, (-40, 10), GEOM)
    assert frac == pytest.approx(43 / 96)  # 40 replicated + 3 real missing columns
    np.testing.assert_array_equal(img, np.float32(0.70))


def test_bench_prints_numbers(capsys):
    from vgq.inpaint import main

    assert main(["--bench", "--reps", "3"]) == 0
    out = capsys.readouterr().out
    assert "ms" in out and "missing" in out


def test_depth_beyond_the_maximum_is_missing_and_filled():
    """A finite but absurd reading (1e30 m, or 65.535 m from a 16-bit 'invalid') is no reading:
    filled like a 0, so the encoder never sees it (it overflowed to a null score before)."""
    from vgq.camera import MAX_DEPTH_M
    from vgq.crop import CropGeometry
    from vgq.inpaint import crop_filled, missing_mask

    d = np.full((120, 120), 0.7, np.float32)
    d[60, 60], d[10, 10], d[20, 20] = 1e30, 65.535, MAX_DEPTH_M
    assert missing_mask(d)[60, 60] and missing_mask(d)[10, 10] and not missing_mask(d)[20, 20]
    img, _, frac = crop_filled(d, (12, 12), CropGeometry())
    assert np.isfinite(img).all() and img.max() <= MAX_DEPTH_M and frac > 0
