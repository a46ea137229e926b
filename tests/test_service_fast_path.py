"""service.routes.ScoringFastPath: the two scoring routes served without FastAPI's router answer
exactly as the router's routes do (status, body, headers), errors included."""

from __future__ import annotations

import io
import warnings

import numpy as np
import pytest
from conftest import table_scene
from servers import grasps_at

with warnings.catch_warnings():  # starlette now asks for the httpx2 package; httpx still does the job here
    warnings.filterwarnings("ignore", message="Using `httpx` with `starlette.testclient`")
    from starlette.testclient import TestClient

from service.app import create_app
from service.config import Settings
from service.routes import ScoringFastPath

KEY = {"x-api-key": "secret"}
OCTET, NPY, NPZ = "application/octet-stream", "application/x-npy", "application/x-npz"


def _npz(**arrays) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def _npy(a) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.asarray(a, np.float32))
    return buf.getvalue()


@pytest.fixture(scope="module")
def clients(model_dir):
    """(fast, router): the same app with and without the fast path."""
    settings = Settings(model_dir=str(model_dir), threads=1, api_key="secret", log_level="warning")
    fast = create_app(settings, load_in_background=False)
    router = create_app(settings, load_in_background=False)
    router.user_middleware = [m for m in router.user_middleware if m.cls is not ScoringFastPath]
    assert len(fast.user_middleware) == len(router.user_middleware) + 1
    with TestClient(fast) as a, TestClient(router) as b:
        yield a, b


def _requests(image_id: str) -> list[tuple[str, str, dict, bytes | None, dict | None]]:
    """(method, path, headers, body, multipart files) of the requests compared."""
    depth = table_scene()
    g = grasps_at(k=16)
    gb = np.ascontiguousarray(g, "<f4").tobytes()
    nan = g.copy()
    nan[3, 2] = np.nan
    zero_q = g.copy()
    zero_q[2, 3:] = 0
    away = g.copy()
    away[:, 3:] = [0.0, 1.0, 0.0, 0.0]  # approach away from the camera: flagged
    scores = f"/v1/images/{image_id}/scores"
    json_h = {**KEY, "content-type": "application/json"}
    return [
        ("POST", scores, {**KEY, "content-type": OCTET, "accept": OCTET}, gb, None),
        ("POST", scores, {**KEY, "content-type": OCTET}, gb, None),
        ("POST", scores, json_h, b'{"grasps": %s}' % str(g.tolist()).encode(), None),
        (
            "POST",
            scores + "?strict=true",
            {**KEY, "content-type": OCTET},
            np.ascontiguousarray(away, "<f4").tobytes(),
            None,
        ),
        ("POST", scores + "?strict=maybe", {**KEY, "content-type": OCTET}, gb, None),
        ("POST", scores + "?strict=", {**KEY, "content-type": OCTET}, gb, None),  # empty: 422, not false
        ("POST", "/v1/score?strict=", {**KEY, "content-type": NPZ}, _npz(depth=depth, grasps=g), None),
        ("POST", scores, {"content-type": OCTET}, gb, None),  # no API key
        ("POST", scores, {**KEY, "content-type": "text/plain"}, gb, None),
        ("POST", scores, {**KEY, "content-type": OCTET}, np.ascontiguousarray(nan, "<f4").tobytes(), None),
        ("POST", scores, {**KEY, "content-type": OCTET}, np.ascontiguousarray(zero_q, "<f4").tobytes(), None),
        ("POST", scores, {**KEY, "content-type": OCTET}, gb[:-4], None),
        ("POST", scores, json_h, b'{"grasps": [[1, 2,', None),
        ("POST", "/v1/images/" + "0" * 32 + "/scores", {**KEY, "content-type": OCTET}, gb, None),
        ("POST", "/v1/images//scores", {**KEY, "content-type": OCTET}, gb, None),
        ("GET", scores, KEY, None, None),
        ("POST", "/v1/score", {**KEY, "content-type": NPZ}, _npz(depth=depth, grasps=g), None),
        ("POST", "/v1/score", {**KEY, "content-type": NPZ, "accept": OCTET}, _npz(depth=depth, grasps=g), None),
        (
            "POST",
            "/v1/score",
            {**KEY, "content-type": NPZ},
            _npz(depth=depth + 0.01, grasps=g, center=[150.0, 150.0]),
            None,
        ),
        ("POST", "/v1/score", {**KEY, "content-type": NPZ}, _npz(depth=depth, grasps=zero_q), None),
        ("POST", "/v1/score", {**KEY, "content-type": NPZ}, _npz(grasps=g), None),
        ("POST", "/v1/score", {**KEY, "content-type": NPZ}, _npz(depth=depth)[:-30], None),
        ("POST", "/v1/score", {**KEY, "content-type": NPY}, _npy(depth), None),
        ("POST", "/v1/score", KEY, None, {"depth": ("d.npy", _npy(depth + 0.02), NPY), "grasps": (None, gb, OCTET)}),
        ("POST", "/v1/score/", {**KEY, "content-type": NPZ}, _npz(depth=depth, grasps=g), None),
        ("GET", "/v1/score", KEY, None, None),
    ]


def test_fast_path_answers_exactly_as_the_router(clients):
    fast, router = clients
    depth = _npy(table_scene())
    ids = [
        c.post("/v1/images", content=depth, headers={**KEY, "content-type": NPY}).json()["image_id"] for c in clients
    ]
    assert ids[0] == ids[1]
    for method, path, headers, body, files in _requests(ids[0]):
        a, b = (
            c.request(method, path, headers=headers, content=body, files=files, follow_redirects=False)
            for c in (fast, router)
        )
        where = f"{method} {path} {headers.get('content-type')}"
        assert a.status_code == b.status_code, (where, a.text[:300], b.text[:300])
        assert a.content == b.content, where
        for h in (
            "content-type",
            "x-image-id",
            "x-calibrated",
            "x-ood-count",
            "x-windows-encoded",
            "allow",
            "location",
        ):
            assert a.headers.get(h) == b.headers.get(h), (where, h)
    assert fast.get("/v1/cache").json()["windows_encoded"] == router.get("/v1/cache").json()["windows_encoded"]


def test_fastapis_opentelemetry_is_off_unless_asked_for(monkeypatch):
    """FastAPI's native OpenTelemetry checks the global providers on every request (~17 us):
    the service turns it off unless ``otel`` is set, even where providers are configured."""
    import fastapi.telemetry._asgi as otel

    monkeypatch.setattr(otel, "_unconfigured", lambda provider: False)  # as if an SDK set providers
    assert not create_app(Settings())._native_telemetry.enabled()
    assert create_app(Settings(otel=True))._native_telemetry.enabled()
