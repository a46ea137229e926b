"""Crop stage: the crops are exactly vgq.crop's, for each architecture."""

from __future__ import annotations

import json

import numpy as np
import pytest
from datagen_fakes import fake_dataset

from datagen import storage
from datagen.crops import crop_object, fast_window_origins, geometry_for, make_crops
from vgq import crop as vcrop
from vgq.schema import SPLITS


@pytest.fixture(scope="module")
def one_image_dataset(tmp_path_factory):
    """One object, one depth image (a raised box on a table), 60 grasps."""
    root = tmp_path_factory.mktemp("grasps")
    fake_dataset(root, n_objects=1, n_images=1, n_grasps=60, seed=2)
    return root


def _first(root):
    sh = next(iter(storage.open_dataset(root)))
    return sh.images["depth"][0], sh.grasps


def test_vgqcnn_crops_are_centred_vgq_crops(one_image_dataset, tmp_path):
    m = make_crops(one_image_dataset, tmp_path, "vgqcnn", log=lambda s: None, sensor="clean")
    depth, g = _first(one_image_dataset)
    a = storage.open_crops(tmp_path, "train")
    geom = vcrop.CropGeometry(96, 32, 0.0)
    for i in range(len(g["u"])):
        expected, _ = vcrop.crop(depth, (g["u"][i], g["v"][i]), geom)
        np.testing.assert_array_equal(a["images"][i], expected)
    np.testing.assert_array_equal(a["poses"][:, :2], 0)
    np.testing.assert_allclose(a["poses"][:, 2], g["z"])
    np.testing.assert_allclose(a["poses"][:, 3:], g["q"])
    np.testing.assert_array_equal(a["labels"], (g["quality"] > 0.002).astype(np.uint8))
    assert m["geometry"]["kappa_px"] == 0
    assert m["counts"]["train"]["positive"] == int(a["labels"].sum())


def test_gqcnn_crops_are_rotated_vgq_crops(one_image_dataset, tmp_path):
    make_crops(one_image_dataset, tmp_path, "gqcnn", log=lambda s: None, sensor="clean")
    depth, g = _first(one_image_dataset)
    a = storage.open_crops(tmp_path, "train")
    geom = vcrop.CropGeometry(96, 32, 0.0)
    for i in range(0, len(g["u"]), 7):
        expected = vcrop.rotated_crop(depth, (g["u"][i], g["v"][i]), float(g["jaw_angle"][i]), geom)
        np.testing.assert_array_equal(a["images"][i], expected)


def test_fast_vgqcnn_crops_keep_grasps_within_kappa(one_image_dataset, tmp_path):
    m = make_crops(one_image_dataset, tmp_path, "fast_vgqcnn", kappa_px=24, log=lambda s: None, sensor="clean")
    depth, g = _first(one_image_dataset)
    a = storage.open_crops(tmp_path, "train")
    geom = vcrop.CropGeometry(96, 32, 24.0)
    uv = np.stack([g["u"], g["v"]], 1).astype(np.float64)
    centres = uv - a["poses"][:, :2].astype(np.float64) * geom.scale
    assert np.all(vcrop.in_training_range(uv, centres, geom))
    assert np.abs(a["poses"][:, :2]).max() > 4  # offsets actually spread over the range
    for i in range(len(uv)):
        expected, c = vcrop.crop(depth, centres[i], geom)
        np.testing.assert_allclose(c, centres[i], atol=1e-3)  # an exact integer window
        np.testing.assert_array_equal(a["images"][i], expected)
    saved = json.loads((tmp_path / "manifest.json").read_text())
    assert saved["kappa_px"] == 24 and saved["architecture"] == "fast_vgqcnn" == m["architecture"]


def test_a_smaller_window_crops_vgq_crops_at_its_scale(one_image_dataset, tmp_path):
    m = make_crops(one_image_dataset, tmp_path, "fast_vgqcnn", log=lambda s: None, sensor="clean", window=64)
    depth, g = _first(one_image_dataset)
    a = storage.open_crops(tmp_path, "train")
    geom = vcrop.CropGeometry(64, 32, 24.0)  # kappa in proportion to the default 36 px of 96
    assert m["geometry"] == geom.to_dict()
    uv = np.stack([g["u"], g["v"]], 1).astype(np.float64)
    centres = uv - a["poses"][:, :2].astype(np.float64) * geom.scale
    assert np.all(vcrop.in_training_range(uv, centres, geom))
    for i in range(0, len(uv), 9):
        expected, _ = vcrop.crop(depth, centres[i], geom)
        np.testing.assert_array_equal(a["images"][i], expected)


def test_fast_window_offsets_are_uniform_within_kappa():
    geom = vcrop.CropGeometry(96, 32, 12.0)
    g = np.tile([[150.3, 80.8]], (20000, 1))
    c = vcrop.window_center(fast_window_origins(g, geom, np.random.default_rng(0)), geom)
    off = g - c
    assert np.all(np.abs(off) <= 12 + 1e-9)
    hist = np.histogram(off[:, 0], bins=6, range=(-12, 12))[0]
    assert hist.min() > 0.8 * hist.max()


def test_crops_split_object_wise(tmp_path):
    fake_dataset(tmp_path / "g", n_objects=10, n_images=1, n_grasps=5)
    m = make_crops(tmp_path / "g", tmp_path / "c", "vgqcnn", log=lambda s: None, sensor="clean")
    seen = {}
    for s in SPLITS:
        ids = set(storage.open_crops(tmp_path / "c", s)["object_id"].tolist())
        assert ids == set(m["counts"][s]["objects"])
        for i in ids:
            assert seen.setdefault(i, s) == s
    assert sorted(seen) == list(range(10))


def test_a_test_only_copy_crops_the_test_objects_alone_with_their_family(tmp_path):
    g = fake_dataset(tmp_path / "g", n_objects=10, n_images=1, n_grasps=5)
    for o in g["objects"]:
        o["family"] = "mug" if o["object_id"] % 2 else "box"
    storage.write_manifest(tmp_path / "g", g)
    full = make_crops(tmp_path / "g", tmp_path / "c", "vgqcnn", log=lambda s: None, sensor="clean")
    m = make_crops(tmp_path / "g", tmp_path / "t", "vgqcnn", log=lambda s: None, sensor="clean", splits=("test",))
    assert m["counts"]["train"]["n"] == 0 and m["counts"]["val"]["n"] == 0
    assert m["counts"]["test"] == full["counts"]["test"]
    assert len(storage.open_crops(tmp_path / "t", "train")["images"]) == 0
    np.testing.assert_array_equal(
        storage.open_crops(tmp_path / "t", "test")["images"], storage.open_crops(tmp_path / "c", "test")["images"]
    )
    # each object's family, for per-family evaluation
    assert {o["object_id"]: o["family"] for o in m["source"]["objects"]} == {
        i: "mug" if i % 2 else "box" for i in range(10)
    }
    with pytest.raises(ValueError, match="splits"):
        make_crops(tmp_path / "g", tmp_path / "x", "vgqcnn", log=lambda s: None, splits=("tset",))


def test_kappa_only_for_fast_vgqcnn():
    with pytest.raises(ValueError, match="fast_vgqcnn only"):
        geometry_for("vgqcnn", 12)
    with pytest.raises(ValueError, match="kappa_px"):
        geometry_for("fast_vgqcnn", 60)
    with pytest.raises(ValueError, match="unknown architecture"):
        geometry_for("resnet")


def test_parallel_crops_equal_the_serial_ones(tmp_path):
    fake_dataset(tmp_path / "g", n_objects=6, n_images=2, n_grasps=8)
    a = make_crops(tmp_path / "g", tmp_path / "a", "fast_vgqcnn", log=lambda s: None, sensor="realistic")
    b = make_crops(tmp_path / "g", tmp_path / "b", "fast_vgqcnn", log=lambda s: None, sensor="realistic", workers=2)
    assert a["counts"] == b["counts"]
    for s in SPLITS:
        ca, cb = storage.open_crops(tmp_path / "a", s), storage.open_crops(tmp_path / "b", s)
        for k in ca:
            np.testing.assert_array_equal(ca[k], cb[k], err_msg=f"{s}/{k}")


def _stop_after(monkeypatch, k):
    """Make datagen.crops.crop_object raise KeyboardInterrupt on its (k+1)-th call; returns the call log."""
    import datagen.crops as crops_mod

    calls, real = [], crop_object

    def stopping(src, entry, *a):
        if len(calls) == k:
            raise KeyboardInterrupt
        calls.append(entry["object_id"])
        return real(src, entry, *a)

    monkeypatch.setattr(crops_mod, "crop_object", stopping)
    monkeypatch.setattr(crops_mod, "SAVE_EVERY_S", 0.0)
    return calls


def test_a_stopped_crop_run_resumes_where_it_stopped_with_the_same_rows(tmp_path, monkeypatch):
    fake_dataset(tmp_path / "g", n_objects=6, n_images=2, n_grasps=8)
    ref = make_crops(tmp_path / "g", tmp_path / "ref", "fast_vgqcnn", log=lambda s: None, sensor="realistic")
    first = _stop_after(monkeypatch, 4)
    with pytest.raises(KeyboardInterrupt):
        make_crops(tmp_path / "g", tmp_path / "c", "fast_vgqcnn", log=lambda s: None, sensor="realistic")
    assert not (tmp_path / "c" / storage.MANIFEST).exists()
    again = _stop_after(monkeypatch, 99)
    m = make_crops(tmp_path / "g", tmp_path / "c", "fast_vgqcnn", log=lambda s: None, sensor="realistic")
    assert sorted(first + again) == list(range(6)) and not set(first) & set(again)  # nothing cropped twice
    assert m["counts"] == ref["counts"]
    for s in SPLITS:
        a, b = storage.open_crops(tmp_path / "ref", s), storage.open_crops(tmp_path / "c", s)
        for k in a:
            np.testing.assert_array_equal(a[k], b[k], err_msg=f"{s}/{k}")
    assert sorted(p.name for p in (tmp_path / "c").rglob(".*")) == []  # no job or partial files left


def test_a_stopped_crop_run_does_not_resume_into_other_inputs(tmp_path, monkeypatch):
    fake_dataset(tmp_path / "g", n_objects=4, n_images=1, n_grasps=5)
    _stop_after(monkeypatch, 2)
    with pytest.raises(KeyboardInterrupt):
        make_crops(tmp_path / "g", tmp_path / "c", "fast_vgqcnn", log=lambda s: None, sensor="clean")
    with pytest.raises(storage.DatasetError, match="unfinished crop run with other inputs"):
        make_crops(tmp_path / "g", tmp_path / "c", "fast_vgqcnn", seed=1, log=lambda s: None, sensor="clean")


def test_crops_aligned_to_the_jaw_are_turned_with_their_pose_turned_alike(one_image_dataset, tmp_path):
    from vgq.pose import canonical_quaternion, roll_quaternions

    m = make_crops(one_image_dataset, tmp_path, "vgqcnn", log=lambda s: None, sensor="clean", align_jaw=True)
    depth, g = _first(one_image_dataset)
    a = storage.open_crops(tmp_path, "train")
    geom = vcrop.CropGeometry.from_dict(m["geometry"])
    assert geom.align_jaw and m["geometry"]["align_jaw"] is True and geom.kappa_px == 0
    for i in range(0, len(g["u"]), 7):
        expected = vcrop.rotated_crop(depth, (g["u"][i], g["v"][i]), float(g["jaw_angle"][i]), geom)
        np.testing.assert_array_equal(a["images"][i], expected)
    np.testing.assert_array_equal(a["poses"][:, :2], 0)
    np.testing.assert_allclose(a["poses"][:, 2], g["z"])
    turned = canonical_quaternion(roll_quaternions(g["q"], g["jaw_angle"]))
    np.testing.assert_allclose(a["poses"][:, 3:], turned, atol=1e-6)
    assert np.abs(a["poses"][:, 3:] - g["q"]).max() > 0.1  # the orientations did turn


def test_a_jaw_axis_in_the_image_plane_turns_horizontal_with_its_crop():
    # rotated_crop turns an in-image axis at angle a (from +u towards +v) horizontal; the pose's
    # orientation turned by the same a (vgq.pose.roll_quaternions) has its jaw axis along x
    from vgq.pose import matrix_from_quaternion, quaternion_from_matrix, roll_quaternions

    for a in np.radians([-170.0, -60.0, 0.0, 25.0, 90.0, 135.0]):
        x = np.array([np.cos(a), np.sin(a), 0.0])
        z = np.array([0.0, 0.0, 1.0])
        R = np.stack([x, np.cross(z, x), z], axis=1)
        rolled = roll_quaternions(quaternion_from_matrix(R[None])[0], a)
        np.testing.assert_allclose(matrix_from_quaternion(rolled)[:, 0], [1.0, 0.0, 0.0], atol=1e-9)


def test_fast_crops_with_jaw_turns_are_windows_of_the_image_turned_towards_each_jaw(one_image_dataset, tmp_path):
    from vgq import inpaint
    from vgq.camera import DEFAULT_INTRINSICS, level_depth, map_pixels
    from vgq.pose import canonical_quaternion, roll_quaternions
    from vgq.turns import pose_jaw_angles, turn_index, turn_roll

    m = make_crops(one_image_dataset, tmp_path, "fast_vgqcnn", log=lambda s: None, sensor="clean", jaw_turns=4)
    depth, g = _first(one_image_dataset)
    a = storage.open_crops(tmp_path, "train")
    geom = vcrop.CropGeometry.from_dict(m["geometry"])
    assert geom.jaw_turns == 4 and geom.kappa_px == 36
    uv = np.stack([g["u"], g["v"]], 1).astype(np.float64)
    index = turn_index(pose_jaw_angles(uv, g["z"], g["q"], DEFAULT_INTRINSICS), 4)
    assert len(set(index.tolist())) == 4  # every turn used
    for t in range(4):
        roll = turn_roll(t, 4)
        turned, intr = level_depth(depth, DEFAULT_INTRINSICS, roll)
        for i in np.flatnonzero(index == t)[:4]:
            uv_t = map_pixels(uv[i : i + 1], DEFAULT_INTRINSICS, intr, roll)[0]
            centre = uv_t - a["poses"][i, :2].astype(np.float64) * geom.scale
            assert vcrop.in_training_range(uv_t, centre, geom)
            expected, c, _ = inpaint.crop_filled(turned, vcrop.window_origin(centre, geom), geom)
            np.testing.assert_allclose(c, centre, atol=1e-3)  # an exact integer window of the turned image
            np.testing.assert_array_equal(a["images"][i], expected)
        rolled = canonical_quaternion(roll_quaternions(g["q"][index == t], roll))
        np.testing.assert_allclose(a["poses"][index == t, 3:], rolled, atol=1e-6)
    with pytest.raises(ValueError, match="fast_vgqcnn crops only"):
        geometry_for("vgqcnn", jaw_turns=4)


def test_align_jaw_is_for_vgqcnn_crops_and_reads_back_only_when_set():
    assert geometry_for("vgqcnn", align_jaw=True).align_jaw
    for arch in ("fast_vgqcnn", "gqcnn"):
        with pytest.raises(ValueError, match="vgqcnn crops only"):
            geometry_for(arch, align_jaw=True)
    with pytest.raises(ValueError, match="centred"):
        vcrop.CropGeometry(96, 32, 12.0, align_jaw=True)
    assert "align_jaw" not in vcrop.CropGeometry(96, 32, 0.0).to_dict()  # older datasets and cards read alike
    g = vcrop.CropGeometry(96, 32, 0.0, align_jaw=True)
    assert vcrop.CropGeometry.from_dict(g.to_dict()) == g
    assert vcrop.CropGeometry.from_dict({"window": 96, "out": 32, "kappa_px": 0}).align_jaw is False


def test_each_crop_carries_the_placement_row_the_service_computes_from_the_same_image(one_image_dataset, tmp_path):
    from planning.placement import placement_rows
    from vgq.camera import DEFAULT_INTRINSICS

    make_crops(one_image_dataset, tmp_path, "fast_vgqcnn", log=lambda s: None, sensor="clean")
    depth, g = _first(one_image_dataset)
    a = storage.open_crops(tmp_path, "train")
    uvz = np.stack([g["u"], g["v"], g["z"]], axis=1)
    expected = placement_rows(depth, DEFAULT_INTRINSICS, uvz, g["q"])
    np.testing.assert_array_equal(a["placement"], expected)
    on_box = (g["u"] > 121) & (g["u"] < 178) & (g["v"] > 101) & (g["v"] < 198)  # the raised box on its table
    assert on_box.any() and (a["placement"][on_box, 0] == 1).all()


def test_placement_rows_put_each_grasp_at_the_depth_the_sensor_image_shows_it(one_image_dataset, tmp_path):
    # the sensor's scale error moves the whole image, and a client reads its grasps off that image
    from datagen.sensor import PRESETS, image_rng
    from planning.placement import placement_rows
    from vgq.camera import DEFAULT_INTRINSICS
    from vgq.schema import PLACEMENT_GRASP_DEPTH

    m = make_crops(one_image_dataset, tmp_path, "fast_vgqcnn", log=lambda s: None, sensor="realistic")
    depth, g = _first(one_image_dataset)
    oid = int(next(iter(storage.open_dataset(one_image_dataset))).object_id)
    seen, scale = PRESETS["realistic"].read(depth, image_rng(0, oid, 0), DEFAULT_INTRINSICS)
    uvz = np.stack([g["u"], g["v"], g["z"]], axis=1)
    rows = storage.open_crops(tmp_path, "train")["placement"]
    as_seen = np.stack([g["u"], g["v"], scale * g["z"]], axis=1)
    np.testing.assert_array_equal(rows, placement_rows(seen, DEFAULT_INTRINSICS, as_seen, g["q"]))
    at_true_depth = placement_rows(seen, DEFAULT_INTRINSICS, uvz, g["q"])
    known = rows[:, 0] == 1
    assert known.any() and np.abs(rows[known, 5] - at_true_depth[known, 5]).min() > 1e-4  # the height moves
    assert m["placement_grasp_depth"] == PLACEMENT_GRASP_DEPTH


def test_context_views_are_wider_windows_of_the_same_centre(one_image_dataset, tmp_path):
    m = make_crops(one_image_dataset, tmp_path, "fast_vgqcnn", log=lambda s: None, sensor="clean", context_scale=3)
    depth, g = _first(one_image_dataset)
    a = storage.open_crops(tmp_path, "train")
    assert m["context"] == {"scale": 3, "window": 288}
    assert a["context"].dtype == np.float16 and a["context"].shape == (len(g["u"]), 32, 32)
    wide = vcrop.CropGeometry(288, 32, 0.0)
    centres = np.stack([g["u"], g["v"]], 1).astype(np.float64) - a["poses"][:, :2].astype(np.float64) * 3
    for i in range(0, len(centres), 7):  # the clean render has no hole to fill
        o = vcrop.window_origin(centres[i : i + 1], wide)[0]
        np.testing.assert_allclose(vcrop.window_center(o, wide), centres[i], atol=1e-3)
        block = vcrop.crop_window(depth, o, wide).reshape(32, 9, 32, 9).mean(axis=(1, 3))  # 9 x 9 block means
        np.testing.assert_allclose(a["context"][i], block, rtol=1e-3)
    plain = make_crops(one_image_dataset, tmp_path / "plain", "fast_vgqcnn", log=lambda s: None, sensor="clean")
    assert "context" not in plain and "context" not in storage.open_crops(tmp_path / "plain", "train")
    np.testing.assert_array_equal(storage.open_crops(tmp_path / "plain", "train")["images"], a["images"])


def test_context_views_are_for_unturned_fast_windows(one_image_dataset, tmp_path):
    with pytest.raises(ValueError, match="context"):
        make_crops(one_image_dataset, tmp_path, "vgqcnn", log=lambda s: None, sensor="clean", context_scale=3)
    with pytest.raises(ValueError, match="context scale"):
        make_crops(one_image_dataset, tmp_path / "b", "fast_vgqcnn", log=lambda s: None, context_scale=5)
