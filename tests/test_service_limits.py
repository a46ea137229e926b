"""The service's bounds on what clients may make it hold, against the real server (uvicorn
subprocess on loopback): header size and count (431), URL length (414), parser errors (400),
all in the JSON error shape and with the connection closed; requests and body bytes in flight
(503 + Retry-After); 405 with Allow; the connection closed after a 408; client disconnects
counted as 499 and logged at INFO without a traceback; no absolute path in any answer."""

from __future__ import annotations

import json
import re
import shutil
import socket
import threading
import time

import httpx
import numpy as np
import pytest
from conftest import table_scene
from servers import grasps_at, running_service, service_process
from test_service_bad_input import npy

TIMEOUT_S = 1.0
MAX_HEADER = 16 * 1024


@pytest.fixture(scope="module")
def served(model_dir, tmp_path_factory):
    """(URL, log file) of one service for the module."""
    log = tmp_path_factory.mktemp("limits") / "service.log"
    with service_process(
        model_dir,
        "--request-timeout-s",
        str(TIMEOUT_S),
        "--max-body-bytes",
        "2000000",
        "--max-buffered-bytes",
        "3000000",
        "--max-inflight",
        "6",
        log_path=log,
    ) as (u, _):
        yield u, log


@pytest.fixture(scope="module")
def url(served):
    return served[0]


def _addr(url: str) -> tuple[str, int]:
    host, port = url.removeprefix("http://").split(":")
    return host, int(port)


def _exchange(url: str, data: bytes, timeout: float = 10.0, chunk: int = 65536) -> tuple[bytes, float]:
    """Send ``data`` (stopping quietly if the server closes first), read until the server closes;
    return (everything it sent, seconds from the first byte sent to the close)."""
    with socket.create_connection(_addr(url), timeout=timeout) as s:
        t0 = time.monotonic()
        try:
            for i in range(0, len(data), chunk):
                s.sendall(data[i : i + chunk])
        except (BrokenPipeError, ConnectionResetError):
            pass
        got = b""
        try:
            while c := s.recv(65536):
                got += c
        except ConnectionResetError:
            pass
        return got, time.monotonic() - t0


def _json_error(raw: bytes, status: int) -> dict:
    head, _, body = raw.partition(b"\r\n\r\n")
    assert head.split(b" ")[1] == str(status).encode(), raw[:200]
    assert b"content-type: application/json" in head.lower(), head
    assert b"connection: close" in head.lower(), head
    err = json.loads(body)["error"]
    assert err["status"] == status and err["message"]
    return err


def test_two_megabyte_headers_are_refused_within_a_second_while_healthz_answers(url):
    """The issue's header flood, from 4 connections at once: each gets 431 within 1 s, and
    /healthz keeps answering meanwhile (the 2 MB are never gathered: the server stops at the
    limit plus one read)."""
    lat, stop = [], threading.Event()

    def probe():
        with httpx.Client(base_url=url, timeout=5) as c:
            while not stop.is_set():
                t = time.perf_counter()
                assert c.get("/healthz").status_code == 200
                lat.append(time.perf_counter() - t)

    def flood(out):
        out.append(_exchange(url, b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Flood: " + b"a" * 2_000_000 + b"\r\n\r\n"))

    th = threading.Thread(target=probe)
    th.start()
    results: list = []
    try:
        while len(lat) < 5:
            time.sleep(0.01)
        floods = [threading.Thread(target=flood, args=(results,)) for _ in range(4)]
        for f in floods:
            f.start()
        for f in floods:
            f.join()
        n = len(lat)
        while len(lat) < n + 5:
            time.sleep(0.01)
    finally:
        stop.set()
        th.join()
    for got, dt in results:
        assert str(MAX_HEADER) in _json_error(got, 431)["message"]
        assert dt < 1.0, dt
    assert len(results) == 4 and max(lat) < 1.0  # loose on a shared machine; the measured p99 is in docs/reliability.md


def test_too_many_headers_is_431(url):
    req = b"GET /healthz HTTP/1.1\r\nHost: x\r\n" + b"".join(b"X-H%d: 1\r\n" % i for i in range(150)) + b"\r\n"
    assert "more than 100 request headers" in _json_error(_exchange(url, req)[0], 431)["message"]


def test_header_block_in_many_small_reads_is_counted(url):
    """Many reads, none over the limit alone: the count is per request, not per read."""
    req = b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Long: " + b"b" * (MAX_HEADER + 100) + b"\r\n\r\n"
    _json_error(_exchange(url, req, chunk=512)[0], 431)


def test_headers_under_the_limit_are_served(url):
    r = httpx.get(f"{url}/healthz", headers={f"x-h{i}": "v" * 100 for i in range(90)})
    assert r.status_code == 200


def test_long_url_is_414(url):
    req = b"GET /healthz?" + b"q" * 10000 + b" HTTP/1.1\r\nHost: x\r\n\r\n"
    assert "request target exceeds" in _json_error(_exchange(url, req)[0], 414)["message"]


@pytest.mark.parametrize(
    "req",
    [
        b"GET / HTTP/1.1\r\nBad Header Line\r\n\r\n",
        b"\x16\x03\x01 TLS hello\r\n\r\n",
        b"POST /v1/images HTTP/1.1\r\nHost: x\r\nContent-Length: -5\r\n\r\n",
    ],
    ids=["bad-header", "tls-to-http", "negative-length"],
)
def test_parser_errors_answer_the_json_error_shape(url, req):
    assert "invalid HTTP request" in _json_error(_exchange(url, req)[0], 400)["message"]


def test_405_names_the_allowed_methods(url):
    r = httpx.get(f"{url}/v1/images")
    assert r.status_code == 405 and r.headers["allow"] == "POST"
    assert r.json()["error"]["status"] == 405
    r = httpx.delete(f"{url}/healthz")
    assert r.status_code == 405 and "GET" in r.headers["allow"]


def test_body_timeout_408_closes_the_connection(url):
    """After a 408 the server closes the connection at once (it used to stay open 30 s)."""
    req = b"POST /v1/images HTTP/1.1\r\nHost: x\r\nContent-Type: application/x-npy\r\nContent-Length: 100000\r\n\r\n\x93NUMPY"
    with socket.create_connection(_addr(url), timeout=10) as s:
        s.sendall(req)
        t0 = time.monotonic()
        got = b""
        while c := s.recv(65536):
            got += c
        closed_after = time.monotonic() - t0
    _json_error(got, 408)
    assert closed_after < TIMEOUT_S + 3


def _stalled_upload(url: str, declared: int) -> socket.socket:
    s = socket.create_connection(_addr(url), timeout=10)
    s.sendall(
        b"POST /v1/images HTTP/1.1\r\nHost: x\r\nContent-Type: application/x-npy\r\n"
        b"Content-Length: %d\r\n\r\n\x93NUMPY" % declared
    )
    return s


def test_byte_budget_refuses_a_body_that_does_not_fit_with_503(url):
    held = _stalled_upload(url, 1_900_000)  # reserves 1.9 of the 3 MB budget while it stalls
    try:
        time.sleep(0.3)
        r = httpx.post(
            f"{url}/v1/images",
            content=npy(np.full((700, 700), 0.7, np.float32)),
            headers={"content-type": "application/x-npy"},
        )
        assert r.status_code == 503 and r.headers["retry-after"] == "1", r.text
        assert "do not fit" in r.json()["error"]["message"]
        ok = httpx.post(f"{url}/v1/images", content=npy(table_scene()), headers={"content-type": "application/x-npy"})
        assert ok.status_code == 200  # a small body still fits
    finally:
        held.close()


def test_requests_in_flight_beyond_the_limit_get_503_and_health_still_answers(url):
    held = [_stalled_upload(url, 1000) for _ in range(6)]
    try:
        time.sleep(0.3)
        r = httpx.post(f"{url}/v1/images", content=npy(table_scene()), headers={"content-type": "application/x-npy"})
        assert r.status_code == 503 and r.headers["retry-after"] == "1"
        assert "requests in flight" in r.json()["error"]["message"]
        assert httpx.get(f"{url}/healthz").status_code == 200
        assert httpx.get(f"{url}/metrics").status_code == 200
    finally:
        for s in held:
            s.close()
    time.sleep(0.3)
    assert (
        httpx.post(
            f"{url}/v1/images", content=npy(table_scene()), headers={"content-type": "application/x-npy"}
        ).status_code
        == 200
    )


def _count(metrics: str, line: str) -> float:
    m = re.search(re.escape(line) + r" ([0-9.]+)", metrics)
    return float(m.group(1)) if m else 0.0


def test_client_disconnect_is_499_at_info_without_traceback(served):
    u, log = served
    line = 'vgq_requests_total{endpoint="upload",status="499"}'
    before = _count(httpx.get(f"{u}/metrics").text, line)
    logged = len([x for x in log.read_text().splitlines() if '"client disconnected"' in x])
    for _ in range(3):
        s = _stalled_upload(u, 500_000)
        s.sendall(b"\0" * 1000)
        time.sleep(0.2)
        s.close()
    time.sleep(0.5)
    text = httpx.get(f"{u}/metrics").text
    assert _count(text, line) == before + 3
    assert 'status="500"' not in text
    lines = [json.loads(x) for x in log.read_text().splitlines() if x.startswith("{")]
    gone = [x for x in lines if x["msg"] == "client disconnected"]
    assert len(gone) == logged + 3 and all(x["level"] == "info" and x["path"] == "/v1/images" for x in gone)
    assert "Traceback" not in log.read_text() and not any(x["level"] == "error" for x in lines)


def _score_path(url: str) -> str:
    r = httpx.post(f"{url}/v1/images", content=npy(table_scene()), headers={"content-type": "application/x-npy"})
    assert r.status_code == 200, r.text
    return f"/v1/images/{r.json()['image_id']}/scores"


def _score_head(path: str, n: int) -> bytes:
    return b"POST %s HTTP/1.1\r\nHost: x\r\nContent-Type: application/octet-stream\r\nContent-Length: %d\r\n\r\n" % (
        path.encode(),
        n,
    )


def test_score_body_late_is_408_and_a_body_after_its_headers_is_read(url):
    """The scoring fast path reads a body that arrives after its headers (no timer is armed only
    when the server holds the whole body already) and answers 408 when it never completes."""
    path = _score_path(url)
    body = np.ascontiguousarray(grasps_at(k=4), "<f4").tobytes()
    with socket.create_connection(_addr(url), timeout=10) as s:
        s.sendall(_score_head(path, len(body)))
        time.sleep(0.3)  # the headers alone: the app starts before its body is in
        s.sendall(body)
        head = s.recv(65536)
    assert head.startswith(b"HTTP/1.1 200"), head[:200]
    with socket.create_connection(_addr(url), timeout=10) as s:
        s.sendall(_score_head(path, len(body)) + body[:10])
        t0 = time.monotonic()
        got = b""
        while c := s.recv(65536):
            got += c
    _json_error(got, 408)
    assert time.monotonic() - t0 < TIMEOUT_S + 3


def test_requests_are_counted_per_endpoint_and_status(url):
    """The request counters and latency histograms (label children looked up once, then reused)
    count each request under its own endpoint and status."""
    path = _score_path(url)
    body = np.ascontiguousarray(grasps_at(k=4), "<f4").tobytes()
    octet = {"content-type": "application/octet-stream"}
    lines = (
        'vgq_requests_total{endpoint="score",status="200"}',
        'vgq_requests_total{endpoint="score",status="404"}',
        'vgq_requests_total{endpoint="score",status="422"}',
        'vgq_request_seconds_count{endpoint="score"}',
        'vgq_requests_total{endpoint="healthz",status="200"}',
        'vgq_request_seconds_count{endpoint="healthz"}',
    )
    before = [_count(httpx.get(f"{url}/metrics").text, x) for x in lines]
    for _ in range(3):
        assert httpx.post(url + path, content=body, headers=octet).status_code == 200
    assert httpx.post(f"{url}/v1/images/{'0' * 32}/scores", content=body, headers=octet).status_code == 404
    assert httpx.post(url + path, content=body[:-4], headers=octet).status_code == 422
    for _ in range(2):
        assert httpx.get(f"{url}/healthz").status_code == 200
    after = [_count(httpx.get(f"{url}/metrics").text, x) for x in lines]
    assert [a - b for a, b in zip(after, before)] == [3, 1, 1, 5, 2, 2]


def test_no_absolute_path_in_any_answer(model_dir, tmp_path):
    """The model card may record where its data was built; answers name no folder of this host."""
    m = tmp_path / "model"
    shutil.copytree(model_dir, m)
    card = json.loads((m / "model_card.json").read_text())
    card["dataset"] = {
        **card.get("dataset", {}),
        "root": "/home/builder/secret/data/crops",
        "files": ["/srv/x/shard_0.npz"],
    }
    (m / "model_card.json").write_text(json.dumps(card))
    with running_service(m) as u:
        for path in ("/v1/model", "/readyz", "/v1/cache", "/healthz", "/openapi.json"):
            text = httpx.get(u + path).text
            for folder in ("/home/", "/srv/", str(tmp_path), str(model_dir)):
                assert folder not in text, (path, folder)
        assert httpx.get(u + "/v1/model").json()["model_card"]["dataset"]["root"] == "crops"
        r = httpx.post(
            f"{u}/v1/images/{'0' * 32}/scores",
            content=grasps_at(k=1).tobytes(),
            headers={"content-type": "application/octet-stream"},
        )
        assert r.status_code == 404 and str(m) not in r.text


def _proc_bytes(pid: int, field: str) -> int:
    for line in open(f"/proc/{pid}/status"):
        if line.startswith(field + ":"):
            return int(line.split()[1]) * 1024
    raise KeyError(field)


def test_rss_under_concurrent_large_bodies_stays_under_the_bound(model_dir):
    """8 clients at once send bodies near the size limit (.npz one-shots, then .npy uploads): what
    fits the byte budget is served, the rest gets 503 + Retry-After, and the peak RSS stays under
    the documented bound (service.limits.worst_case_rss_bytes). The issue's 8 x 30 MB at the
    default limits is the same at 1/4 scale here (8 MB bodies, 16 MB budget) to keep the suite
    fast; VGQ_RSS_FULL=1 runs it at full scale (29 MB bodies, the default limits), as
    docs/reliability.md reports."""
    import io
    import os

    from service.config import Settings
    from service.limits import worst_case_rss_bytes

    if os.environ.get("VGQ_RSS_FULL"):
        settings, side = Settings(), 2700  # 29.2 MB of float32 per body
    else:
        settings, side = (
            Settings(max_body_bytes=8_000_000, max_buffered_bytes=16_000_000, cache_bytes=4096 * 4096),
            1400,
        )
    d = np.full((side, side), 0.7, np.float32)

    def body(kind: str, i: int) -> bytes:
        d[0, 0] = 0.5 + i * 1e-4 + (kind == "npy") * 0.01
        b = io.BytesIO()
        if kind == "npz":
            np.savez(b, depth=d, grasps=np.tile([side / 2, side / 2, 0.66, 1, 0, 0, 0], (8, 1)))
        else:
            np.save(b, d)
        return b.getvalue()

    with service_process(
        model_dir,
        "--max-body-bytes",
        str(settings.max_body_bytes),
        "--max-buffered-bytes",
        str(settings.max_buffered_bytes),
        "--cache-bytes",
        str(settings.cache_bytes),
    ) as (u, proc):
        ready = _proc_bytes(proc.pid, "VmRSS")
        bound = worst_case_rss_bytes(settings, ready)
        for kind, path, ct in (("npz", "/v1/score", "application/x-npz"), ("npy", "/v1/images", "application/x-npy")):
            bodies = [body(kind, i) for i in range(8)]
            with open(f"/proc/{proc.pid}/clear_refs", "w") as f:
                f.write("5")  # reset the peak (VmHWM) to the current RSS
            answers = []

            def send(i):
                try:
                    r = httpx.post(u + path, content=bodies[i], headers={"content-type": ct}, timeout=60)
                    answers.append((r.status_code, r.headers.get("retry-after")))
                except httpx.TransportError:  # refused with 503 + close while still sending
                    answers.append(("closed", None))

            threads = [threading.Thread(target=send, args=(i,)) for i in range(8)]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            peak = _proc_bytes(proc.pid, "VmHWM")
            print(
                f"{kind}: ready {ready / 2**20:.0f} MiB, peak {peak / 2**20:.0f} MiB, bound {bound / 2**20:.0f} MiB, {answers}"
            )
            served = [a for a in answers if a[0] == 200]
            assert served and len(served) < 8, answers  # two max-size bodies at once at most
            assert all(a in ((200, None), (503, "1"), ("closed", None)) for a in answers), answers
            assert peak <= bound, f"{kind}: peak RSS {peak / 2**20:.0f} MiB over the bound {bound / 2**20:.0f} MiB"
        assert httpx.get(u + "/healthz").status_code == 200
