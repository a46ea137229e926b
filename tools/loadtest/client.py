"""The load test's HTTP clients: N concurrent closed-loop clients (httpx, or a minimal raw
HTTP/1.1 keep-alive client for precise sequential latency) driving one base URL."""

from __future__ import annotations

import asyncio
import gc
import ipaddress
import json
import time
from urllib.parse import urlsplit

import numpy as np

from .report import ENDPOINTS, SERVER_ENDPOINT, Recorder, server_latency_totals
from .workload import OCTET, FreshImages, Mix, Workload, bad_requests


def check_target(url: str, allow_remote: bool) -> str:
    """The base URL without a trailing slash; ValueError unless http(s) to a loopback host
    (or ``allow_remote``)."""
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ValueError(f"--url must be http://HOST:PORT, got {url!r}")
    host = parts.hostname
    try:
        loopback = ipaddress.ip_address(host).is_loopback
    except ValueError:
        loopback = host == "localhost"
    if not loopback and not allow_remote:
        raise ValueError(f"refusing to load non-loopback host {host!r}; pass --allow-remote if you own it")
    return url.rstrip("/")


async def _server_totals(http) -> dict | None:
    try:
        r = await http.get("/metrics")
        return server_latency_totals(r.text) if r.status_code == 200 else None
    except Exception:  # metrics are optional (e.g. behind a proxy that hides them)
        return None


# ---- clients ------------------------------------------------------------------------------
async def _timed(rec: Recorder, endpoint: str, coro, check, ok=lambda status: status == 200) -> object | None:
    t = time.perf_counter()
    try:
        r = await coro
    except Exception as e:  # transport errors count as errors, the run goes on
        rec.error(endpoint, f"{type(e).__name__}: {e}")
        return None
    dt = time.perf_counter() - t
    problem = f"HTTP {r.status_code}: {r.text[:160]}" if not ok(r.status_code) else check(r)
    if problem:
        rec.error(endpoint, problem)
        return None
    if rec.recording:
        rec.latencies[endpoint].append(dt)
    return r


NPY_H = {"content-type": "application/x-npy"}
SCORE_H = {"content-type": OCTET, "accept": OCTET}


def _upload_ok(r):
    try:
        return None if r.json().get("image_id") else "no image_id in answer"
    except ValueError:
        return "answer is not JSON"


def _plan_ok(r):
    try:
        grasps = r.json()["grasps"]
    except (ValueError, KeyError, TypeError):
        return "answer is not a plan"
    return None if isinstance(grasps, list) else "no grasps list in answer"


def _scores_ok(k: int):
    def check(r):
        return None if len(r.content) == 4 * k else f"answer of {len(r.content)} bytes, expected {4 * k}"

    return check


async def pin_image(http, work: Workload, fresh: FreshImages) -> str:
    """For a cached-score-only mix (``upload=0``): upload a fresh image and score the workload's
    grasps against it once, so its crop windows are encoded before anything is timed. Returns
    its id; RuntimeError when the service refuses either call."""
    gbytes = np.ascontiguousarray(work.grasps, "<f4").tobytes()
    r = await http.post("/v1/images", content=fresh.next_npy(), headers=NPY_H)
    if r.status_code != 200 or _upload_ok(r):
        raise RuntimeError(f"setting up the pinned image: upload answered {r.status_code}: {r.text[:160]}")
    image_id = r.json()["image_id"]
    r = await http.post(f"/v1/images/{image_id}/scores", content=gbytes, headers=SCORE_H)
    if r.status_code != 200 or _scores_ok(len(work.grasps))(r):
        raise RuntimeError(f"setting up the pinned image: score answered {r.status_code}: {r.text[:160]}")
    return image_id


async def client_loop(
    http,
    work: Workload,
    mix: Mix,
    deadline: float,
    rec: Recorder,
    fresh: FreshImages,
    bad: list[tuple[str, bytes, dict]] | None = None,
    pinned: str | None = None,
) -> None:
    """One client: repeat the mix's cycle until ``deadline`` (perf_counter seconds). ``bad``: the
    malformed requests of ``bad_requests`` (made once per run: the zip bomb alone takes ~0.25 s of
    CPU, which, made at the start of every client loop, held up the other clients' first requests).
    ``pinned``: the image of a cached-score-only mix (``pin_image``); score calls go to it."""
    k = len(work.grasps)
    gbytes = np.ascontiguousarray(work.grasps, "<f4").tobytes()
    npz_h = {"content-type": "application/x-npz", "accept": OCTET}
    scores_ok, upload_ok = _scores_ok(k), _upload_ok
    if mix.pinned and pinned is None:
        raise ValueError("a mix with upload=0 and score calls needs a pinned image (pin_image)")

    def error_named(r):
        try:
            return None if r.json()["error"]["message"] else "4xx without a message"
        except (ValueError, KeyError, TypeError):
            return f"4xx answer is not an error object: {r.text[:80]}"

    if mix.bad and not bad:
        bad = bad_requests(work)
    n_bad = 0

    while time.perf_counter() < deadline:
        image_id, first = pinned, not mix.pinned  # after an upload, the first score call encodes the windows
        for _ in range(mix.upload):
            r = await _timed(rec, "upload", http.post("/v1/images", content=fresh.next_npy(), headers=NPY_H), upload_ok)
            image_id = r.json()["image_id"] if r is not None else image_id
            if time.perf_counter() >= deadline:
                return
        for _ in range(mix.score if image_id else 0):
            endpoint, first = ("score_first" if first else "score"), False
            r = await _timed(
                rec, endpoint, http.post(f"/v1/images/{image_id}/scores", content=gbytes, headers=SCORE_H), scores_ok
            )
            if r is not None and rec.recording:
                rec.grasps += k
            if time.perf_counter() >= deadline:
                return
        for _ in range(mix.once):
            r = await _timed(
                rec, "score_once", http.post("/v1/score", content=fresh.next_npz(work.grasps), headers=npz_h), scores_ok
            )
            if r is not None and rec.recording:
                rec.grasps += k
            if time.perf_counter() >= deadline:
                return
        for _ in range(mix.plan):
            await _timed(rec, "plan", http.post("/v1/plan", content=fresh.next_npy(), headers=NPY_H), _plan_ok)
            if time.perf_counter() >= deadline:
                return
        for _ in range(mix.bad):
            path, body, headers = bad[n_bad % len(bad)]
            n_bad += 1
            await _timed(
                rec, "bad", http.post(path, content=body, headers=headers), error_named, ok=lambda st: 400 <= st < 500
            )
            if time.perf_counter() >= deadline:
                return


class RawResponse:
    """The parts of an httpx.Response the load test reads."""

    def __init__(self, status_code: int, content: bytes):
        self.status_code, self.content = status_code, content

    @property
    def text(self) -> str:
        return self.content.decode("utf-8", "replace")

    def json(self):
        return json.loads(self.content)


class RawHTTP:
    """A minimal HTTP/1.1 keep-alive client on one asyncio connection, for precise sequential
    latency (``--transport raw``): a few tens of microseconds per request where httpx takes
    several hundred, which on a 2-core machine also takes less CPU from the server."""

    def __init__(self, url: str, timeout: float):
        parts = urlsplit(url)
        if parts.scheme != "http":
            raise ValueError("--transport raw speaks plain http only; use --transport httpx for https")
        self.host, self.port, self.timeout = parts.hostname, parts.port or 80, timeout
        self.reader = self.writer = None

    async def _connect(self) -> None:
        self.reader, self.writer = await asyncio.open_connection(self.host, self.port)

    async def _request(self, method: str, path: str, content: bytes, headers: dict) -> RawResponse:
        if self.writer is None:
            await self._connect()
        head = [f"{method} {path} HTTP/1.1", f"host: {self.host}:{self.port}", f"content-length: {len(content)}"]
        head += [f"{k}: {v}" for k, v in headers.items()]
        self.writer.write(("\r\n".join(head) + "\r\n\r\n").encode() + content)
        status_line = await self.reader.readline()
        if not status_line:
            raise ConnectionError("server closed the connection")
        status = int(status_line.split()[1])
        length, chunked, close = None, False, False
        while (line := await self.reader.readline()) not in (b"\r\n", b""):
            name, _, value = line.decode("latin-1").partition(":")
            name, value = name.strip().lower(), value.strip().lower()
            if name == "content-length":
                length = int(value)
            elif name == "transfer-encoding" and "chunked" in value:
                chunked = True
            elif name == "connection" and value == "close":
                close = True
        if chunked:
            body = b""
            while (size := int((await self.reader.readline()).split(b";")[0], 16)) > 0:
                body += await self.reader.readexactly(size + 2)
                body = body[:-2]
            await self.reader.readline()
        else:
            body = await self.reader.readexactly(length or 0)
        if close:
            await self.aclose()
        return RawResponse(status, body)

    async def request(self, method: str, path: str, content: bytes = b"", headers: dict | None = None) -> RawResponse:
        try:
            async with _timeout(self.timeout):
                return await self._request(method, path, content, headers or {})
        except BaseException:
            await self.aclose()  # a half-read answer would poison the next request
            raise

    async def post(self, path: str, content: bytes = b"", headers: dict | None = None) -> RawResponse:
        return await self.request("POST", path, content, headers)

    async def get(self, path: str) -> RawResponse:
        return await self.request("GET", path)

    async def aclose(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.reader = self.writer = None


class _timeout:
    """``asyncio.timeout`` where available (3.11+), else a cancel-after-delay fallback."""

    def __init__(self, seconds: float):
        self.seconds = seconds
        self.cm = asyncio.timeout(seconds) if hasattr(asyncio, "timeout") else None

    async def __aenter__(self):
        if self.cm is not None:
            return await self.cm.__aenter__()
        task = asyncio.current_task()
        self.handle = asyncio.get_running_loop().call_later(self.seconds, task.cancel)

    async def __aexit__(self, *exc):
        if self.cm is not None:
            return await self.cm.__aexit__(*exc)
        self.handle.cancel()
        if exc[0] is asyncio.CancelledError:
            raise asyncio.TimeoutError from None


async def run_load(
    url: str,
    clients: int,
    duration: float,
    work: Workload,
    mix: Mix,
    warmup: float = 1.0,
    timeout: float = 10.0,
    seed: int | None = None,
    transport: str = "httpx",
) -> tuple[Recorder, float]:
    """Drive ``url`` with ``clients`` concurrent clients for ``warmup`` (not recorded) then
    ``duration`` seconds. ``transport``: ``httpx`` (one pooled AsyncClient, a connection per
    client) or ``raw`` (RawHTTP, one connection per client). A cached-score-only mix
    (``upload=0``) first pins an image per client (``pin_image``, not timed). Returns the
    recorder and the measured wall time (s)."""
    import httpx

    limits = httpx.Limits(max_connections=clients + 1, max_keepalive_connections=clients + 1)
    rec = Recorder()
    fresh = FreshImages(work.depth, seed)
    bad = bad_requests(work) if mix.bad else None
    async with httpx.AsyncClient(base_url=url, timeout=timeout, limits=limits) as http:
        conns = [RawHTTP(url, timeout) for _ in range(clients)] if transport == "raw" else [http] * clients
        try:
            r = await http.get("/readyz")
            if r.status_code != 200:
                raise RuntimeError(f"{url}/readyz answered {r.status_code}: {r.text[:200]}")
            pinned = [await pin_image(c, work, fresh) for c in conns] if mix.pinned else [None] * len(conns)
            if warmup > 0:
                rec.recording = False
                end = time.perf_counter() + warmup
                await asyncio.gather(
                    *(client_loop(c, work, mix, end, rec, fresh, bad, p) for c, p in zip(conns, pinned))
                )
                rec.recording = True
            gc.collect()
            before = await _server_totals(http)
            gc.freeze()  # the client's own GC pauses would show up as server latency
            t0 = time.perf_counter()
            end = t0 + duration
            # every request is bounded by ``timeout``: the run ends by end + timeout at the latest
            await asyncio.wait_for(
                asyncio.gather(*(client_loop(c, work, mix, end, rec, fresh, bad, p) for c, p in zip(conns, pinned))),
                duration + timeout + 5,
            )
            wall = time.perf_counter() - t0
            gc.unfreeze()
            after = await _server_totals(http)
        finally:
            for c in conns:
                if isinstance(c, RawHTTP):
                    await c.aclose()
    if before is not None and after is not None:
        for ep in ENDPOINTS:
            label = SERVER_ENDPOINT[ep]
            (s0, n0), (s1, n1) = before.get(label, (0.0, 0.0)), after.get(label, (0.0, 0.0))
            rec.server_mean_ms[ep] = (s1 - s0) / (n1 - n0) * 1e3 if n1 > n0 else None
    return rec, wall
