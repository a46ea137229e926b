"""Fuzzing the real service from its own OpenAPI schema (schemathesis + hypothesis): no 5xx,
every status code documented, every response body and content type as the schema says.

Bodies of the binary media types come from strategies that build real .npy / PNG / .npz
payloads (valid ones and broken ones: truncated, NaN, wrong dtypes and shapes) so the
fuzzer reaches the decoders and the model, not only the first format check."""

from __future__ import annotations

import io
import zipfile

import httpx
import numpy as np
import pytest

schemathesis = pytest.importorskip("schemathesis", reason="schemathesis not installed (pip install 'schemathesis==4.32.5')")

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from PIL import Image  # noqa: E402
from schemathesis.checks import (content_type_conformance, not_a_server_error, response_schema_conformance,
                                 status_code_conformance)  # noqa: E402

from conftest import table_scene  # noqa: E402
from servers import running_service  # noqa: E402

CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance, response_schema_conformance]
MAX_EXAMPLES = 25

_values = st.sampled_from([0.7, 0.65, 0.0, -0.1, float("nan"), float("inf"), 1e30])
_shapes = st.one_of(st.tuples(st.integers(30, 70), st.integers(30, 70)), st.sampled_from([(0,), (5,), (2, 40, 40), (40, 40, 1), ()]))
_dtypes = st.sampled_from(["<f4", ">f4", "<f8", "<f2", "<i4", "|u1"])


@st.composite
def depth_arrays(draw) -> np.ndarray:
    shape = draw(_shapes)
    a = np.full(shape, 0.7, np.float64)
    if a.size:
        flat = a.reshape(-1)
        for i in draw(st.lists(st.integers(0, flat.size - 1), max_size=4)):
            flat[i] = draw(_values)
    with np.errstate(invalid="ignore", over="ignore"):
        return a.astype(draw(_dtypes))


def _npy(a: np.ndarray) -> bytes:
    b = io.BytesIO()
    np.save(b, a, allow_pickle=False)
    return b.getvalue()


@st.composite
def broken(draw, body: bytes) -> bytes:
    """``body`` as is, truncated, or with a few bytes overwritten."""
    how = draw(st.sampled_from(["keep", "keep", "truncate", "flip"]))
    if how == "truncate" and body:
        return body[: draw(st.integers(0, len(body) - 1))]
    if how == "flip" and body:
        b = bytearray(body)
        for i in draw(st.lists(st.integers(0, len(b) - 1), min_size=1, max_size=4)):
            b[i] = draw(st.integers(0, 255))
        return bytes(b)
    return body


npy_bodies = depth_arrays().map(_npy).flatmap(broken)
raw_bodies = st.one_of(st.binary(max_size=64), depth_arrays().map(lambda a: np.asarray(a, "<f4").tobytes()))


@st.composite
def png_bodies(draw) -> bytes:
    h, w = draw(st.integers(20, 60)), draw(st.integers(20, 60))
    mode = draw(st.sampled_from(["I;16", "I;16", "L"]))
    v = draw(st.integers(0, 65535))
    a = np.full((h, w), v, np.uint16) if mode == "I;16" else np.full((h, w), v % 256, np.uint8)
    b = io.BytesIO()
    Image.fromarray(a).save(b, format="PNG")
    return draw(broken(b.getvalue()))


@st.composite
def grasp_arrays(draw) -> np.ndarray:
    k = draw(st.integers(0, 6))
    g = np.tile(np.array([149.5, 149.5, 0.66, 1.0, 0.0, 0.0, 0.0]), (k, 1))
    for _ in range(draw(st.integers(0, 3))):
        if k:
            g[draw(st.integers(0, k - 1)), draw(st.integers(0, 6))] = draw(st.sampled_from([0.0, -1.0, 120.0, 1e9, float("nan"), 2.5]))
    return g.reshape(-1, 7) if draw(st.booleans()) else g.reshape(-1)


@st.composite
def npz_bodies(draw) -> bytes:
    members = {"depth": draw(depth_arrays()), "grasps": draw(grasp_arrays())}
    if draw(st.booleans()):
        members["center"] = np.array(draw(st.sampled_from([[149.5, 149.5], [20.0, 30.0], [1.0], [float("nan"), 1.0]])))
    if draw(st.booleans()):
        del members[draw(st.sampled_from(["depth", "grasps"]))]
    b = io.BytesIO()
    with zipfile.ZipFile(b, "w", draw(st.sampled_from([zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED]))) as z:
        for k, v in members.items():
            z.writestr(k + ".npy", _npy(v))
    return draw(broken(b.getvalue()))


schemathesis.openapi.media_type("application/x-npy", npy_bodies)
schemathesis.openapi.media_type("image/png", png_bodies())
schemathesis.openapi.media_type("application/x-npz", npz_bodies())


@pytest.fixture(scope="module")
def url(model_dir):
    with running_service(model_dir, "--max-grasps", "4", "--max-body-bytes", "400000", "--request-timeout-s", "5") as u:
        yield u


@pytest.fixture(scope="module")
def image_id(url):
    b = _npy(table_scene())
    return httpx.post(f"{url}/v1/images", content=b, headers={"content-type": "application/x-npy"}).json()["image_id"]


def _service_schema() -> dict:
    """The service's own OpenAPI document (the app is built, not started: no model needed)."""
    from service.app import create_app
    from service.config import Settings

    return create_app(Settings()).openapi()


schema = schemathesis.openapi.from_dict(_service_schema())


@schema.parametrize()
@settings(max_examples=MAX_EXAMPLES, deadline=None, derandomize=True, database=None,
          suppress_health_check=list(HealthCheck))
def test_schema_fuzz(case, url, image_id):
    if "image_id" in (case.path_parameters or {}) and len(case.path_parameters["image_id"]) % 2 == 0:
        case.path_parameters["image_id"] = image_id  # half the score requests hit a real cached image
    if case.path == "/v1/images" and isinstance(case.body, bytes) and len(case.body) % 2 == 0:
        case.query = {}  # random fx / fy / centres reject nearly every upload: send half without them
    if case.media_type == "application/octet-stream" and case.path.endswith("/scores") and isinstance(case.body, bytes):
        case.body = case.body[: len(case.body) // 28 * 28]  # whole k x 7 float32 rows: reach the grasp checks
    case.call_and_validate(base_url=url, checks=CHECKS)


@settings(max_examples=MAX_EXAMPLES, deadline=None, derandomize=True, database=None, suppress_health_check=list(HealthCheck))
@given(body=npz_bodies(), binary=st.booleans())
def test_one_shot_npz_fuzz(url, body, binary):
    """The .npz one-shot gets its own run: schemathesis rarely picks the second media type."""
    case = schema["/v1/score"]["POST"].Case(body=body, media_type="application/x-npz",
                                            headers={"accept": "application/octet-stream"} if binary else {})
    case.call_and_validate(base_url=url, checks=CHECKS)


@settings(max_examples=MAX_EXAMPLES, deadline=None, derandomize=True, database=None, suppress_health_check=list(HealthCheck))
@given(grasps=grasp_arrays(), as_json=st.booleans())
def test_score_grasps_fuzz(url, image_id, grasps, as_json):
    if as_json:
        case = schema["/v1/images/{image_id}/scores"]["POST"].Case(
            path_parameters={"image_id": image_id}, media_type="application/json",
            body={"grasps": [[float(x) if np.isfinite(x) else 0.0 for x in row] for row in grasps.reshape(-1, 7)]})
    else:
        case = schema["/v1/images/{image_id}/scores"]["POST"].Case(
            path_parameters={"image_id": image_id}, media_type="application/octet-stream", body=np.asarray(grasps, "<f4").tobytes())
    r = case.call_and_validate(base_url=url, checks=CHECKS)
    if r.status_code == 200:
        p = np.asarray(r.json()["p_success"], dtype=float)
        assert p.shape == (len(grasps.reshape(-1, 7)),) and np.all(np.isfinite(p))
