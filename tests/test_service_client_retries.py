"""The Python client sends a request again after a 503 (as Retry-After says) or a failed
connection, a bounded number of times; other answers are not repeated."""

from __future__ import annotations

import httpx
import pytest

from service.client import ServiceClient, ServiceError

MODEL = {"model_version": "m", "camera": {}}


def scripted(*steps):
    """A transport answering each request with the next step: a status code (503 with
    Retry-After 0) or an exception to raise; it records the requests."""
    seen = []

    def handle(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        step = steps[min(len(seen) - 1, len(steps) - 1)]
        if isinstance(step, Exception):
            raise step
        if step == 503:
            return httpx.Response(503, json={"error": {"status": 503, "message": "busy"}}, headers={"retry-after": "0"})
        if step == 422:
            return httpx.Response(422, json={"error": {"status": 422, "message": "field k is bad"}})
        return httpx.Response(200, json=MODEL)

    return httpx.MockTransport(handle), seen


def test_a_503_is_sent_again_until_it_is_answered():
    transport, seen = scripted(503, 503, 200)
    with ServiceClient("http://svc", transport=transport) as c:
        assert c.model() == MODEL
    assert len(seen) == 3


def test_a_failed_connection_is_tried_again():
    transport, seen = scripted(httpx.ConnectError("refused"), 200)
    with ServiceClient("http://svc", transport=transport) as c:
        assert c.model() == MODEL
    assert len(seen) == 2


def test_retries_are_bounded_and_the_last_answer_stands():
    transport, seen = scripted(503)
    with ServiceClient("http://svc", transport=transport, retries=2) as c, pytest.raises(ServiceError) as e:
        c.model()
    assert e.value.status == 503 and len(seen) == 3
    transport, seen = scripted(httpx.ConnectError("refused"))
    with ServiceClient("http://svc", transport=transport, retries=1) as c, pytest.raises(httpx.ConnectError):
        c.model()
    assert len(seen) == 2


def test_other_errors_are_not_repeated():
    transport, seen = scripted(422)
    with ServiceClient("http://svc", transport=transport) as c, pytest.raises(ServiceError) as e:
        c.model()
    assert e.value.status == 422 and len(seen) == 1
    transport, seen = scripted(503)
    with ServiceClient("http://svc", transport=transport, retries=0) as c, pytest.raises(ServiceError):
        c.model()
    assert len(seen) == 1


@pytest.mark.parametrize("bad", [-1, 1.5, True, "3"])
def test_retries_must_be_a_count(bad):
    with pytest.raises(ValueError, match="retries"):
        ServiceClient("http://svc", retries=bad)
