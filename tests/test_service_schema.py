"""Schemathesis with every check against the real service, from the service's own OpenAPI
document: no 5xx, every answer in a documented status, content type, schema and headers; the
JSON error shape; 405 with Allow for undeclared methods; schema-invalid requests refused
(negative data); schema-valid ones never refused as malformed.

One setting differs from schemathesis's defaults, on purpose: schema-valid requests may be
answered 422. A JSON schema cannot say that a ``format: binary`` body must be a float32 .npy
with finite, non-negative depth, that grasps must lie in the crop window, or that fx must
match the model's camera; the service answers those with 422 naming the value. What the
schema can say, it says (bounds, integer-ness, required parts), and those answers are never
400 / 415 for data the schema accepts."""

from __future__ import annotations

import httpx
import pytest

schemathesis = pytest.importorskip(
    "schemathesis", reason="schemathesis not installed (pip install 'schemathesis==4.32.5')"
)

import io  # noqa: E402

import numpy as np  # noqa: E402
from conftest import table_scene  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from PIL import Image  # noqa: E402
from schema_operations import add_operation_tests  # noqa: E402
from schemathesis.config import SchemathesisConfig  # noqa: E402
from servers import grasps_at, running_service  # noqa: E402
from test_service_bad_input import npy  # noqa: E402


def _npz() -> bytes:
    b = io.BytesIO()
    np.savez(b, depth=table_scene(), grasps=grasps_at(k=2))
    return b.getvalue()


def _png() -> bytes:
    b = io.BytesIO()
    Image.fromarray(np.round(table_scene() * 1000).astype(np.uint16)).save(b, format="PNG")
    return b.getvalue()


# binary bodies: a valid one (reaches the model) or a few random bytes (reaches the decoders)
for media, valid in (("application/x-npy", npy(table_scene())), ("application/x-npz", _npz()), ("image/png", _png())):
    schemathesis.openapi.media_type(media, st.one_of(st.just(valid), st.binary(max_size=64)))

MAX_EXAMPLES = 30
POSITIVE_OK = ["2xx", "404", "422"]  # 404: a generated image id names no cached image


def _service_schema() -> dict:
    """The service's own OpenAPI document (the app is built, not started: no model needed)."""
    from service.app import create_app
    from service.config import Settings

    return create_app(Settings()).openapi()


CONFIG = SchemathesisConfig.from_dict(
    {
        "checks": {"positive_data_acceptance": {"expected-statuses": POSITIVE_OK}},
        "generation": {"mode": "all"},
    }
)
schema = schemathesis.openapi.from_dict(_service_schema(), config=CONFIG)


@pytest.fixture(scope="module")
def url(model_dir):
    with running_service(
        model_dir,
        "--max-grasps",
        "4",
        "--max-body-bytes",
        "400000",
        "--max-buffered-bytes",
        "4000000",
        "--request-timeout-s",
        "5",
    ) as u:
        yield u


@pytest.fixture(scope="module")
def image_id(url):
    r = httpx.post(f"{url}/v1/images", content=npy(table_scene()), headers={"content-type": "application/x-npy"})
    return r.json()["image_id"]


def check_every(case, url, image_id):
    """One case with every check enabled in CONFIG (all of schemathesis's built-ins)."""
    if "image_id" in (case.path_parameters or {}) and len(str(case.path_parameters["image_id"])) % 2 == 0:
        case.path_parameters["image_id"] = image_id  # half the score requests reach a cached image
    case.call_and_validate(base_url=url)  # every check enabled in CONFIG: all of schemathesis's built-ins


add_operation_tests(globals(), "test_every_check_", schema, MAX_EXAMPLES, check_every)
