"""What the service holds at once: requests in flight and body bytes buffered, with the ASGI
middleware that counts, bounds and measures every request.

* ``max_inflight`` requests are served at once; one more answers 503 with ``Retry-After``
  at once, before its body is read (health, readiness and metrics are never refused).
* ``max_buffered_bytes`` of request bodies are held in memory across all requests; a body
  that does not fit answers 503 with ``Retry-After`` (its ``Content-Length`` is reserved
  before reading; a chunked body reserves as it arrives). A reservation lasts until the
  request's answer is sent.
* A client that goes away before its answer is counted as status 499 and logged at INFO,
  without a traceback: it is not a server error.
"""

from __future__ import annotations

import logging
import time

import orjson

from . import logs
from .metrics import Metrics

#: peak bytes held per buffered body byte: the body itself, plus, for an .npz, its unpacked depth
#: member (1x) and the boolean masks of the depth check (0.25x, one at a time); measured in
#: tests/test_service_limits.py::test_rss_under_concurrent_large_bodies_stays_under_the_bound
BODY_AMPLIFICATION = 2.25
#: per request in flight: uvicorn's read buffer (64 KiB high-water mark) and the header block
PER_REQUEST_BYTES = 64 * 1024 + 16 * 1024
#: peak bytes per pixel of the resampled image while an upload is resampled (about five float32
#: images, vgq.camera.resample_depth; one at a time, on the event loop)
RESAMPLE_BYTES_PER_PIXEL = 20
#: peak bytes per pixel of the resampled image while a plan runs (float32 organised cloud, normals
#: and their differences; vgq-plan's peak RSS on 300 to 4096 px images, 2026-12-01: ~86 B/px)
PLAN_BYTES_PER_PIXEL = 90


def worst_case_rss_bytes(settings, ready_rss_bytes: int) -> int:
    """Upper bound on the service's resident memory: its size once ready (model, sessions,
    empty cache), plus a full cache, plus every buffered body at its worst amplification, plus
    the per-request buffers of ``max_inflight`` requests."""
    return int(
        ready_rss_bytes
        + settings.cache_bytes
        + BODY_AMPLIFICATION * settings.max_buffered_bytes
        + settings.max_inflight * (PER_REQUEST_BYTES + settings.max_header_bytes)
    )


def worst_case_compute_bytes(settings) -> int:
    """Upper bound on what requests hold while they compute, on top of :func:`worst_case_rss_bytes`:
    one resample at a time on the event loop, and ``max_concurrent_plans`` plans in worker
    threads, each on an image of ``max_image_side`` squared pixels."""
    px = settings.max_image_side**2
    return int(RESAMPLE_BYTES_PER_PIXEL * px + settings.max_concurrent_plans * PLAN_BYTES_PER_PIXEL * px)


EXEMPT = frozenset({"/healthz", "/readyz", "/metrics"})
RETRY_AFTER_S = 1
CLIENT_GONE = 499  # nginx's code for "client closed the request"; never sent, only counted


class ByteBudget:
    """Bytes of request bodies held at once, all requests together (one event loop: no lock)."""

    def __init__(self, limit: int):
        self.limit, self.used = limit, 0

    def take(self, n: int) -> bool:
        if self.used + n > self.limit:
            return False
        self.used += n
        return True

    def give(self, n: int) -> None:
        self.used -= n


class Reservation:
    """One request's share of a ByteBudget; the middleware gives it back when the request ends."""

    def __init__(self, budget: ByteBudget):
        self.budget, self.held = budget, 0

    def take(self, n: int) -> bool:
        if self.budget.take(n):
            self.held += n
            return True
        return False

    def release(self) -> None:
        self.budget.give(self.held)
        self.held = 0


ENDPOINTS = {
    "/v1/images": "upload",
    "/v1/score": "score_once",
    "/metrics": "metrics",
    "/healthz": "healthz",
    "/readyz": "readyz",
    "/v1/model": "model",
    "/v1/cache": "cache",
    "/v1/plan": "plan",
}


def _endpoint(path: str) -> str:
    """The ``endpoint`` label of a request path (few values: the metrics stay small)."""
    if path.startswith("/v1/images/"):
        if path.endswith("/scores"):
            return "score"
        if path.endswith("/plan"):
            return "plan"
    return ENDPOINTS.get(path, "other")


class RequestMetrics:
    """The per-request metrics (latency by endpoint, count by endpoint and status) with each
    label combination's child looked up once: prometheus_client's ``labels()`` costs more
    than the observation itself."""

    def __init__(self, metrics: Metrics):
        self.metrics = metrics
        self._latency: dict[str, object] = {}
        self._count: dict[tuple[str, int], object] = {}

    def observe(self, endpoint: str, status: int, seconds: float) -> None:
        latency = self._latency.get(endpoint)
        if latency is None:
            latency = self._latency[endpoint] = self.metrics.latency.labels(endpoint)
        count = self._count.get((endpoint, status))
        if count is None:
            count = self._count[(endpoint, status)] = self.metrics.requests.labels(endpoint, str(status))
        latency.observe(seconds)
        count.inc()


async def _send_overloaded(send, message: str) -> None:
    body = orjson.dumps({"error": {"status": 503, "message": message}})
    await send(
        {
            "type": "http.response.start",
            "status": 503,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
                (b"retry-after", str(RETRY_AFTER_S).encode()),
                (b"connection", b"close"),
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})


class LimitsMiddleware:
    """Pure ASGI middleware: the in-flight bound, the byte budget's per-request reservation,
    request counts and latency per endpoint and status, and the optional access log."""

    def __init__(
        self, app, metrics: Metrics, log: logging.Logger, access_log: bool, max_inflight: int, max_buffered_bytes: int
    ):
        self.app, self.metrics, self.log, self.access_log = app, metrics, log, access_log
        self.request_metrics = RequestMetrics(metrics)
        self.max_inflight, self.inflight = max_inflight, 0
        self.budget = ByteBudget(max_buffered_bytes)

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        t0 = scope.get("vgq.t0") or time.perf_counter()  # headers complete (service.protocol), queueing included
        status = [500]

        async def send_status(msg):
            if msg["type"] == "http.response.start":
                status[0] = msg["status"]
            await send(msg)

        exempt = scope["path"] in EXEMPT
        reservation = Reservation(self.budget)
        scope["vgq.reservation"] = reservation
        counted = False
        try:
            if not exempt and self.inflight >= self.max_inflight:
                await _send_overloaded(
                    send_status, f"{self.inflight} requests in flight (limit {self.max_inflight}); retry shortly"
                )
            else:
                counted = not exempt
                self.inflight += counted
                await self.app(scope, receive, send_status)
        finally:
            self.inflight -= counted
            reservation.release()
            dt = time.perf_counter() - t0
            self.request_metrics.observe(_endpoint(scope["path"]), status[0], dt)
            if status[0] == CLIENT_GONE:
                logs.event(
                    self.log, "client disconnected", method=scope["method"], path=scope["path"], ms=round(dt * 1e3, 3)
                )
            elif self.access_log:
                logs.event(
                    self.log,
                    "request",
                    method=scope["method"],
                    path=scope["path"],
                    status=status[0],
                    ms=round(dt * 1e3, 3),
                )
