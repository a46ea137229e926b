"""A camera rolled about its optical axis, through the real service and the bundled model: with
the world's up direction (``up_x``, ``up_y``, ``up_z``) the image is turned level and scores
and plans as the level camera's; without it the model sees rows it was never trained on.
Bad up directions answer 422 naming the field."""

from __future__ import annotations

import io
import json

import httpx
import numpy as np
import pytest
from servers import ROOT, running_service

from service.client import ServiceClient, ServiceError
from vgq.camera import DEFAULT_INTRINSICS, level_depth, leveled_intrinsics, map_pixels, roll_matrix
from vgq.pose import roll_quaternions

MODEL_DIR = ROOT / "models" / "fast-vgqcnn-default"
BETA = np.pi / 2  # the client's camera: the training camera rolled a quarter turn (pixels move exactly)
LEVEL_UP = np.array([0.0, -0.5, -0.866])  # up as a level camera looking 30 deg off straight down sees it
UP = roll_matrix(BETA).T @ LEVEL_UP  # the same up, seen by the rolled camera


def rolled(depth, grasps, beta=BETA):
    """What the camera rolled by ``beta`` sees of ``depth`` and ``grasps`` (k, 7), and its intrinsics."""
    intr = leveled_intrinsics(DEFAULT_INTRINSICS, beta)
    g = np.array(grasps, dtype=np.float64)
    g[:, :2] = map_pixels(g[:, :2], DEFAULT_INTRINSICS, intr, beta)
    g[:, 3:7] = roll_quaternions(g[:, 3:7], beta)
    return level_depth(depth, DEFAULT_INTRINSICS, beta)[0], g, intr


@pytest.fixture(scope="module")
def url():
    with running_service(MODEL_DIR, "--threads", "1") as u:
        yield u


@pytest.fixture(scope="module")
def client(url):
    with ServiceClient(url) as c:
        yield c


@pytest.fixture(scope="module")
def heldout():
    """Six held-out images of the bundled model's test objects and their grasps."""
    d = np.load(ROOT / "examples" / "heldout_images.npz")
    return [(d["depth"][i], d["grasps"][d["image_index"] == i]) for i in np.unique(d["image_index"])[:6]]


def test_a_rolled_camera_with_its_up_scores_as_the_level_camera(client, heldout):
    moved = []
    for depth, grasps in heldout:
        level = client.score_details(client.upload(depth), grasps)["raw_score"]
        d, g, intr = rolled(depth, grasps)
        with_up = client.score_details(client.upload(d, intrinsics=intr, up=UP), g)["raw_score"]
        # the placement rows come from the image as uploaded: the same table and objects, their pixels in
        # another order for the table's seeded RANSAC, whose plane moves a little (measured |dp| <= 2.1e-4)
        np.testing.assert_allclose(with_up, level, atol=1e-3)
        without = client.score_details(client.upload(d, intrinsics=intr), g)["raw_score"]
        moved.append(np.abs(without - level))
    assert np.concatenate(moved).mean() > 0.05  # not given, the roll changes what the model sees


def test_a_window_reaching_past_a_turned_image_is_not_refused_for_the_canvas_corner(client, heldout):
    # turned level by 45 deg, the image sits diamond-wise on a larger canvas whose corners no camera
    # saw: those pixels lie beyond the image, as the edge of an unturned image does, not missing
    depth, grasps = heldout[0]
    beta = np.pi / 4
    up = roll_matrix(beta).T @ LEVEL_UP
    intr = leveled_intrinsics(DEFAULT_INTRINSICS, beta)
    d = level_depth(depth, DEFAULT_INTRINSICS, beta)[0]
    g = np.tile(grasps[:1], (2, 1))
    g[:, :2] = [[intr.cx, 12.0], [intr.cx, intr.cy]]  # near the top corner of the turned image; its centre
    s = client.score_details(client.upload(d, intrinsics=(intr.fx, intr.fy, intr.cx, intr.cy), up=up), g)
    assert s["windows"] == 2 and s["missing_fraction"] < 0.5
    holed = d.copy()
    holed[: int(intr.cy), :] = 0.0  # the top half of the image reads nothing: still a 422
    with pytest.raises(ServiceError, match="no depth reading|no valid depth pixel"):
        client.score(client.upload(holed, intrinsics=(intr.fx, intr.fy, intr.cx, intr.cy), up=up), g[:1])


def test_the_upload_reports_the_roll_and_tilt(client, heldout):
    d, _, intr = rolled(*heldout[0])
    client.upload(d, intrinsics=intr, up=5 * UP)
    level = client.last_upload["level"]
    assert level["roll_deg"] == pytest.approx(-90.0) and level["tilt_deg"] == pytest.approx(30.0, abs=0.01)
    assert level["up"] == pytest.approx((5 * UP).tolist()) and level["from"] == "client"
    client.upload(heldout[0][0])
    assert client.last_upload["level"] == {"up": None, "roll_deg": 0.0, "tilt_deg": None, "from": None}


def test_a_camera_tilted_beyond_the_training_cameras_flags_every_grasp(client, heldout):
    assert client.model()["camera"]["tilt_range_deg"] == pytest.approx([0.0, 70.0])
    depth, grasps = heldout[2]
    sideways = [0.0, -np.cos(np.radians(10)), -np.sin(np.radians(10))]  # tilted 80 deg from straight down
    r = client.score_details(client.upload(depth, up=sideways), grasps)
    assert all("camera_tilt_outside_training" in f for f in r["ood"])
    r = client.score_details(client.upload(depth, up=LEVEL_UP), grasps)
    assert not any("camera_tilt_outside_training" in f for f in r["ood"])


def test_a_one_shot_with_up_scores_as_the_upload_with_up(client, heldout):
    d, g, intr = rolled(*heldout[1], beta=np.radians(30))
    up = roll_matrix(np.radians(30)).T @ LEVEL_UP
    uploaded = client.score_details(client.upload(d, intrinsics=intr, up=up), g)["raw_score"]
    once = client.score_once(d, g, intrinsics=intr, up=up, details=True)["raw_score"]
    np.testing.assert_allclose(once, uploaded, atol=1e-6)
    b = io.BytesIO()
    np.save(b, d)
    fields = {k: repr(float(getattr(intr, k))) for k in ("fx", "fy", "cx", "cy")}
    fields.update({f"up_{a}": repr(float(x)) for a, x in zip("xyz", up)})
    r = httpx.post(
        f"{client.http.base_url}/v1/score",
        files={
            "depth": ("d.npy", b.getvalue(), "application/x-npy"),
            "grasps": ("g.json", json.dumps({"grasps": g.tolist()}), "application/json"),
        },
        data=fields,
    )
    assert r.status_code == 200, r.text
    np.testing.assert_allclose(r.json()["raw_score"], uploaded, atol=1e-6)  # multipart fields: the same


@pytest.mark.parametrize(
    ("params", "field"),
    [
        ({"up_x": "0.0"}, "up_y"),
        ({"up_x": "0", "up_y": "0", "up_z": "0"}, "up_x"),
        ({"up_x": "0", "up_y": "nan", "up_z": "-1"}, "up_y"),
    ],
)
def test_a_bad_up_answers_422_naming_it(url, heldout, params, field):
    b = io.BytesIO()
    np.save(b, heldout[0][0])
    r = httpx.post(
        f"{url}/v1/images",
        content=b.getvalue(),
        params=params,
        headers={"content-type": "application/x-npy"},
    )
    assert r.status_code == 422, r.text
    assert r.json()["error"]["details"]["field"] == field


def test_a_one_shot_up_of_two_values_answers_422(url, heldout):
    b = io.BytesIO()
    np.savez(b, depth=heldout[0][0], grasps=heldout[0][1].astype(np.float32), up=np.array([0.0, -1.0]))
    r = httpx.post(f"{url}/v1/score", content=b.getvalue(), headers={"content-type": "application/x-npz"})
    assert r.status_code == 422 and "up must hold 3 values" in r.text


def test_a_rolled_camera_with_its_up_plans_the_level_cameras_grasps_in_its_own_frame(client):
    pytest.importorskip("trimesh")
    from tests.planning_scenes import boxes_scene

    depth = boxes_scene(extents=((0.03, 0.04, 0.05), (0.035, 0.03, 0.04)), at=((-0.07, 0.0), (0.07, 0.02)))[0]
    level = client.plan(depth, k=3, seed=0)
    assert len(level.grasps) == 3
    d, _, intr = rolled(depth, np.zeros((0, 7)))
    turned = client.plan(d, k=3, seed=0, intrinsics=intr, up=UP)
    R = roll_matrix(BETA)
    np.testing.assert_allclose(turned.scores, level.scores, atol=1e-6)
    np.testing.assert_allclose(
        turned.poses,
        np.einsum("ij,njk->nik", np.block([[R.T, np.zeros((3, 1))], [np.zeros((1, 3)), 1]]), level.poses),
        atol=1e-6,
    )
    uv = map_pixels(level.rows[:, :2], DEFAULT_INTRINSICS, intr, BETA)
    np.testing.assert_allclose(turned.rows[:, :2], uv, atol=1e-6)
    box = np.array([[60.0, 90.0], [160.0, 230.0]])  # a region of interest: the left box
    corners = map_pixels(box, DEFAULT_INTRINSICS, intr, BETA)
    level_roi = client.plan(depth, k=2, seed=0, roi=box.ravel())
    turned_roi = client.plan(d, k=2, seed=0, intrinsics=intr, up=UP, roi=[*corners.min(0), *corners.max(0)])
    assert len(level_roi.grasps) == 2 and (level_roi.rows[:, 0] < 170).all()
    np.testing.assert_allclose(turned_roi.scores, level_roi.scores, atol=1e-6)
    cached = client.plan(k=3, seed=0, image_id=client.upload(d, intrinsics=intr, up=UP))
    np.testing.assert_allclose(cached.poses, turned.poses, atol=1e-9)
    image_id = client.upload(d, intrinsics=intr, up=UP)
    again = client.plan(k=3, seed=0, image_id=image_id, up=UP)  # repeating the upload's up
    np.testing.assert_allclose(again.poses, turned.poses, atol=1e-9)
    for other in (LEVEL_UP, None):  # another up, or one on an image uploaded without
        iid = image_id if other is not None else client.upload(d, intrinsics=intr)
        with pytest.raises(ServiceError) as e:
            client.plan(k=3, image_id=iid, up=UP if other is None else other)
        assert e.value.status == 422 and e.value.details["field"] == "up_x"


def test_a_plan_with_a_partial_up_answers_422_naming_it(url):
    b = io.BytesIO()
    np.save(b, np.full((300, 300), 0.7, np.float32))
    r = httpx.post(
        f"{url}/v1/plan",
        content=b.getvalue(),
        params={"up_z": "-1"},
        headers={"content-type": "application/x-npy"},
    )
    assert r.status_code == 422 and r.json()["error"]["details"]["field"] == "up_x"


# ---- level=table: the up direction read from the image's table plane ------------------------------
def test_level_table_reads_the_up_from_the_table_and_scores_as_the_level_camera(client, heldout):
    for depth, grasps in (heldout[0], heldout[3], heldout[5]):  # cameras 63, 18 and 20 deg off straight down
        level = client.score_details(client.upload(depth), grasps)["raw_score"]
        d, g, intr = rolled(depth, grasps)
        read = client.score_details(client.upload(d, intrinsics=intr, up="table"), g)["raw_score"]
        lv = client.last_upload["level"]
        assert lv["from"] == "table" and lv["roll_deg"] == pytest.approx(-90.0, abs=0.1)
        assert np.abs(read - level).mean() < 0.01
        assert client.last_upload["image_id"] != client.upload(d, intrinsics=intr)  # level is part of the id


def test_a_one_shot_and_a_plan_with_level_table_are_the_upload_with_the_up_it_read(client, heldout):
    d, g, intr = rolled(*heldout[0], beta=np.radians(30))
    uploaded = client.score_details(client.upload(d, intrinsics=intr, up="table"), g)["raw_score"]
    read = client.last_upload["level"]["up"]
    once = client.score_once(d, g, intrinsics=intr, up="table", details=True)["raw_score"]
    np.testing.assert_allclose(once, uploaded, atol=1e-6)
    plan = client.plan(d, k=2, seed=0, intrinsics=intr, up="table")
    given = client.plan(d, k=2, seed=0, intrinsics=intr, up=read)
    np.testing.assert_allclose(plan.poses, given.poses, atol=1e-9)
    assert plan.answer["level"]["from"] == "table" and given.answer["level"]["from"] == "client"


def test_a_plan_on_an_image_takes_level_table_only_from_its_upload(client, heldout):
    d, _, intr = rolled(*heldout[0])
    by_table = client.upload(d, intrinsics=intr, up="table")
    assert client.plan(k=1, seed=0, image_id=by_table, up="table").answer["level"]["from"] == "table"
    with pytest.raises(ServiceError) as e:
        client.plan(k=1, seed=0, image_id=client.upload(d, intrinsics=intr), up="table")
    assert e.value.status == 422 and e.value.details["field"] == "level"
    r = httpx.post(
        f"{client.http.base_url}/v1/images/{by_table}/plan",
        params={"level": "table", "up_x": "0", "up_y": "-1", "up_z": "0"},
    )
    assert r.status_code == 422 and r.json()["error"]["details"]["field"] == "level" and "not both" in r.text


@pytest.mark.parametrize(
    ("params", "depth", "says"),
    [
        ({"level": "table", "up_x": "0", "up_y": "-1", "up_z": "0"}, "heldout", "not both"),
        ({"level": "floor"}, "heldout", "must be 'table'"),
        ({"level": "table"}, "no table", "found no table"),
    ],
)
def test_a_bad_level_answers_422_naming_it(url, heldout, params, depth, says):
    if depth == "no table":  # depth readings scattered over 0.4-1.2 m: no plane holds 10% of them
        img = np.random.default_rng(0).uniform(0.4, 1.2, (300, 300)).astype(np.float32)
    else:
        img = heldout[0][0]
    b = io.BytesIO()
    np.save(b, img)
    for route in ("/v1/images", "/v1/plan"):
        r = httpx.post(
            f"{url}{route}", content=b.getvalue(), params=params, headers={"content-type": "application/x-npy"}
        )
        assert r.status_code == 422, (route, r.text)
        assert r.json()["error"]["details"]["field"] == "level" and says in r.text
