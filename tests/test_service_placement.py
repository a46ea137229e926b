"""A model whose head reads placement rows (vgq.placement) served: each grasp's row is the one
datagen computes (planning.placement on the image as uploaded, with the upload's own camera, from
the grasp as sent), appended after its pose columns on every route that runs the head; models
without placement run no analysis and answer as before."""

from __future__ import annotations

import io
import warnings

import numpy as np
import pytest
from conftest import table_scene

with warnings.catch_warnings():  # starlette now asks for the httpx2 package; httpx still does the job here
    warnings.filterwarnings("ignore", message="Using `httpx` with `starlette.testclient`")
    from starlette.testclient import TestClient

from planning.placement import ImagePlacement
from service.app import create_app
from service.cache import CachedImage
from service.config import Settings
from service.preprocess import window_input
from service.redis_cache import pack_entry, unpack_entry
from service.runtime import FastModel
from vgq.camera import DEFAULT_INTRINSICS, Intrinsics
from vgq.crop import CropGeometry
from vgq.placement import PLACEMENT_COLUMNS

NPY, OCTET, NPZ = "application/x-npy", "application/octet-stream", "application/x-npz"
CAMERA = Intrinsics(600.0, 600.0, 160.0, 140.0, 300, 300)  # not the model's: the upload is resampled


def _npy(a) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.asarray(a, np.float32))
    return buf.getvalue()


def _npz(**arrays) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def _query(intr: Intrinsics, **more) -> dict:
    return {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy, **more}


def box_scene(height: float = 0.08) -> np.ndarray:
    """A table 0.7 m away with a box (rows 120-180, columns 130-170) ``height`` tall."""
    return table_scene(box_height=height)


def grasps(depth: np.ndarray, seed: int = 0) -> np.ndarray:
    """(12, 7): 8 grasps on the box top (approach down, turned about it), 4 on the table far from it."""
    rng = np.random.default_rng(seed)
    uv = np.r_[np.c_[rng.uniform(133, 167, 8), rng.uniform(123, 177, 8)], [[30, 30], [270, 40], [40, 260], [260, 270]]]
    z = depth[np.rint(uv[:, 1]).astype(int), np.rint(uv[:, 0]).astype(int)]
    a = rng.uniform(0, np.pi, len(uv))
    q = np.c_[np.cos(a / 2), np.zeros((len(uv), 2)), np.sin(a / 2)]  # about the camera's z: approach down
    return np.c_[uv, z, q]


@pytest.fixture(scope="module")
def placement_net():
    """A tiny placement network (random weights; the placement columns made to matter)."""
    torch = pytest.importorskip("torch")
    from training.networks import GraspQualityNet

    torch.manual_seed(0)
    net = GraspQualityNet("fast_vgqcnn", placement=True).eval()
    with torch.no_grad():
        net.pc1.weight[:, -7:] = 3.0 * torch.randn(net.pc1.weight.shape[0], 7)
        net.fc4_pose.weight.mul_(2.0)  # not so strong that the probabilities saturate
    return net


def _export(net, out, geom: CropGeometry):
    from export.onnx_export import export_model

    rng = np.random.default_rng(0)
    imgs = (0.6 + 0.01 * rng.standard_normal((16, 32, 32))).astype(np.float32)
    poses = np.c_[rng.uniform(-10, 10, (16, 2)), rng.uniform(0.5, 0.8, 16), np.tile([1.0, 0, 0, 0], (16, 1))]
    place = np.c_[
        np.ones(16), rng.uniform(0, 0.08, (16, 3)), rng.uniform(-0.05, 0.05, 16), rng.uniform(0, 0.1, (16, 2))
    ]
    export_model(net, out, imgs, np.c_[poses, place].astype(np.float32), geom, DEFAULT_INTRINSICS)
    return out


@pytest.fixture(scope="module")
def placement_dir(tmp_path_factory, placement_net):
    return _export(placement_net, tmp_path_factory.mktemp("placement") / "m", CropGeometry(96, 32, 36.0))


def _client(model_dir, **settings) -> TestClient:
    s = Settings(model_dir=str(model_dir), threads=1, log_level="warning", **settings)
    return TestClient(create_app(s, load_in_background=False))


@pytest.fixture(scope="module")
def client(placement_dir):
    with _client(placement_dir) as c:
        yield c


@pytest.fixture(scope="module")
def reference(placement_dir):
    """The model outside the service (its own onnxruntime sessions)."""
    return FastModel(placement_dir, threads=1, head_precision="fp32", encoder_precision="fp32")


def _upload(client, depth, intr: Intrinsics = CAMERA, **more) -> dict:
    r = client.post("/v1/images", params=_query(intr, **more), content=_npy(depth), headers={"content-type": NPY})
    assert r.status_code == 200, r.text
    return r.json()


def _score(client, image_id: str, g: np.ndarray) -> dict:
    r = client.post(f"/v1/images/{image_id}/scores", json={"grasps": g.tolist()})
    assert r.status_code == 200, r.text
    return r.json()


def _expected(client, model: FastModel, image_id: str, g: np.ndarray, place: np.ndarray) -> np.ndarray:
    """Raw scores of ``model`` on the service's own crops and pose rows of ``g``, each pose row followed
    by ``place``."""
    svc = client.app.state.service
    entry = svc.cache.get(image_id)
    rows, origins, _ = svc.place(entry, g)
    out = np.empty(len(g), np.float32)
    for o in np.unique(origins, axis=0):
        ix = np.flatnonzero((origins == o).all(axis=1))
        crop = window_input(entry.depth, o, model.geometry, 1.0, entry.outside()).image
        out[ix] = model.score(model.encode(crop), np.c_[rows[ix], place[ix]].astype(np.float32))
    return out


def test_the_model_card_reads_placement_columns(placement_dir):
    card = FastModel(placement_dir, threads=1).card
    assert card.placement_columns == PLACEMENT_COLUMNS and card.head_pose_width == 14


def test_served_scores_read_the_rows_datagen_computes(client, reference):
    depth = box_scene()
    g = grasps(depth)
    up = _upload(client, depth)
    got = _score(client, up["image_id"], g)
    place = ImagePlacement.analyse(depth, CAMERA).rows(g[:, :3], g[:, 3:7])
    assert place[:8, 0].all() and not place[8:, 0].any()  # on the box: known; far out on the table: not
    np.testing.assert_allclose(got["raw_score"], _expected(client, reference, up["image_id"], g, place), atol=1e-5)
    assert up["placement"] == {"table_found": True, "objects": 1}
    assert got["placement"] == {"table_found": True, "known": (place[:, 0] > 0).tolist()}


def test_the_placement_rows_change_the_served_scores(client, reference):
    depth = box_scene()
    g = grasps(depth, seed=1)
    image_id = _upload(client, depth)["image_id"]
    got = np.array(_score(client, image_id, g)["raw_score"])
    unknown = _expected(client, reference, image_id, g, np.zeros((len(g), 7), np.float32))
    assert np.abs(got - unknown)[:8].max() > 1e-3


def test_the_one_shot_route_scores_as_upload_then_score(client):
    depth = box_scene(0.06)
    g = grasps(depth, seed=3)
    body = _npz(depth=depth, grasps=g, intrinsics=np.array([CAMERA.fx, CAMERA.fy, CAMERA.cx, CAMERA.cy]))
    once = client.post("/v1/score", content=body, headers={"content-type": NPZ})
    assert once.status_code == 200, once.text
    two = _score(client, _upload(client, depth)["image_id"], g)
    assert once.json()["raw_score"] == two["raw_score"] and once.json()["placement"] == two["placement"]
    binary = client.post(
        f"/v1/images/{once.json()['image_id']}/scores",
        content=np.ascontiguousarray(g, "<f4").tobytes(),
        headers={"content-type": OCTET, "accept": OCTET},
    )
    assert binary.headers["x-placement-known"] == str(sum(two["placement"]["known"]))


def test_a_one_shot_encodes_its_windows_while_its_image_is_analysed(client, monkeypatch):
    """The one-shot route analyses the upload in a helper thread while its own thread encodes the
    batch's windows (onnxruntime lets go of the GIL): the encoder starts before the analysis ends,
    the answer still counts the windows it encoded, and the scores are the sequential ones."""
    import threading
    import time

    from service import placement as service_placement

    events, analyse, svc = [], service_placement.analyse, client.app.state.service
    encode = svc.model.encode

    def slow_analysis(depth, camera):
        events.append(("analysis", threading.current_thread().name))
        time.sleep(0.2)
        out = analyse(depth, camera)
        events.append(("analysed", threading.current_thread().name))
        return out

    def encoder(crops):
        events.append(("encode", threading.current_thread().name))
        return encode(crops)

    monkeypatch.setattr(service_placement, "analyse", slow_analysis)
    monkeypatch.setattr(svc.model, "encode", encoder)
    depth = box_scene(0.05)
    g = grasps(depth, seed=5)
    camera = np.array([CAMERA.fx, CAMERA.fy, CAMERA.cx, CAMERA.cy])
    once = client.post(
        "/v1/score", content=_npz(depth=depth, grasps=g, intrinsics=camera), headers={"content-type": NPZ}
    )
    assert once.status_code == 200, once.text
    names = [e[0] for e in events]
    assert names.index("encode") < names.index("analysed")  # the encoder ran while the analysis went on
    helper = events[names.index("analysis")][1]
    assert helper.startswith("vgq-placement") and events[names.index("encode")][1] != helper
    assert once.json()["windows_encoded"] == once.json()["windows"] >= 1
    events.clear()
    strict = client.post(
        "/v1/score?strict=true", content=_npz(depth=depth + 0.01, grasps=g), headers={"content-type": NPZ}
    )
    assert strict.status_code == 200 and [e[0] for e in events][:2] == ["analysis", "analysed"]  # strict: in turn
    two = _score(client, _upload(client, depth)["image_id"], g)
    assert once.json()["raw_score"] == two["raw_score"]


def test_a_turned_upload_reads_the_rows_of_the_image_as_sent(client, reference):
    depth = box_scene()
    g = grasps(depth, seed=4)
    up = _upload(client, depth, up_x=0.6, up_y=0.0, up_z=-0.8)  # rolled a quarter turn: the image is turned
    assert abs(up["level"]["roll_deg"]) > 1
    got = _score(client, up["image_id"], g)
    place = ImagePlacement.analyse(depth, CAMERA).rows(g[:, :3], g[:, 3:7])
    np.testing.assert_allclose(got["raw_score"], _expected(client, reference, up["image_id"], g, place), atol=1e-5)


def test_an_image_without_a_table_scores_with_unknown_placement(client, reference):
    v, u = np.mgrid[:300, :300]
    bowl = (0.6 + 1e-5 * ((u - 150.0) ** 2 + (v - 150.0) ** 2)).astype(np.float32)  # no plane in it
    g = grasps(bowl, seed=5)
    up = _upload(client, bowl)
    got = _score(client, up["image_id"], g)
    assert up["placement"] == {"table_found": False, "objects": 0}
    assert got["placement"] == {"table_found": False, "known": [False] * len(g)}
    unknown = _expected(client, reference, up["image_id"], g, np.zeros((len(g), 7), np.float32))
    np.testing.assert_allclose(got["raw_score"], unknown, atol=1e-5)


def test_a_placement_model_plans_with_each_candidates_placement_row(client, monkeypatch):
    depth = box_scene()
    r = client.post("/v1/plan", params={"k": 3}, content=_npy(depth), headers={"content-type": NPY})
    assert r.status_code == 200, r.text
    assert r.json()["grasps"] and "placement" not in r.json()
    image_id = _upload(client, depth, DEFAULT_INTRINSICS)["image_id"]
    cached = client.post(f"/v1/images/{image_id}/plan", params={"k": 3})
    assert cached.status_code == 200, cached.text
    assert [x["row"] for x in cached.json()["grasps"]] == [x["row"] for x in r.json()["grasps"]]
    monkeypatch.setattr(ImagePlacement, "rows", lambda self, uvz, q: np.zeros((len(uvz), 7), np.float32))
    blind = client.post("/v1/plan", params={"k": 3}, content=_npy(depth), headers={"content-type": NPY})
    assert [x["score"] for x in blind.json()["grasps"]] != [x["score"] for x in r.json()["grasps"]]


def test_the_redis_entry_keeps_the_placement_analysis():
    from service.placement import analyse

    depth = box_scene()
    entry = CachedImage(depth, CAMERA, CAMERA, placement=analyse(depth, CAMERA))
    back = unpack_entry(pack_entry(entry))
    g = grasps(depth)
    assert np.array_equal(back.placement.rows(g[:, :3], g[:, 3:7]), entry.placement.rows(g[:, :3], g[:, 3:7]))
    assert unpack_entry(pack_entry(CachedImage(depth, CAMERA, CAMERA))).placement is None


def test_a_model_without_placement_runs_no_analysis_and_answers_as_before(monkeypatch, model_dir):
    def refuse(*args, **kwargs):
        raise AssertionError("a model without placement analysed an image")

    monkeypatch.setattr(ImagePlacement, "analyse", refuse)
    depth = box_scene()
    g = grasps(depth)
    with _client(model_dir) as c:
        up = _upload(c, depth)
        scored = _score(c, up["image_id"], g)
        once = c.post("/v1/score", content=_npz(depth=depth, grasps=g), headers={"content-type": NPZ})
        binary = c.post(
            f"/v1/images/{up['image_id']}/scores",
            content=np.ascontiguousarray(g, "<f4").tobytes(),
            headers={"content-type": OCTET, "accept": OCTET},
        )
        plan = c.post("/v1/plan", params={"k": 2}, content=_npy(depth), headers={"content-type": NPY})
    assert once.status_code == binary.status_code == plan.status_code == 200
    assert not any("placement" in a for a in (up, scored, once.json(), plan.json()))
    assert "x-placement-known" not in binary.headers


def _grid_crops(depth, uv, jaw, arch, geom, rng):
    """datagen.crops.crop_grasps with each window on the service's grid instead of a random offset."""
    from vgq import inpaint
    from vgq.crop import grid_window_centers, pose_uv, window_origin

    origins = window_origin(grid_window_centers(uv, depth.shape, geom), geom)
    out = [inpaint.crop_filled(depth, o, geom) for o in origins]
    return (
        np.stack([o[0] for o in out]),
        pose_uv(uv, np.stack([o[1] for o in out]), geom),
        np.array([o[2] for o in out]),
    )


def test_a_model_of_turned_windows_scores_what_datagen_cut_for_training(placement_net, tmp_path, monkeypatch):
    import datagen.crops as crops_mod
    from vgq.pose import canonical_quaternion
    from vgq.turns import pose_jaw_angles, turn_index

    geom = CropGeometry(96, 32, 36.0, jaw_turns=4)
    model_dir = _export(placement_net, tmp_path / "turned", geom)
    depth = box_scene()
    rng = np.random.default_rng(6)
    uv = np.c_[rng.uniform(128, 172, 24), rng.uniform(118, 182, 24)]  # on the box and just beside it
    z = depth[np.rint(uv[:, 1]).astype(int), np.rint(uv[:, 0]).astype(int)].astype(np.float64)
    q = canonical_quaternion(rng.standard_normal((24, 4)))
    assert len(set(turn_index(pose_jaw_angles(uv, z, q, DEFAULT_INTRINSICS), 4).tolist())) == 4  # every turn
    # datagen's crop stage, on the service's grid: the turned crops and pose rows, then the placement rows
    monkeypatch.setattr(crops_mod, "crop_grasps", _grid_crops)
    images, puv, _, q_turned = crops_mod.turned_crops(depth, uv, z, q, geom, DEFAULT_INTRINSICS, None)
    place = ImagePlacement.analyse(depth, DEFAULT_INTRINSICS).rows(np.c_[uv, z], q)
    poses = np.c_[puv, z, q_turned, place].astype(np.float32)
    model = FastModel(model_dir, threads=1)
    expected = [model.score(model.encode(images[i : i + 1, None]), poses[i : i + 1])[0] for i in range(len(z))]
    with _client(model_dir) as c:
        got = _score(c, _upload(c, depth, DEFAULT_INTRINSICS)["image_id"], np.c_[uv, z, q])
    assert place[:, 0].all()
    np.testing.assert_allclose(got["raw_score"], expected, atol=1e-5)
