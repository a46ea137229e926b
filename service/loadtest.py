"""HTTP load test of a running scoring service (asyncio + httpx; no torch).

    python -m service.loadtest --url http://127.0.0.1:8000 --clients 8 --duration 30 --k 128
    python -m service.loadtest --clients 1 --duration 20          # sequential latency (raw client)

N clients run concurrently for a bounded time. Each repeats a cycle (``--mix``, default
``upload=1,score=8,once=1``): upload a fresh depth image (``POST /v1/images``, encoder runs),
score k grasps against it several times (``POST /v1/images/{id}/scores``, cached image, head
only; float32 body and answer, as ``service.client`` sends), then one-shot calls with fresh
images (``POST /v1/score``, .npz body, uncached: encoder + head), then (``bad=N``) malformed
requests in rotation, each of which must get a 4xx with an error message (soak runs). Images are the example in
``examples/`` (or a synthetic table + box scene) with a unique value written into pixel (0, 0),
outside the crop window, so every upload is a cache miss.

Reports per endpoint the requests, errors, p50 / p90 / p99 / max latency (client side, ms),
the server-side mean (from the service's /metrics, when readable), requests and grasps per second, and with ``--server-pid`` the server's resident memory
(process and its children) before and after. It only targets the URL given and refuses
non-loopback hosts unless ``--allow-remote`` is passed.
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import io
import ipaddress
import json
import os
import sys
import time
import zipfile
from dataclasses import asdict, dataclass, field
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = ROOT / "examples"
ENDPOINTS = ("upload", "score", "score_once", "bad")
OCTET = "application/octet-stream"


@dataclass(frozen=True)
class Mix:
    """Requests per client cycle: uploads of a fresh image, score calls per upload, one-shots,
    and bad requests (malformed on purpose; each must get a 4xx naming the problem)."""

    upload: int = 1
    score: int = 8
    once: int = 1
    bad: int = 0

    @classmethod
    def parse(cls, text: str) -> "Mix":
        """``"upload=1,score=8,once=1,bad=0"`` (missing keys keep their defaults)."""
        kw = {}
        for part in filter(None, (p.strip() for p in text.split(","))):
            name, _, value = part.partition("=")
            if name not in ("upload", "score", "once", "bad") or not value.strip().isdigit():
                raise ValueError(f"bad --mix entry {part!r}; expected upload=N, score=N, once=N, bad=N (N >= 0)")
            kw[name] = int(value)
        mix = cls(**kw)
        if mix.score and not mix.upload:
            raise ValueError("--mix: score calls need an upload (upload >= 1)")
        if not (mix.upload or mix.once or mix.bad):
            raise ValueError("--mix: nothing to do (upload, once and bad are all 0)")
        return mix


@dataclass
class Workload:
    depth: np.ndarray  # (H, W) float32 metres
    grasps: np.ndarray  # (k, 7) float32 u, v, z, qw, qx, qy, qz
    source: str


@dataclass
class Recorder:
    latencies: dict[str, list[float]] = field(default_factory=lambda: {e: [] for e in ENDPOINTS})
    errors: dict[str, int] = field(default_factory=lambda: {e: 0 for e in ENDPOINTS})
    messages: dict[str, int] = field(default_factory=dict)
    grasps: int = 0
    recording: bool = True
    server_mean_ms: dict[str, float | None] = field(default_factory=dict)  # from /metrics, server side

    def error(self, endpoint: str, message: str) -> None:
        if self.recording:
            self.errors[endpoint] += 1
            self.messages[message[:200]] = self.messages.get(message[:200], 0) + 1


# ---- workload ---------------------------------------------------------------------------
def synthetic_scene(h: int = 300, w: int = 300, table: float = 0.7, box=(120, 180, 130, 170), height: float = 0.05) -> np.ndarray:
    """Depth (metres) of a table seen from above with a box on it."""
    d = np.full((h, w), table, np.float32)
    d[box[0] : box[1], box[2] : box[3]] = table - height
    return d


def synthetic_grasps(k: int, center=(149.5, 149.5), spread: float = 30.0, z: float = 0.66, seed: int = 0) -> np.ndarray:
    """k grasps within +/- spread px of ``center``, depth z metres, random unit quaternions."""
    rng = np.random.default_rng(seed)
    g = np.zeros((k, 7), np.float32)
    g[:, :2] = np.asarray(center) + rng.uniform(-spread, spread, (k, 2))
    g[:, 2] = z
    q = rng.standard_normal((k, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    g[:, 3:] = np.where(q[:, :1] < 0, -q, q)
    return g


def load_workload(k: int, examples: Path = EXAMPLES) -> Workload:
    """The example image and grasps (tiled to k rows) if present, else the synthetic scene."""
    dpath, gpath = examples / "depth_example.npy", examples / "grasps_example.json"
    if dpath.is_file() and gpath.is_file():
        try:
            depth = np.load(dpath, allow_pickle=False).astype(np.float32)
            g = np.asarray(json.loads(gpath.read_text())["grasps"], np.float32).reshape(-1, 7)
            if depth.ndim == 2 and len(g):
                return Workload(depth, np.resize(g, (k, 7)), str(dpath.relative_to(ROOT)) if dpath.is_relative_to(ROOT) else str(dpath))
        except (OSError, ValueError, KeyError) as e:
            print(f"loadtest: cannot use {examples} ({e}); using the synthetic scene", file=sys.stderr)
    return Workload(synthetic_scene(), synthetic_grasps(k), "synthetic table + box")


class FreshImages:
    """Distinct depth images (a counter and a per-run salt in pixel (0, 0)), as .npy bytes."""

    def __init__(self, depth: np.ndarray, seed: int | None = None):
        self.depth = np.array(depth, np.float32)
        self.salt = np.random.default_rng(seed).uniform(0.5, 1.0)
        self.n = 0

    def next_array(self) -> np.ndarray:
        self.n += 1
        self.depth[0, 0] = np.float32(self.salt + (self.n % (1 << 20)) * 2.0**-22)
        self.depth[0, 1] = np.float32(0.5 + (self.n >> 20) * 2.0**-22)
        return self.depth

    def next_npy(self) -> bytes:
        return _npy_bytes(self.next_array())

    def next_npz(self, grasps: np.ndarray) -> bytes:
        return _npz_bytes(depth=self.next_array(), grasps=grasps)


def bad_requests(work: Workload) -> list[tuple[str, bytes, dict]]:
    """Malformed requests the service must answer with a 4xx naming the problem:
    (path, body, headers). NaN depth, truncated .npy, corrupt PNG, a zip-bomb .npz (40 MB of
    zeros declared, ~40 kB sent), malformed JSON, zero quaternion, an unknown image id."""
    npy_h, octet = {"content-type": "application/x-npy"}, {"content-type": OCTET}
    nan = np.array(work.depth, np.float32)
    nan[100:110, 100:110] = np.nan
    good = _npy_bytes(np.asarray(work.depth, np.float32))
    bomb = io.BytesIO()
    with zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as z:
        with z.open("depth.npy", "w") as f:
            np.save(f, np.zeros((5000, 2000), np.float32))
    zero_q = np.array(work.grasps[:4], "<f4")
    zero_q[1, 3:] = 0
    unknown = "/v1/images/" + "0" * 64 + "/scores"
    return [
        ("/v1/images", _npy_bytes(nan), npy_h),
        ("/v1/images", good[: len(good) // 2], npy_h),
        ("/v1/images", b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 4, {"content-type": "image/png"}),
        ("/v1/score", bomb.getvalue(), {"content-type": "application/x-npz"}),
        (unknown, b'{"grasps": [[1, 2,', {"content-type": "application/json"}),
        ("/v1/score", _npz_bytes(depth=np.asarray(work.depth, np.float32), grasps=zero_q), {"content-type": "application/x-npz"}),
        (unknown, np.ascontiguousarray(work.grasps, "<f4").tobytes(), octet),
    ]


def _npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


def _npz_bytes(**arrays: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


# ---- target and server memory ------------------------------------------------------------
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


def _children(pid: int) -> list[int]:
    out = []
    try:
        for tid in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{tid}/children") as f:
                out += [int(c) for c in f.read().split()]
    except OSError:
        pass
    return out


def server_rss_bytes(pid: int) -> dict:
    """Resident memory of ``pid`` and its descendants (bytes, from /proc; Linux)."""
    pids, seen, total, peak = [pid], set(), 0, 0
    while pids:
        p = pids.pop()
        if p in seen:
            continue
        seen.add(p)
        try:
            with open(f"/proc/{p}/status") as f:
                st = dict(line.split(":", 1) for line in f if ":" in line)
        except OSError:
            if p == pid:
                raise ValueError(f"no process with pid {pid} (or /proc not readable)") from None
            continue
        total += int(st.get("VmRSS", "0 kB").split()[0]) * 1024
        peak += int(st.get("VmHWM", "0 kB").split()[0]) * 1024
        pids += _children(p)
    return {"pids": sorted(seen), "rss_bytes": total, "peak_rss_bytes": peak}


def server_latency_totals(metrics_text: str) -> dict[str, tuple[float, float]]:
    """endpoint -> (sum of seconds, count) of ``vgq_request_seconds`` in a /metrics page."""
    out: dict[str, list[float]] = {}
    for line in metrics_text.splitlines():
        for suffix, i in (("_sum{", 0), ("_count{", 1)):
            head = "vgq_request_seconds" + suffix
            if line.startswith(head):
                labels, _, value = line[len(head):].rpartition("} ")
                ep = labels.partition('endpoint="')[2].partition('"')[0]
                out.setdefault(ep, [0.0, 0.0])[i] += float(value)
    return {k: (v[0], v[1]) for k, v in out.items()}


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


async def client_loop(http, work: Workload, mix: Mix, deadline: float, rec: Recorder, fresh: FreshImages) -> None:
    """One client: repeat the mix's cycle until ``deadline`` (perf_counter seconds)."""
    k = len(work.grasps)
    gbytes = np.ascontiguousarray(work.grasps, "<f4").tobytes()
    npy_h = {"content-type": "application/x-npy"}
    score_h = {"content-type": OCTET, "accept": OCTET}
    npz_h = {"content-type": "application/x-npz", "accept": OCTET}

    def scores_ok(r):
        return None if len(r.content) == 4 * k else f"answer of {len(r.content)} bytes, expected {4 * k}"

    def upload_ok(r):
        try:
            return None if r.json().get("image_id") else "no image_id in answer"
        except ValueError:
            return "answer is not JSON"

    def error_named(r):
        try:
            return None if r.json()["error"]["message"] else "4xx without a message"
        except (ValueError, KeyError, TypeError):
            return f"4xx answer is not an error object: {r.text[:80]}"

    bad, n_bad = bad_requests(work), 0

    while time.perf_counter() < deadline:
        image_id = None
        for _ in range(mix.upload):
            r = await _timed(rec, "upload", http.post("/v1/images", content=fresh.next_npy(), headers=npy_h), upload_ok)
            image_id = r.json()["image_id"] if r is not None else image_id
            if time.perf_counter() >= deadline:
                return
        for _ in range(mix.score if image_id else 0):
            r = await _timed(rec, "score", http.post(f"/v1/images/{image_id}/scores", content=gbytes, headers=score_h), scores_ok)
            if r is not None and rec.recording:
                rec.grasps += k
            if time.perf_counter() >= deadline:
                return
        for _ in range(mix.once):
            r = await _timed(rec, "score_once", http.post("/v1/score", content=fresh.next_npz(work.grasps), headers=npz_h), scores_ok)
            if r is not None and rec.recording:
                rec.grasps += k
            if time.perf_counter() >= deadline:
                return
        for _ in range(mix.bad):
            path, body, headers = bad[n_bad % len(bad)]
            n_bad += 1
            await _timed(rec, "bad", http.post(path, content=body, headers=headers), error_named, ok=lambda st: 400 <= st < 500)
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


async def run_load(url: str, clients: int, duration: float, work: Workload, mix: Mix, warmup: float = 1.0,
                   timeout: float = 10.0, seed: int | None = None, transport: str = "httpx") -> tuple[Recorder, float]:
    """Drive ``url`` with ``clients`` concurrent clients for ``warmup`` (not recorded) then
    ``duration`` seconds. ``transport``: ``httpx`` (one pooled AsyncClient, a connection per
    client) or ``raw`` (RawHTTP, one connection per client). Returns the recorder and the
    measured wall time (s)."""
    import httpx

    limits = httpx.Limits(max_connections=clients + 1, max_keepalive_connections=clients + 1)
    rec = Recorder()
    fresh = FreshImages(work.depth, seed)
    async with httpx.AsyncClient(base_url=url, timeout=timeout, limits=limits) as http:
        conns = [RawHTTP(url, timeout) for _ in range(clients)] if transport == "raw" else [http] * clients
        try:
            r = await http.get("/readyz")
            if r.status_code != 200:
                raise RuntimeError(f"{url}/readyz answered {r.status_code}: {r.text[:200]}")
            if warmup > 0:
                rec.recording = False
                end = time.perf_counter() + warmup
                await asyncio.gather(*(client_loop(c, work, mix, end, rec, fresh) for c in conns))
                rec.recording = True
            gc.collect()
            before = await _server_totals(http)
            gc.freeze()  # the client's own GC pauses would show up as server latency
            t0 = time.perf_counter()
            end = t0 + duration
            # every request is bounded by ``timeout``: the run ends by end + timeout at the latest
            await asyncio.wait_for(asyncio.gather(*(client_loop(c, work, mix, end, rec, fresh) for c in conns)),
                                   duration + timeout + 5)
            wall = time.perf_counter() - t0
            gc.unfreeze()
            after = await _server_totals(http)
        finally:
            for c in conns:
                if isinstance(c, RawHTTP):
                    await c.aclose()
    if before is not None and after is not None:
        for ep in ENDPOINTS:
            (s0, n0), (s1, n1) = before.get(ep, (0.0, 0.0)), after.get(ep, (0.0, 0.0))
            rec.server_mean_ms[ep] = (s1 - s0) / (n1 - n0) * 1e3 if n1 > n0 else None
    return rec, wall


# ---- report ---------------------------------------------------------------------------------
def summarize(rec: Recorder, wall: float) -> dict:
    eps = {}
    for e in ENDPOINTS:
        if e == "bad" and not (rec.latencies[e] or rec.errors[e]):
            continue  # no bad requests in this mix
        lat = np.asarray(rec.latencies[e]) * 1e3
        n = len(lat)
        eps[e] = {"requests": n, "errors": rec.errors[e], "per_s": n / wall if wall > 0 else 0.0,
                  **({f"p{q}_ms": float(np.percentile(lat, q)) for q in (50, 90, 99)} if n else
                     {"p50_ms": None, "p90_ms": None, "p99_ms": None}),
                  "max_ms": float(lat.max()) if n else None, "server_mean_ms": rec.server_mean_ms.get(e)}
    total = sum(v["requests"] for v in eps.values())
    return {"endpoints": eps, "requests": total, "errors": sum(rec.errors.values()), "error_messages": rec.messages,
            "wall_s": wall, "requests_per_s": total / wall if wall > 0 else 0.0,
            "grasps_per_s": rec.grasps / wall if wall > 0 else 0.0}


def table(report: dict) -> str:
    def f(x):
        return "-" if x is None else f"{x:.2f}"

    c = report["config"]
    lines = [f"{c['clients']} client(s) ({c['transport']}), {report['wall_s']:.1f} s, k = {c['k']}, mix {c['mix']}, image: {c['workload']}",
             "", "| endpoint | requests | errors | req/s | p50 ms | p90 ms | p99 ms | max ms | server mean ms |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for e, v in report["endpoints"].items():
        lines.append(f"| {e} | {v['requests']} | {v['errors']} | {v['per_s']:.1f} | {f(v['p50_ms'])} | {f(v['p90_ms'])} | "
                     f"{f(v['p99_ms'])} | {f(v['max_ms'])} | {f(v['server_mean_ms'])} |")
    lines += ["", f"total: {report['requests']} requests ({report['requests_per_s']:.0f}/s), "
                  f"{report['grasps_per_s']:.0f} grasps/s, {report['errors']} errors"]
    for msg, n in list(report["error_messages"].items())[:5]:
        lines.append(f"  error x{n}: {msg}")
    if "server_rss" in report:
        b, a = report["server_rss"]["before"], report["server_rss"]["after"]
        lines.append(f"server RSS (pids {a['pids']}): {b['rss_bytes'] / 2**20:.1f} MiB before, {a['rss_bytes'] / 2**20:.1f} MiB after "
                     f"(peak {a['peak_rss_bytes'] / 2**20:.1f} MiB)")
    return "\n".join(lines)


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(prog="python -m service.loadtest", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--url", default="http://127.0.0.1:8000", help="service base URL (loopback only unless --allow-remote)")
    p.add_argument("--clients", type=int, default=8, help="concurrent clients, one connection each (default 8)")
    p.add_argument("--duration", type=float, default=10.0, help="measured seconds (default 10)")
    p.add_argument("--warmup", type=float, default=1.0, help="seconds of unrecorded load first (default 1)")
    p.add_argument("--k", type=int, default=128, help="grasps per score call (default 128)")
    p.add_argument("--mix", default="upload=1,score=8,once=1", help="requests per client cycle (default upload=1,score=8,once=1)")
    p.add_argument("--timeout", type=float, default=10.0, help="per-request timeout, seconds (default 10)")
    p.add_argument("--server-pid", type=int, help="record this process's (and its children's) RSS before and after")
    p.add_argument("--json", help="also write the report as JSON to this file")
    p.add_argument("--allow-remote", action="store_true", help="allow a non-loopback --url")
    p.add_argument("--seed", type=int, help="seed of the fresh-image salt (default: random)")
    p.add_argument("--transport", choices=("auto", "httpx", "raw"), default="auto",
                   help="HTTP client: httpx, or raw (minimal keep-alive HTTP/1.1, least client overhead); "
                        "auto = raw for --clients 1 over http, else httpx")
    a = p.parse_args(argv)
    if a.clients < 1 or a.k < 1 or not a.duration > 0 or a.warmup < 0 or not a.timeout > 0:
        p.error("--clients and --k must be >= 1, --duration and --timeout > 0, --warmup >= 0")
    if a.duration > 24 * 3600:
        p.error("--duration is limited to 24 h")
    try:
        url = check_target(a.url, a.allow_remote)
        mix = Mix.parse(a.mix)
        before = server_rss_bytes(a.server_pid) if a.server_pid else None
    except ValueError as e:
        p.error(str(e))
    transport = a.transport
    if transport == "auto":
        transport = "raw" if a.clients == 1 and url.startswith("http://") else "httpx"
    if transport == "raw" and not url.startswith("http://"):
        p.error("--transport raw speaks plain http only")
    work = load_workload(a.k)
    try:
        rec, wall = asyncio.run(run_load(url, a.clients, a.duration, work, mix, a.warmup, a.timeout, a.seed, transport))
    except (RuntimeError, OSError, asyncio.TimeoutError) as e:
        print(f"loadtest: {type(e).__name__}: {e}", file=sys.stderr)
        sys.exit(1)
    except Exception as e:  # httpx connection errors on /readyz
        print(f"loadtest: cannot reach {url}: {type(e).__name__}: {e}", file=sys.stderr)
        sys.exit(1)
    report = summarize(rec, wall)
    report["config"] = {"url": url, "clients": a.clients, "transport": transport, "duration_s": a.duration, "warmup_s": a.warmup, "k": a.k,
                        "mix": asdict(mix), "workload": work.source, "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
                        "load_average": list(os.getloadavg()), "cpu_count": os.cpu_count()}
    if a.server_pid:
        try:
            report["server_rss"] = {"before": before, "after": server_rss_bytes(a.server_pid)}
        except ValueError as e:
            report["server_rss_error"] = str(e)
    print(table(report))
    if a.json:
        Path(a.json).write_text(json.dumps(report, indent=2) + "\n")
    return report


if __name__ == "__main__":
    main()
