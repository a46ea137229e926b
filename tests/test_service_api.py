"""The real service over HTTP (uvicorn subprocess on loopback) against a real exported model."""

from __future__ import annotations

import io

import httpx
import numpy as np
import pytest
from PIL import Image
from servers import grasps_at, running_service

from service.client import ServiceClient, ServiceError

NPY = {"content-type": "application/x-npy"}


def npy(a) -> bytes:
    b = io.BytesIO()
    np.save(b, a)
    return b.getvalue()


@pytest.fixture(scope="module")
def url(model_dir):
    with running_service(model_dir, "--max-grasps", "512", "--max-body-bytes", "2000000") as u:
        yield u


@pytest.fixture(scope="module")
def client(url):
    with ServiceClient(url) as c:
        yield c


def test_upload_then_score_returns_one_probability_per_grasp(client, scene):
    iid = client.upload(scene)
    p = client.score(iid, grasps_at(k=128))
    assert p.shape == (128,) and np.all((p >= 0) & (p <= 1))


def test_scores_follow_grasp_order(client, scene):
    iid = client.upload(scene)
    g = grasps_at(k=16)
    p = client.score(iid, g)
    assert np.allclose(client.score(iid, g[::-1]), p[::-1], atol=1e-6)


def test_json_and_binary_scores_agree(url, client, scene):
    iid = client.upload(scene)
    g = grasps_at(k=8)
    r = httpx.post(f"{url}/v1/images/{iid}/scores", json={"grasps": g.tolist()})
    assert r.status_code == 200
    assert np.allclose(r.json()["p_success"], client.score(iid, g), atol=1e-6)


def test_grasp_objects_accepted_in_json(url, client, scene):
    iid = client.upload(scene)
    g = grasps_at(k=2)
    objs = [{"u": float(r[0]), "v": float(r[1]), "z": float(r[2]), "q": [float(x) for x in r[3:]]} for r in g]
    r = httpx.post(f"{url}/v1/images/{iid}/scores", json={"grasps": objs})
    assert np.allclose(r.json()["p_success"], client.score(iid, g), atol=1e-6)


def test_same_image_uploaded_again_is_a_cache_hit(url, scene):
    body = npy(scene + 0.001)
    first = httpx.post(f"{url}/v1/images", content=body, headers=NPY).json()
    second = httpx.post(f"{url}/v1/images", content=body, headers=NPY).json()
    assert first["cached"] is False and second["cached"] is True
    assert first["image_id"] == second["image_id"]


def test_different_window_centre_is_a_different_image(url, scene):
    body = npy(scene)
    a = httpx.post(f"{url}/v1/images", content=body, headers=NPY).json()
    b = httpx.post(f"{url}/v1/images", content=body, headers=NPY, params={"center_u": 140, "center_v": 150}).json()
    assert a["image_id"] != b["image_id"]
    assert b["window_center"] == [140.5, 150.5]  # nearest pixel-aligned window (ties round up)


def test_sign_of_quaternion_does_not_change_the_score(client, scene):
    iid = client.upload(scene)
    g = grasps_at(k=8)
    flipped = g.copy()
    flipped[:, 3:] *= -1
    assert np.allclose(client.score(iid, g), client.score(iid, flipped), atol=1e-6)


def test_non_unit_quaternion_is_normalised(client, scene):
    iid = client.upload(scene)
    g = grasps_at(k=8)
    scaled = g.copy()
    scaled[:, 3:] *= 3.0
    assert np.allclose(client.score(iid, g), client.score(iid, scaled), atol=1e-6)


def test_png_millimetres_upload_scores_like_npy(url, client, scene):
    mm = np.round(scene * 1000).astype(np.uint16)
    b = io.BytesIO()
    Image.fromarray(mm).save(b, format="PNG")
    r = httpx.post(f"{url}/v1/images", content=b.getvalue(), headers={"content-type": "image/png"})
    assert r.status_code == 200
    g = grasps_at(k=8)
    assert np.allclose(client.score(r.json()["image_id"], g), client.score(client.upload(mm / 1000.0), g), atol=1e-5)


def test_raw_float32_upload_needs_and_uses_shape(url, client, scene):
    raw = scene.astype("<f4").tobytes()
    r = httpx.post(
        f"{url}/v1/images",
        content=raw,
        headers={"content-type": "application/octet-stream"},
        params={"width": 300, "height": 300},
    )
    assert r.status_code == 200
    g = grasps_at(k=4)
    assert np.allclose(client.score(r.json()["image_id"], g), client.score(client.upload(scene), g), atol=1e-6)


def test_one_shot_npz_matches_upload_then_score(client, scene):
    g = grasps_at(k=32)
    assert np.allclose(client.score_once(scene + 0.002, g), client.score(client.upload(scene + 0.002), g), atol=1e-6)


def test_one_shot_multipart_fills_the_cache(url, client, scene):
    d = scene + 0.003
    g = grasps_at(k=4)
    r = httpx.post(
        f"{url}/v1/score",
        files={"depth": ("d.npy", npy(d), "application/x-npy")},
        data={"grasps": f'{{"grasps": {g.tolist()}}}'},
    )
    assert r.status_code == 200 and r.json()["cached"] is False
    up = httpx.post(f"{url}/v1/images", content=npy(d), headers=NPY).json()
    assert up["cached"] is True and up["image_id"] == r.json()["image_id"]


def test_unknown_image_id_is_404_asking_for_upload(client):
    with pytest.raises(ServiceError) as e:
        client.score("0" * 32, grasps_at(k=1))
    assert e.value.status == 404 and "upload" in e.value.message


def test_grasp_outside_a_fixed_window_is_422_naming_it(client, scene):
    iid = client.upload(scene, center=(149.5, 149.5))
    g = grasps_at(k=5)
    g[3, 0] = 10.0
    with pytest.raises(ServiceError) as e:
        client.score(iid, g)
    assert e.value.status == 422 and e.value.details["grasps"] == [3]


def test_non_finite_grasp_is_422_naming_it(client, scene):
    iid = client.upload(scene)
    g = grasps_at(k=5)
    g[1, 2] = np.nan
    with pytest.raises(ServiceError) as e:
        client.score(iid, g)
    assert e.value.status == 422 and e.value.details["grasps"] == [1]


def test_zero_quaternion_is_422(client, scene):
    iid = client.upload(scene)
    g = grasps_at(k=3)
    g[2, 3:] = 0
    with pytest.raises(ServiceError) as e:
        client.score(iid, g)
    assert e.value.status == 422 and e.value.details["grasps"] == [2]


def test_too_many_grasps_is_422(client, scene):
    iid = client.upload(scene)
    with pytest.raises(ServiceError) as e:
        client.score(iid, grasps_at(k=513))
    assert e.value.status == 422 and "at most 512" in e.value.message


def test_zero_grasps_is_422(url, client, scene):
    iid = client.upload(scene)
    r = httpx.post(f"{url}/v1/images/{iid}/scores", json={"grasps": []})
    assert r.status_code == 422 and "k = 0" in r.json()["error"]["message"]


def test_malformed_json_is_400(url, client, scene):
    iid = client.upload(scene)
    r = httpx.post(f"{url}/v1/images/{iid}/scores", content=b"{not json", headers={"content-type": "application/json"})
    assert r.status_code == 400


def test_nan_depth_is_422(url, scene):
    d = scene.copy()
    d[5, 5] = np.nan
    r = httpx.post(f"{url}/v1/images", content=npy(d), headers=NPY)
    assert r.status_code == 422 and "non-finite" in r.json()["error"]["message"]


def test_body_over_limit_is_413(url):
    r = httpx.post(f"{url}/v1/images", content=npy(np.ones((800, 800), np.float32)), headers=NPY)
    assert r.status_code == 413


def test_wrong_content_type_is_415(url, scene):
    r = httpx.post(f"{url}/v1/images", content=npy(scene), headers={"content-type": "text/plain"})
    assert r.status_code == 415


def test_focal_length_outside_the_served_range_is_422(url, scene):
    r = httpx.post(f"{url}/v1/images", content=npy(scene), headers=NPY, params={"fx": 1200})
    assert r.status_code == 422 and "fx" in r.json()["error"]["message"]
    assert httpx.post(f"{url}/v1/images", content=npy(scene), headers=NPY, params={"fx": 600}).status_code == 200


def test_health_ready_model_and_metrics(url, client, scene):
    assert httpx.get(f"{url}/healthz").status_code == 200
    assert httpx.get(f"{url}/readyz").json()["status"] == "ready"
    card = client.model()["model_card"]
    assert card["architecture"] == "fast_vgqcnn" and card["geometry"]["window"] == 96
    client.score(client.upload(scene), grasps_at(k=4))
    text = httpx.get(f"{url}/metrics").text
    for name in (
        "vgq_request_seconds_bucket",
        "vgq_encoder_seconds",
        "vgq_head_seconds",
        "vgq_grasps_per_request",
        "vgq_cache_hits_total",
        "vgq_cache_evictions_total",
        'vgq_requests_total{endpoint="score",status="200"}',
    ):
        assert name in text, name


def test_openapi_documents_the_endpoints(url):
    spec = httpx.get(f"{url}/openapi.json").json()
    assert {"/v1/images", "/v1/images/{image_id}/scores", "/v1/score"} <= set(spec["paths"])
    assert "application/x-npy" in spec["paths"]["/v1/images"]["post"]["requestBody"]["content"]


def test_lru_eviction_then_404_and_reupload(model_dir, scene):
    with running_service(model_dir, "--cache-entries", "2") as u, ServiceClient(u) as c:
        ids = [c.upload(scene + 0.001 * i) for i in range(3)]
        with pytest.raises(ServiceError) as e:
            c.score(ids[0], grasps_at(k=1))
        assert e.value.status == 404
        assert len(c.score(ids[2], grasps_at(k=1))) == 1
        stats = httpx.get(f"{u}/v1/cache").json()
        assert stats["evictions"] == 1 and stats["entries"] == 2
        assert c.upload(scene) == ids[0]  # re-upload restores the same id


def test_api_key_required_when_configured(model_dir, scene):
    with running_service(model_dir, env={"VGQ_API_KEY": "s3cret"}) as u:
        with ServiceClient(u) as anon, pytest.raises(ServiceError) as e:
            anon.upload(scene)
        assert e.value.status == 401
        with ServiceClient(u, api_key="s3cret") as c:
            assert len(c.score(c.upload(scene), grasps_at(k=2))) == 2
