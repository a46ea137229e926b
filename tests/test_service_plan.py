"""POST /v1/plan on the real service (uvicorn subprocess, the bundled model) with scenes
rendered by datagen: k distinct grasps whose rows are their poses, in every upload format;
bad input answers 422 naming it; nothing to grasp answers 200 with a reason; the client's
plan(); an uploaded image planned by its id answers as its depth planned directly."""

from __future__ import annotations

import io

import httpx
import numpy as np
import pytest
from PIL import Image

pytest.importorskip("trimesh")
pytest.importorskip("scipy")

from servers import ROOT, running_service

from planning.policy import frame_from_row
from service.client import ServiceClient, ServiceError
from tests.planning_scenes import boxes_scene
from vgq.camera import DEFAULT_INTRINSICS, Intrinsics, project

MODEL_DIR = ROOT / "models" / "fast-vgqcnn-default"


def npy(a) -> bytes:
    b = io.BytesIO()
    np.save(b, np.asarray(a, np.float32), allow_pickle=False)
    return b.getvalue()


def png_mm(a) -> bytes:
    b = io.BytesIO()
    Image.fromarray(np.round(np.asarray(a) * 1000).astype(np.uint16)).save(b, format="PNG")
    return b.getvalue()


@pytest.fixture(scope="module")
def url():
    with running_service(MODEL_DIR, "--threads", "1") as u:
        yield u


@pytest.fixture(scope="module")
def two_boxes():
    return boxes_scene(extents=((0.03, 0.04, 0.05), (0.035, 0.03, 0.04)), at=((-0.07, 0.0), (0.07, 0.02)))


@pytest.fixture(scope="module")
def table_only():
    from datagen.camera import look_at_table_origin
    from datagen.render import render_depth

    return render_depth(None, look_at_table_origin(0.6, 0.3, 0.2)[0], DEFAULT_INTRINSICS)


def post_plan(url, depth, params=None, body=None, content_type="application/x-npy") -> httpx.Response:
    return httpx.post(
        f"{url}/v1/plan",
        content=npy(depth) if body is None else body,
        params=params or {},
        headers={"content-type": content_type},
        timeout=60,
    )


def test_plan_returns_k_distinct_grasps_whose_rows_are_their_poses(url, two_boxes):
    depth = two_boxes[0]
    r = post_plan(url, depth, {"k": 5, "seed": 0})
    assert r.status_code == 200, r.text
    d = r.json()
    assert d["reason"] is None and len(d["grasps"]) == 5 and d["k"] == 5 and d["seed"] == 0
    assert d["intrinsics"] == DEFAULT_INTRINSICS.to_dict()  # the model's camera by default
    intr = Intrinsics.from_dict(d["intrinsics"])
    assert d["ranked_by"] == "ranker"  # the bundled model's planner ranker (planning.ranker) ordered them
    assert all(0 <= g["score"] <= 1 for g in d["grasps"])
    poses = np.array([g["pose"] for g in d["grasps"]])
    for g, pose in zip(d["grasps"], poses):
        row = np.array(g["row"])
        assert row.tolist() == [g["u"], g["v"], g["z"], *g["q"]]
        assert np.allclose(frame_from_row(row, intr), pose, atol=1e-6)  # row -> pose
        assert np.allclose(project(pose[None, :3, 3], intr)[0], row[:3], atol=1e-6)  # pose -> row
        contacts = np.array(g["contacts"])
        assert np.allclose(pose[:3, 3], contacts.mean(axis=0), atol=1e-6)
        assert np.isclose(g["width"], np.linalg.norm(contacts[1] - contacts[0]), atol=1e-6)
        assert g["ood_flags"] == 0 and g["ood"] == []
    # distinct: no two share both their centre (1 cm) and their jaw axis (30 degrees)
    for i in range(5):
        for j in range(i):
            near = np.linalg.norm(poses[i, :3, 3] - poses[j, :3, 3]) < 0.01
            parallel = abs(poses[i, :3, 0] @ poses[j, :3, 0]) > np.cos(np.radians(30))
            assert not (near and parallel)
    assert set(d["seconds"]) >= {"scene", "sample", "score", "total"}


@pytest.mark.parametrize("fmt", ["png", "raw"])
def test_every_upload_format_is_planned(url, two_boxes, fmt):
    depth = two_boxes[0]
    if fmt == "png":
        r = post_plan(url, depth, {"k": 3}, png_mm(depth), "image/png")
    else:
        h, w = depth.shape
        r = post_plan(
            url, depth, {"k": 3, "width": w, "height": h}, depth.astype("<f4").tobytes(), "application/octet-stream"
        )
    assert r.status_code == 200, r.text
    assert len(r.json()["grasps"]) == 3


def test_the_same_seed_plans_the_same_grasps(url, two_boxes):
    a, b = (post_plan(url, two_boxes[0], {"k": 3, "seed": 11}).json() for _ in range(2))
    assert [g["row"] for g in a["grasps"]] == [g["row"] for g in b["grasps"]]


def test_roi_and_camera_reach_the_planner(url, two_boxes):
    depth, T_wc, meshes = two_boxes
    T_cw = np.linalg.inv(T_wc)
    uv = project(meshes[1].vertices @ T_cw[:3, :3].T + T_cw[:3, 3], DEFAULT_INTRINSICS)[:, :2]
    (u0, v0), (u1, v1) = uv.min(axis=0) - 3, uv.max(axis=0) + 3
    intr = {"fx": 525.0, "fy": 525.0, "cx": 149.5, "cy": 149.5}
    r = post_plan(url, depth, {"k": 4, "roi": f"{u0},{v0},{u1},{v1}", **intr})
    assert r.status_code == 200, r.text
    grasps = r.json()["grasps"]
    assert grasps
    for g in grasps:
        c0 = project(np.array(g["contacts"][:1]), DEFAULT_INTRINSICS)[0]
        assert u0 <= c0[0] <= u1 and v0 <= c0[1] <= v1


@pytest.mark.parametrize(
    "params, field",
    [
        ({"roi": "400,400,500,500"}, "roi"),  # outside the image: empty
        ({"roi": "50,50,10,10"}, "roi"),  # u1 < u0
        ({"roi": "1,2,3"}, "roi"),
        ({"roi": "1,2,nan,4"}, "roi"),
        ({"roi": "1,2,,4"}, "roi"),  # an empty part
        ({"roi": "1,-2,3,4"}, "roi"),
        ({"k": 0}, "k"),
        ({"k": 101}, "k"),
        ({"k": 2.5}, "k"),
        ({"k": "true"}, "k"),
        ({"fx": "nan"}, "fx"),
        ({"fx": "-525"}, "fx"),
        ({"fy": "1e999"}, "fy"),
        ({"fx": 2000}, "intrinsics"),  # a focal length the model cannot be resampled to
        ({"seed": -1}, "seed"),
        ({"cem": 11}, "cem"),
    ],
)
def test_bad_parameters_answer_422_naming_them(url, two_boxes, params, field):
    r = post_plan(url, two_boxes[0], params)
    assert r.status_code == 422, r.text
    assert field in r.json()["error"]["message"]


def test_an_image_without_valid_depth_answers_422_naming_the_depth(url):
    r = post_plan(url, np.zeros((300, 300), np.float32))
    assert r.status_code == 422 and "depth" in r.json()["error"]["message"]


def test_a_bare_table_answers_200_with_no_grasps_and_a_reason(url, table_only):
    r = post_plan(url, table_only, {"k": 5})
    assert r.status_code == 200, r.text
    d = r.json()
    assert d["grasps"] == [] and "no object" in d["reason"]


def test_plans_are_counted_in_the_metrics(url, two_boxes, table_only):
    post_plan(url, two_boxes[0], {"k": 1})
    post_plan(url, table_only, {"k": 1})
    text = httpx.get(f"{url}/metrics").text
    assert 'vgq_plans_total{outcome="grasps"}' in text and 'vgq_plans_total{outcome="none"}' in text
    assert 'vgq_requests_total{endpoint="plan",status="200"}' in text and "vgq_plan_seconds_count" in text


def test_client_plan(url, two_boxes, table_only):
    depth = two_boxes[0]
    with ServiceClient(url, timeout=60) as c:
        plan = c.plan(depth, k=3, intrinsics=DEFAULT_INTRINSICS, seed=11)
        assert len(plan.grasps) == 3 and plan.reason is None
        assert plan.rows.shape == (3, 7) and plan.poses.shape == (3, 4, 4)
        assert plan.ranked_by == "ranker" and np.all((plan.scores >= 0) & (plan.scores <= 1))
        # the same grasps as the HTTP answer for the same image and seed
        assert plan.rows.tolist() == [g["row"] for g in post_plan(url, depth, {"k": 3, "seed": 11}).json()["grasps"]]
        empty = c.plan(table_only)
        assert empty.grasps == [] and empty.reason and empty.rows.shape == (0, 7)
        with pytest.raises(ServiceError) as e:
            c.plan(depth, k=0)
        assert e.value.status == 422 and "k" in e.value.message


# ---- planning on an uploaded image (POST /v1/images/{image_id}/plan, or a JSON body on /v1/plan)


def upload(url, depth, intr: dict | None = None) -> str:
    r = httpx.post(
        f"{url}/v1/images", content=npy(depth), params=intr or {}, headers={"content-type": "application/x-npy"}
    )
    assert r.status_code == 200, r.text
    return r.json()["image_id"]


def plan_id(url, image_id, params=None, **kw) -> httpx.Response:
    return httpx.post(f"{url}/v1/images/{image_id}/plan", params=params or {}, timeout=60, **kw)


def same_plan(a: dict, b: dict) -> None:
    assert a["reason"] == b["reason"] and a["intrinsics"] == b["intrinsics"]
    assert a["grasps"] == b["grasps"]  # every row, pose, contact, width, score and flag, bit for bit
    assert {k: v for k, v in a["counts"].items() if k != "windows_reused"} == {
        k: v for k, v in b["counts"].items() if k != "windows_reused"
    }


# the model's camera (nothing sent at upload: all assumed), and a 600 px one the image is resampled from
CAMERAS = [None, {"fx": 600.0, "fy": 610.0, "cx": 151.0, "cy": 148.0}]


@pytest.mark.parametrize("intr", CAMERAS, ids=["model_camera", "resampled"])
def test_planning_an_uploaded_image_equals_planning_its_depth(url, two_boxes, intr):
    depth = two_boxes[0]
    params = {"k": 4, "seed": 7, "roi": "60,60,260,240"}
    direct = post_plan(url, depth, {**params, **(intr or {})})
    assert direct.status_code == 200, direct.text
    image_id = upload(url, depth, intr)
    first = plan_id(url, image_id, params)
    assert first.status_code == 200, first.text
    a = first.json()
    same_plan(a, direct.json())
    assert a["image_id"] == image_id and len(a["grasps"]) == 4
    assert a["intrinsics_assumed"] == ([] if intr else ["fx", "fy", "cx", "cy"])
    assert a["counts"]["windows_reused"] == 0  # nothing was encoded for this image before
    # again, by the JSON body of /v1/plan: the windows the first plan encoded are reused
    again = httpx.post(f"{url}/v1/plan", params=params, json={"image_id": image_id}, timeout=60)
    assert again.status_code == 200, again.text
    b = again.json()
    same_plan(b, direct.json())
    assert b["counts"]["windows_reused"] == b["counts"]["windows"] >= 1
    # the camera may be repeated in the query
    if intr:
        assert plan_id(url, image_id, {**params, **intr}).json()["grasps"] == a["grasps"]


def test_windows_a_plan_encodes_are_cached_with_the_image(url, two_boxes):
    image_id = upload(url, two_boxes[0] + 0.001)
    before = httpx.get(f"{url}/v1/cache").json()["windows"]
    d = plan_id(url, image_id, {"k": 2}).json()
    assert httpx.get(f"{url}/v1/cache").json()["windows"] == before + d["counts"]["windows"]


def test_an_image_uploaded_with_a_fixed_window_is_planned_and_keeps_only_that_window(url, two_boxes):
    depth = two_boxes[0] + 0.002
    up = httpx.post(
        f"{url}/v1/images",
        content=npy(depth),
        params={"center_u": 150, "center_v": 150},
        headers={"content-type": "application/x-npy"},
    ).json()
    before = httpx.get(f"{url}/v1/cache").json()["windows"]
    d = plan_id(url, up["image_id"], {"k": 2, "seed": 1}).json()
    assert d["grasps"] == post_plan(url, depth, {"k": 2, "seed": 1}).json()["grasps"]
    assert httpx.get(f"{url}/v1/cache").json()["windows"] == before  # the upload's one window, no more
    again = httpx.post(
        f"{url}/v1/images",
        content=npy(depth),
        params={"center_u": 150, "center_v": 150},
        headers={"content-type": "application/x-npy"},
    ).json()
    assert again["cached"] and again["missing_fraction"] == up["missing_fraction"]


def test_an_unknown_image_id_answers_404(url):
    for r in (
        plan_id(url, "0" * 32, {"k": 2}),
        httpx.post(f"{url}/v1/plan", json={"image_id": "0" * 32}, timeout=60),
    ):
        assert r.status_code == 404, r.text
        msg = r.json()["error"]["message"]
        assert "unknown or evicted image id" in msg and "upload the image again" in msg


@pytest.mark.parametrize(
    "params, field",
    [
        ({"k": 0}, "k"),
        ({"k": 101}, "k"),
        ({"seed": -1}, "seed"),
        ({"cem": 11}, "cem"),
        ({"roi": "400,400,500,500"}, "roi"),  # outside the image: empty
        ({"roi": "50,50,10,10"}, "roi"),
        ({"roi": "1,2,3"}, "roi"),
        ({"fx": 600.0}, "fx"),  # the upload's camera is the model's (assumed): it may not be changed
        ({"cy": 10.0}, "cy"),
    ],
)
def test_bad_parameters_on_an_uploaded_image_answer_422_naming_them(url, two_boxes, params, field):
    image_id = upload(url, two_boxes[0])
    r = plan_id(url, image_id, params)
    assert r.status_code == 422, r.text
    assert field in r.json()["error"]["message"]


def test_a_camera_other_than_the_uploads_answers_422_naming_it(url, two_boxes):
    image_id = upload(url, two_boxes[0], CAMERAS[1])
    r = plan_id(url, image_id, {"fy": 600.0})
    assert r.status_code == 422 and r.json()["error"]["details"] == {"field": "fy"}
    assert "uploaded with fy 610" in r.json()["error"]["message"]


@pytest.mark.parametrize(
    "body, status",
    [
        (b'{"image_id": 5}', 422),
        (b'{"image_id": "x", "k": 3}', 422),  # k goes in the query
        (b"[1]", 422),
        (b"{not json", 400),
    ],
)
def test_a_malformed_image_id_body_is_refused(url, body, status):
    r = httpx.post(f"{url}/v1/plan", content=body, headers={"content-type": "application/json"}, timeout=60)
    assert r.status_code == status, r.text


def test_planning_an_uploaded_image_takes_no_body(url, two_boxes):
    image_id = upload(url, two_boxes[0])
    r = plan_id(url, image_id, {"k": 1}, content=npy(two_boxes[0]), headers={"content-type": "application/x-npy"})
    assert r.status_code == 422 and "no body" in r.json()["error"]["message"]


def test_client_plans_an_uploaded_image(url, two_boxes):
    depth = two_boxes[0]
    with ServiceClient(url, timeout=60) as c:
        image_id = c.upload(depth, intrinsics=CAMERAS[1])
        by_id = c.plan(image_id=image_id, k=3, roi=(60, 60, 260, 240), seed=5)
        by_depth = c.plan(depth, k=3, intrinsics=CAMERAS[1], roi=(60, 60, 260, 240), seed=5)
        assert by_id.image_id == image_id and by_depth.image_id is None
        assert by_id.grasps == by_depth.grasps and len(by_id.grasps) == 3
        with pytest.raises(ServiceError) as e:
            c.plan(image_id="f" * 32)
        assert e.value.status == 404
        with pytest.raises(ServiceError) as e:
            c.plan(image_id=image_id, intrinsics={"fx": 525.0})
        assert e.value.status == 422 and e.value.details == {"field": "fx"}
        for bad in ({}, {"depth": depth, "image_id": image_id}):
            with pytest.raises(ValueError, match="one of the two"):
                c.plan(**bad)


def test_plan_needs_the_api_key_when_one_is_set(two_boxes):
    with running_service(MODEL_DIR, "--api-key", "s3cret") as u:
        assert post_plan(u, two_boxes[0], {"k": 1}).status_code == 401
        with ServiceClient(u, api_key="s3cret", timeout=60) as c:
            assert len(c.plan(two_boxes[0], k=1).grasps) == 1
        assert plan_id(u, "0" * 32).status_code == 401
        spec = httpx.get(f"{u}/openapi.json").json()
        assert spec["paths"]["/v1/plan"]["post"]["security"] == [{"ApiKey": []}]
        assert spec["paths"]["/v1/images/{image_id}/plan"]["post"]["security"] == [{"ApiKey": []}]


@pytest.mark.parametrize("slots", [1, 3])
def test_plans_run_at_most_max_concurrent_plans_at_once(two_boxes, monkeypatch, slots):
    """Six plans sent at once: no more than ``max_concurrent_plans`` compute together, and all answer."""
    import threading
    import time
    from concurrent.futures import ThreadPoolExecutor

    from fastapi.testclient import TestClient

    import service.plan_routes as plan_routes
    from service.app import create_app
    from service.config import Settings

    lock, active, peak = threading.Lock(), [0], [0]
    real = plan_routes.plan

    def counted(*args, **kw):
        with lock:
            active[0] += 1
            peak[0] = max(peak[0], active[0])
        try:
            time.sleep(0.25)  # long enough for the others to arrive
            return real(*args, **kw)
        finally:
            with lock:
                active[0] -= 1

    monkeypatch.setattr(plan_routes, "plan", counted)
    app = create_app(
        Settings(model_dir=str(MODEL_DIR), threads=1, max_concurrent_plans=slots, log_level="warning"),
        load_in_background=False,
    )
    with TestClient(app) as c, ThreadPoolExecutor(6) as pool:
        body = npy(two_boxes[0])
        codes = list(
            pool.map(
                lambda _: c.post("/v1/plan", content=body, headers={"content-type": "application/x-npy"}).status_code,
                range(6),
            )
        )
    assert codes == [200] * 6
    assert peak[0] == slots if slots == 1 else 1 < peak[0] <= slots


def test_a_plan_whose_client_left_while_it_waited_is_not_computed(two_boxes):
    """One plan slot: a second plan, whose client gives up while the first one computes, is
    dropped when the slot frees (counted as client gone), not planned."""
    import threading
    import time

    big = np.tile(two_boxes[0], (8, 8))  # 2400 x 2400 px: over a second of planning
    headers = {"content-type": "application/x-npy"}
    with running_service(MODEL_DIR, "--threads", "1", "--max-concurrent-plans", "1") as u:
        first = threading.Thread(target=lambda: post_plan(u, big))
        first.start()
        time.sleep(0.2)  # the first plan holds the slot
        with pytest.raises(httpx.TimeoutException):
            httpx.post(f"{u}/v1/plan", content=npy(big), headers=headers, timeout=0.3)
        first.join()
        deadline = time.monotonic() + 10
        gone = 'vgq_requests_total{endpoint="plan",status="499"}'
        while gone not in (m := httpx.get(f"{u}/metrics").text) and time.monotonic() < deadline:
            time.sleep(0.05)
    plans = [line for line in m.splitlines() if line.startswith("vgq_plans_total")]
    assert sum(float(line.split()[-1]) for line in plans) == 1, plans
    assert 'vgq_requests_total{endpoint="plan",status="499"} 1.0' in m, "the client gone is not counted"


def test_a_plan_whose_resampled_image_exceeds_max_image_side_answers_422(two_boxes):
    """As for uploads (fy following fx when only fx is sent): a camera with half the model's
    focal length doubles the image's sides when resampled, and over ``max_image_side`` that is
    a 422 naming fx, not a plan."""
    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.config import Settings

    app = create_app(
        Settings(model_dir=str(MODEL_DIR), threads=1, max_image_side=400, log_level="warning"),
        load_in_background=False,
    )
    body, headers = npy(two_boxes[0]), {"content-type": "application/x-npy"}
    with TestClient(app) as c:
        up = c.post("/v1/images", content=body, headers=headers, params={"fx": 262.5})
        r = c.post("/v1/plan", content=body, headers=headers, params={"fx": 262.5})
        ok = c.post("/v1/plan", content=body, headers=headers, params={"fx": 525.0})
    assert up.status_code == r.status_code == 422 and r.json()["error"]["message"] == up.json()["error"]["message"]
    assert "600x600 px, over max_image_side 400" in r.json()["error"]["message"] and r.json()["error"]["details"] == {
        "field": "fx"
    }
    assert ok.status_code == 200


def test_plans_beyond_the_queue_answer_503_at_once(two_boxes, monkeypatch):
    """One slot, one waiting place: of three plans sent while one computes, one waits its turn
    and the other two are refused at once with 503 and Retry-After (they do not wait)."""
    import threading
    import time
    from concurrent.futures import ThreadPoolExecutor

    from fastapi.testclient import TestClient

    import service.plan_routes as plan_routes
    from service.app import create_app
    from service.config import Settings

    real, started = plan_routes.plan, threading.Event()

    def slow(*args, **kw):
        started.set()
        time.sleep(1.0)
        return real(*args, **kw)

    monkeypatch.setattr(plan_routes, "plan", slow)
    settings = Settings(
        model_dir=str(MODEL_DIR), threads=1, max_concurrent_plans=1, max_queued_plans=1, log_level="warning"
    )
    body, headers = npy(two_boxes[0]), {"content-type": "application/x-npy"}
    app = create_app(settings, load_in_background=False)
    with TestClient(app) as c, ThreadPoolExecutor(4) as pool:
        first = pool.submit(c.post, "/v1/plan", content=body, headers=headers)
        assert started.wait(10)
        queued = pool.submit(c.post, "/v1/plan", content=body, headers=headers)
        deadline = time.monotonic() + 10
        while app.state.service.plan_slots.statistics().tasks_waiting < 1:  # the second waits for the slot
            assert time.monotonic() < deadline, "the second plan never waited"
            time.sleep(0.01)
        refused = [c.post("/v1/plan", content=body, headers=headers) for _ in range(2)]
        answers = [first.result(), queued.result()]
    assert [r.status_code for r in answers] == [200, 200]
    assert [r.status_code for r in refused] == [503, 503] and refused[0].headers["retry-after"] == "1"
    assert "max_queued_plans" in refused[0].json()["error"]["message"]  # a plan that waited would be a 200


def test_the_plan_limits_are_in_v1_model(url):
    limits = httpx.get(f"{url}/v1/model").json()["limits"]
    assert (limits["max_concurrent_plans"], limits["max_queued_plans"]) == (2, 16)


def test_the_planners_scores_equal_the_services_on_grasps_over_several_windows(url, two_boxes):
    """The planner scores as the service does, a head call per window (the bundled int8 head's
    activation scales follow its batch, so scoring each grasp with its own copy of the window's
    encoding in one stacked call gave other scores, and took 2.3x as long for 256 grasps)."""
    from planning.policy import grasp_rows, plan, window_scorer
    from service.runtime import FastModel

    depth = two_boxes[0]
    model = FastModel(MODEL_DIR, threads=1)
    res = plan(depth, DEFAULT_INTRINSICS, model, k=5, seed=0)
    rows = grasp_rows(res.candidates["frames"], DEFAULT_INTRINSICS).astype(np.float32)
    with ServiceClient(url) as c:
        served = c.score_details(c.upload(depth), rows)
    assert served["windows"] >= 2, served["windows"]  # grasps on both boxes: several windows
    ours, _ = window_scorer(model, depth, DEFAULT_INTRINSICS, "grid").score(rows.astype(np.float64))
    np.testing.assert_allclose(ours, served["raw_score"], atol=1e-6)
