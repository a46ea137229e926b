"""Depth-sensor model (datagen.sensor) and its use by the crop stage: each effect does what
its parameters say on real rendered depth, draws are seeded per image, and training crops
are exactly what the service computes from the same corrupted image."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from datagen_fakes import fake_dataset

from datagen import storage
from datagen.__main__ import main as datagen_main
from datagen.crops import fast_window_origins, make_crops
from datagen.render import render_depth
from datagen.sensor import (
    CLEAN,
    PRESETS,
    SensorModel,
    blob_mask,
    correlated_noise,
    discontinuity_mask,
    image_rng,
    missing_fraction,
    resolve,
    shadow_mask,
)
from vgq import crop as vcrop
from vgq.camera import DEFAULT_INTRINSICS

FX = DEFAULT_INTRINSICS.fx
TABLE_Z, BOX_H = 0.70, 0.05


@pytest.fixture(scope="module")
def box_scene() -> np.ndarray:
    """Real rendered depth (embree) of a 6 x 4 x 5 cm box on the table, camera 0.7 m above,
    looking straight down (camera x = world x)."""
    m = trimesh.creation.box((0.06, 0.04, BOX_H))
    m.apply_translation((0, 0, BOX_H / 2))
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = (0, 0, TABLE_Z)
    return render_depth(m, T)


def box_columns(depth, row=150):
    top = np.flatnonzero(depth[row] < TABLE_Z - 0.01)
    return top[0], top[-1]


def test_clean_preset_is_the_identity(box_scene):
    out = CLEAN.apply(box_scene, np.random.default_rng(0))
    np.testing.assert_array_equal(out, box_scene)
    assert resolve("clean")[1].is_clean and not resolve(None)[1].is_clean  # the default is realistic


def test_draws_are_seeded_per_image(box_scene):
    s = PRESETS["realistic"]
    a = s.apply(box_scene, image_rng(0, 3, 7))
    np.testing.assert_array_equal(a, s.apply(box_scene, image_rng(0, 3, 7)))
    for other in (image_rng(1, 3, 7), image_rng(0, 4, 7), image_rng(0, 3, 8)):
        assert not np.array_equal(a, s.apply(box_scene, other))


def test_occlusion_shadow_lies_beside_the_box_away_from_the_projector(box_scene):
    u0, u1 = box_columns(box_scene)
    b = 0.075
    width = FX * b * (1 / (TABLE_Z - BOX_H) - 1 / TABLE_Z)  # disparity difference, px
    sh = shadow_mask(box_scene, b, FX)
    cols = np.flatnonzero(sh[150])
    assert cols.size and cols.max() == u0 - 1  # projector at +x: shadow on the -u side
    assert abs(cols.size - width) <= 1
    assert not sh[:, u1 + 1 :].any() and not sh[:100].any()  # nothing right of the box or away from it
    mirrored = np.flatnonzero(shadow_mask(box_scene, -b, FX)[150])
    assert mirrored.min() == u1 + 1 and abs(mirrored.size - width) <= 1
    assert not shadow_mask(box_scene, 0.0, FX).any()


def test_discontinuities_are_the_box_outline(box_scene):
    e = discontinuity_mask(box_scene, 0.005, 5.0)
    u0, u1 = box_columns(box_scene)
    assert e[150, u0 - 1] and e[150, u0] and e[150, u1] and e[150, u1 + 1]
    assert not e[150, u0 + 1 : u1].any() and not e[:, : u0 - 1].any()
    assert not discontinuity_mask(box_scene, 0.06, 5.0).any()  # a 5 cm jump is below 6 cm
    assert discontinuity_mask(box_scene, 0.005, 5.0, width_px=3)[150, u0 - 3 : u0 + 3].all()


def test_a_steep_plane_is_not_a_discontinuity():
    """A plane seen at 80 deg incidence at the image centre (more towards its horizon): large
    depth steps per pixel, but no jump until the incidence nears 85 deg (z ~ 1.4 m)."""
    v = np.arange(300, dtype=np.float64)[:, None] - 149.5
    tilt = np.radians(80)
    # plane through (0, 0, 0.7) with normal (0, -sin, -cos): depth along the ray (x, y, 1)
    z = 0.7 * np.cos(tilt) / (np.cos(tilt) - np.sin(tilt) * v / DEFAULT_INTRINSICS.fy)
    z = np.where(z > 0, z, 0) * np.ones((1, 300))
    z[z > 5] = 0
    steps = np.abs(np.diff(z, axis=0))[z[1:] * z[:-1] > 0]
    assert steps.max() > 0.005  # a fixed depth threshold would call this an edge
    e = discontinuity_mask(z, 0.005, 5.0)
    assert not e[(z > 0) & (z < 1.2)].any()
    assert e[(z > 1.6) & (z < 4.5)].all()  # grazing beyond ~85 deg: the sensor loses it


def test_edge_dropout_probability_and_missing_readings(box_scene):
    s = SensorModel(edge_jump_m=0.005, edge_dropout=0.5)
    e = discontinuity_mask(box_scene, 0.005, 5.0)
    out = s.apply(box_scene, np.random.default_rng(0))
    dropped = out == 0
    assert not dropped[~e].any()
    assert 0.4 < dropped[e].mean() < 0.6


def test_blobs_follow_the_rate_and_radius():
    rng = np.random.default_rng(0)
    areas = [blob_mask((300, 300), 2.0, (4.0, 4.0), rng).sum() for _ in range(300)]
    # 2 discs of radius 4 per image on average (area ~50 px each, overlaps and borders aside)
    assert 2 * np.pi * 16 * 0.8 < np.mean(areas) < 2 * np.pi * 16 * 1.2
    assert blob_mask((300, 300), 0.0, (4.0, 4.0), rng).sum() == 0


def test_gamma_scale_error_has_the_configured_spread():
    flat = np.full((8, 8), 0.7, np.float32)
    s = SensorModel(gamma_shape=100.0)
    ratios = np.array([s.apply(flat, np.random.default_rng(i))[0, 0] / 0.7 for i in range(600)])
    assert abs(ratios.mean() - 1) < 0.015 and abs(ratios.std() - 0.1) < 0.015
    img = s.apply(flat, np.random.default_rng(0))
    assert np.all(img == img[0, 0])  # one scale per image


def test_read_gives_the_same_image_as_apply_and_the_scale_it_applied():
    d = np.random.default_rng(5).uniform(0.5, 0.9, (40, 40)).astype(np.float32)
    s = PRESETS["realistic"]
    img, scale = s.read(d, np.random.default_rng(3))
    assert np.array_equal(img, s.apply(d, np.random.default_rng(3))) and scale != 1.0
    gamma_only, _ = SensorModel(gamma_shape=1000.0).read(d, np.random.default_rng(3))
    assert np.allclose(
        gamma_only, (d * SensorModel(gamma_shape=1000.0).read(d, np.random.default_rng(3))[1]).astype(np.float32)
    )
    assert SensorModel().read(d, np.random.default_rng(3))[1] == 1.0  # clean: no scale


def test_pixel_noise_grows_with_depth():
    d = np.full((200, 200), 0.5, np.float32)
    d[:, 100:] = 1.0
    s = SensorModel(noise_base_m=0.0005, noise_quad_m=0.002)
    out = s.apply(d, np.random.default_rng(0)) - d
    for sl, z in ((np.s_[:, :100], 0.5), (np.s_[:, 100:], 1.0)):
        assert abs(out[sl].std() / (0.0005 + 0.002 * z**2) - 1) < 0.05


def test_correlated_noise_is_smooth_and_has_the_configured_sigma():
    rng = np.random.default_rng(0)
    n = np.stack([correlated_noise((300, 300), 0.005, 4.0, rng) for _ in range(20)])
    assert abs(n.std() / 0.005 - 1) < 0.25  # bicubic upsampling keeps most of the variance
    r = np.corrcoef(n[:, :, :-1].ravel(), n[:, :, 1:].ravel())[0, 1]
    assert r > 0.9  # neighbours move together (white noise: r ~ 0)
    always = SensorModel(gp_sigma_m=0.005, gp_rate=1.0).apply(np.full((40, 40), 0.7, np.float32), rng)
    assert always.std() > 0.001


def test_quantisation_to_one_millimetre(box_scene):
    out = PRESETS["realistic"].apply(box_scene, np.random.default_rng(0))
    mm = out[out > 0] * 1000
    np.testing.assert_allclose(mm, np.round(mm), atol=1e-3)


def test_realistic_preset_misses_few_pixels_and_keeps_the_rest_close(box_scene):
    fr = []
    for i in range(10):
        out = PRESETS["realistic"].apply(box_scene, np.random.default_rng(i))
        fr.append(missing_fraction(out))
        ok = out > 0
        assert np.median(np.abs(out[ok] / box_scene[ok] - 1)) < 0.1
    assert 0.001 < np.mean(fr) < 0.02


@pytest.mark.parametrize(
    "field, value, words",
    [
        ("gp_rate", 1.5, "probability"),
        ("baseline_m", 2.0, "[-1, 1]"),
        ("blob_radius_px", [6, 2], "pair"),
        ("gamma_shape", -1, ">= 0"),
        ("quantum_m", float("nan"), "finite"),
        ("edge_width_px", 0, "integer"),
        ("edge_angle_deg", 60, "(0, 45]"),
    ],
)
def test_out_of_range_values_name_the_setting(field, value, words):
    with pytest.raises(ValueError, match=field) as e:
        PRESETS["clean"].with_overrides({field: value})
    assert words in str(e.value)


def test_cli_rejects_a_bad_sensor_value_with_exit_2_and_one_line(tmp_path, capsys):
    fake_dataset(tmp_path / "g", n_objects=1, n_images=1, n_grasps=3)
    rc = datagen_main(
        [
            "crops",
            "--in",
            str(tmp_path / "g"),
            "--out",
            str(tmp_path / "c"),
            "--arch",
            "fast_vgqcnn",
            "--quiet",
            "--sensor-set",
            "edge_dropout=2",
        ]
    )
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "sensor.edge_dropout" in err
    assert not (tmp_path / "c" / "manifest.json").exists()
    rc = datagen_main(
        [
            "crops",
            "--in",
            str(tmp_path / "g"),
            "--out",
            str(tmp_path / "c"),
            "--arch",
            "fast_vgqcnn",
            "--quiet",
            "--sensor",
            "kinect",
        ]
    )
    assert rc == 2 and "kinect" in capsys.readouterr().err


def test_sensor_json_file_builds_on_a_preset(tmp_path):
    p = tmp_path / "s.json"
    p.write_text(json.dumps({"preset": "realistic", "baseline_m": 0.05}))
    name, s = resolve(str(p))
    assert name == "s" and s.baseline_m == 0.05 and s.gamma_shape == PRESETS["realistic"].gamma_shape


def test_crop_stage_crops_are_what_the_service_computes(tmp_path):
    """Corrupted training crops = service preprocessing of the same corrupted image."""
    from service.preprocess import window_input

    fake_dataset(tmp_path / "g", n_objects=1, n_images=2, n_grasps=40, seed=3)
    sensor = PRESETS["realistic"].with_overrides({"blob_rate": 30.0})  # plenty of holes
    m = make_crops(tmp_path / "g", tmp_path / "c", "fast_vgqcnn", seed=5, log=lambda s: None, sensor=sensor)
    assert m["sensor"]["params"]["blob_rate"] == 30.0 and m["counts"]["train"]["missing_fraction_mean"] > 0.005
    sh = next(iter(storage.open_dataset(tmp_path / "g")))
    a = storage.open_crops(tmp_path / "c", "train")
    geom = vcrop.CropGeometry(**m["geometry"])
    g = sh.grasps
    order = np.argsort(g["image_index"], kind="stable")  # the crop stage's row order
    rng = np.random.default_rng([5, sh.object_id])
    row = 0
    for img_i in np.unique(g["image_index"]):
        rows = order[g["image_index"][order] == img_i]
        depth = sensor.apply(sh.images["depth"][img_i], image_rng(5, sh.object_id, int(img_i)))
        assert missing_fraction(depth) > 0
        uv = np.stack([g["u"][rows], g["v"][rows]], 1).astype(np.float64)
        origins = fast_window_origins(uv, geom, rng)
        for k in range(len(rows)):
            win = window_input(depth, origins[k], geom, max_missing_fraction=1.0)
            np.testing.assert_array_equal(a["images"][row], win.image)
            assert np.all(win.image > 0)
            row += 1
    assert row == len(a["images"])
