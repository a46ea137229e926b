"""training.centroid_probe: a grasp's offset from the visible centroid, and what it adds on unseen objects."""

import numpy as np
import pytest

from training.centroid_probe import features, grasp_offsets, image_offsets, object_cv
from vgq.camera import Intrinsics

INTR = Intrinsics(fx=100.0, fy=100.0, cx=50.0, cy=50.0, width=100, height=100)
DOWN = np.array([[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 0.6], [0, 0, 0, 1]], float)  # 0.6 m above, looking down


def box_scene(u, v, z) -> dict:
    """A sampled shard of one image from DOWN: the table (z = 0) and a 5 cm tall box's 20 x 20 px top
    around pixel (49.5, 49.5), with grasps at pixels (u, v) and depths z."""
    depth = np.full((100, 100), 0.6)
    depth[40:60, 40:60] = 0.55
    n = len(u)
    return {
        "depth": depth[None],
        "T_world_camera": DOWN[None],
        "image_index": np.zeros(n, int),
        "u": np.asarray(u, float),
        "v": np.asarray(v, float),
        "z": np.asarray(z, float),
    }


def test_offset_is_the_horizontal_distance_from_the_visible_top_centroid():
    shard = box_scene([70.0, 49.5], [50.0, 49.5], [0.55, 0.58])
    shard["depth"][0, 0, 0] = 0.0  # no reading: ignored
    g = grasp_offsets(shard, np.array([0, 1]), INTR)
    centre = np.array([-0.5 * 0.55 / 100, 0.5 * 0.55 / 100])  # world x, y of the top's mean pixel (49.5, 49.5)
    assert g["offset"][0] == pytest.approx(np.hypot(0.11 - centre[0], 0.0 - centre[1]))
    assert g["offset"][1] == pytest.approx(np.hypot(*(np.array([-0.5, 0.5]) * 0.58 / 100 - centre)), abs=1e-9)
    assert g["height"] == pytest.approx([0.05, 0.02]) and g["top"] == pytest.approx([0.05, 0.05])


def test_the_image_alone_gives_the_same_offsets_through_its_table_plane():
    shard = box_scene([70.0, 20.0], [50.0, 45.0], [0.55, 0.6])
    known, seen = grasp_offsets(shard, np.array([0, 1]), INTR), image_offsets(shard, np.array([0, 1]), INTR)
    for k in ("offset", "height", "top"):
        np.testing.assert_allclose(seen[k], known[k], atol=2e-3)
    flat = {**shard, "depth": np.full((1, 100, 100), 0.6)}  # nothing on the table
    assert np.isnan(image_offsets(flat, np.array([0]), INTR)["offset"]).all()


def test_object_cv_credits_geometry_only_where_it_predicts_on_unseen_objects():
    rng = np.random.default_rng(0)
    oid = np.repeat(np.arange(8), 400)
    family = np.where(oid < 4, "a", "b")
    off = rng.uniform(0, 0.1, len(oid))
    y = off + 0.01 * rng.standard_normal(len(oid)) < 0.03  # holds near the centre only
    score = rng.uniform(0.05, 0.95, len(oid))  # a score blind to it
    geo = {"offset": off, "height": rng.uniform(0.01, 0.05, len(oid)), "top": np.full(len(oid), 0.06)}
    cv = object_cv({"score": features(score, None), "geo": features(score, geo)}, y, oid, family, repeats=2)
    assert cv["score"]["all"] < 0.6 < 0.9 < cv["geo"]["all"]
    assert set(cv["geo"]) == {"all", "a", "b"}


def test_cli_refuses_a_per_object_count_below_one(tmp_path, capsys):
    from training.__main__ import main

    argv = ["centroid-probe", "--sampled", str(tmp_path), "--crops", str(tmp_path), "--model-dir", str(tmp_path)]
    assert main([*argv, "--per-object", "0"]) == 2
    assert "--per-object must be >= 1" in capsys.readouterr().err
