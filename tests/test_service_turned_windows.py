"""A model trained on windows turned towards the jaw (``datagen crops --jaw-turns K``) is served
and planned on windows turned the same way: the service's scores are the network's on the crops
datagen cuts for those grasps, the planner's scorer agrees with the service, the turned images
are cached beside the upload, and a scene turned a quarter scores the same where the turned
windows coincide."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import table_scene
from datagen_fakes import fake_dataset
from servers import running_service

from service.client import ServiceClient
from vgq import inpaint
from vgq.camera import DEFAULT_INTRINSICS, level_depth, map_pixels
from vgq.crop import CropGeometry, grid_window_centers, pose_uv, window_origin
from vgq.pose import canonical_quaternion, roll_quaternions
from vgq.turns import pose_jaw_angles, turn_index

GEOM = CropGeometry(96, 32, 36.0, jaw_turns=4)


@pytest.fixture(scope="module")
def turned_model(tmp_path_factory, briefly_trained):
    from export.onnx_export import export_model

    net, imgs, poses = briefly_trained
    out = tmp_path_factory.mktemp("models") / "turned"
    export_model(net, out, imgs[:32], poses[:32], GEOM, DEFAULT_INTRINSICS, dataset={"recipe": "tests"})
    return out


@pytest.fixture(scope="module")
def client(turned_model):
    with running_service(turned_model, "--threads", "1") as url, ServiceClient(url) as c:
        yield c


def _grasps(n: int, seed: int, lo=(40, 40), hi=(260, 260)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    g = np.zeros((n, 7))
    g[:, :2] = rng.uniform(lo, hi, (n, 2))
    g[:, 2] = rng.uniform(0.6, 0.7, n)
    g[:, 3:] = canonical_quaternion(rng.standard_normal((n, 4)))
    return g


def _grid_crops(depth, uv, jaw, arch, geom, rng):
    """datagen.crops.crop_grasps with each window on the service's grid instead of a random offset."""
    origins = window_origin(grid_window_centers(uv, depth.shape, geom), geom)
    out = [inpaint.crop_filled(depth, o, geom) for o in origins]
    images = np.stack([o[0] for o in out])
    return images, pose_uv(uv, np.stack([o[1] for o in out]), geom), np.array([o[2] for o in out])


def test_the_service_scores_the_crops_datagen_cuts_for_the_same_grasps(client, turned_model, tmp_path, monkeypatch):
    import datagen.crops as crops_mod
    from datagen import storage
    from service.runtime import FastModel

    fake_dataset(tmp_path / "g", n_objects=1, n_images=1, n_grasps=40, seed=4)
    sh = next(iter(storage.open_dataset(tmp_path / "g")))
    depth, g = sh.images["depth"][0], sh.grasps
    monkeypatch.setattr(crops_mod, "crop_grasps", _grid_crops)
    uv = np.stack([g["u"], g["v"]], 1).astype(np.float64)
    inside = np.all((uv > 50) & (uv < 250), axis=1)  # windows well inside every turned canvas
    uv, z, q = uv[inside], g["z"][inside].astype(np.float64), g["q"][inside].astype(np.float64)
    images, puv, _, q_turned = crops_mod.turned_crops(depth, uv, z, q, GEOM, DEFAULT_INTRINSICS, None)
    model = FastModel(turned_model)
    poses = np.concatenate([puv, z[:, None], q_turned], axis=1).astype(np.float32)
    expected = np.array(
        [model.score(model.encode(images[i : i + 1, None]), poses[i : i + 1])[0] for i in range(len(z))]
    )
    rows = np.concatenate([uv, z[:, None], q], axis=1)
    got = client.score_details(client.upload(depth), rows)
    assert len(set(turn_index(pose_jaw_angles(uv, z, q, DEFAULT_INTRINSICS), 4).tolist())) == 4  # every turn used
    np.testing.assert_allclose(got["raw_score"], expected, atol=1e-5)


def test_the_planners_turned_scorer_scores_as_the_service_does(client, turned_model):
    from planning.policy import window_scorer
    from service.runtime import FastModel

    depth, g = table_scene(), _grasps(48, seed=1)
    ours, missing = window_scorer(FastModel(turned_model), depth, DEFAULT_INTRINSICS, "grid").score(g)
    np.testing.assert_allclose(ours, client.score_details(client.upload(depth), g)["raw_score"], atol=1e-5)
    assert missing.shape == (48,)


def test_turned_images_are_cached_beside_the_upload(client):
    depth = table_scene(box=(100, 190, 110, 175))
    image = client.upload(depth)
    g = _grasps(64, seed=2)
    first = client.score_details(image, g)
    again = client.score_details(image, g)
    assert first["windows_encoded"] == first["windows"] > 4 and again["windows_encoded"] == 0
    np.testing.assert_array_equal(first["raw_score"], again["raw_score"])


def test_a_scene_turned_a_quarter_scores_the_same_where_the_turned_windows_coincide(client):
    # a quarter turn of the scene moves each grasp's jaw angle by 90 deg, two turns of 45 deg: for
    # grasps in turns 2 and 3 the service's turned image is the very same picture; for turns 0 and 1 it
    # is that picture turned half way round (turns are chosen modulo 180 deg), a different input
    depth = table_scene(box=(100, 190, 110, 175))
    g = _grasps(80, seed=3, lo=(90, 90), hi=(210, 210))
    quarter = np.pi / 2
    d_rot, intr_rot = level_depth(depth, DEFAULT_INTRINSICS, quarter)
    g_rot = g.copy()
    g_rot[:, :2] = map_pixels(g[:, :2], DEFAULT_INTRINSICS, intr_rot, quarter)
    g_rot[:, 3:] = canonical_quaternion(roll_quaternions(g[:, 3:], quarter))
    a = client.score_details(client.upload(depth), g)["raw_score"]
    intr = (intr_rot.fx, intr_rot.fy, intr_rot.cx, intr_rot.cy)
    b = client.score_details(client.upload(d_rot, intrinsics=intr), g_rot)["raw_score"]
    turn = turn_index(pose_jaw_angles(g[:, :2], g[:, 2], g[:, 3:], DEFAULT_INTRINSICS), 4)
    same = turn >= 2
    assert 10 < same.sum() < len(g) - 10
    np.testing.assert_allclose(b[same], a[same], atol=1e-5)
    assert np.abs(b[~same] - a[~same]).max() > 1e-3  # the half-turned windows are another input


def test_a_mostly_missing_turned_window_is_a_422_naming_the_requests_rows(client):
    from service.client import ServiceError

    depth = table_scene()
    depth[170:300, 170:300] = 0.0  # no reading in the lower right
    g = np.zeros((4, 7))
    g[:, 2] = 0.66
    g[:3, :2], g[:3, 3] = [[100, 100], [110, 100], [100, 110]], 1.0  # jaw along u: turn 0, well-read windows
    g[3, :2], g[3, 3:] = [240, 240], [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]  # jaw along v: turn 2, in the hole
    assert turn_index(pose_jaw_angles(g[:, :2], g[:, 2], g[:, 3:], DEFAULT_INTRINSICS), 4).tolist() == [0, 0, 0, 2]
    with pytest.raises(ServiceError, match="has no depth reading") as e:
        client.score(client.upload(depth), g)
    assert e.value.status == 422 and e.value.details["grasps"] == [3]
