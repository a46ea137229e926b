"""The Redis cache backend against a real redis-server on a loopback port: replicas share
images (upload on A, score or plan on B), and the service degrades (404, local uploads, metrics,
logs) when Redis goes away."""

from __future__ import annotations

import logging
import shutil
import subprocess
import time
from contextlib import contextmanager

import httpx
import numpy as np
import pytest
from conftest import skip_or_fail_in_ci, table_scene
from servers import free_port, grasps_at, running_service

from service.cache import CachedImage, EncodedWindow
from service.client import ServiceClient, ServiceError
from vgq.camera import Intrinsics


@pytest.fixture(scope="module", autouse=True)
def _redis_server_installed():
    """Skipped without redis-server, except in CI (CI=true), where a missing server fails."""
    if shutil.which("redis-server") is None:
        skip_or_fail_in_ci("redis-server not installed (apt-get install -y redis-server)")


@contextmanager
def redis_server(port: int | None = None):
    """A throw-away redis-server on 127.0.0.1 (no persistence, 64 MB, allkeys-lru); yields (url, process)."""
    import redis

    port = port or free_port()
    proc = subprocess.Popen(
        [
            "redis-server",
            "--port",
            str(port),
            "--bind",
            "127.0.0.1",
            "--save",
            "",
            "--appendonly",
            "no",
            "--maxmemory",
            "64mb",
            "--maxmemory-policy",
            "allkeys-lru",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    url = f"redis://127.0.0.1:{port}/0"
    try:
        deadline = time.monotonic() + 10
        while True:
            try:
                if redis.Redis.from_url(url, socket_timeout=0.2).ping():
                    break
            except redis.ConnectionError:
                if time.monotonic() > deadline or proc.poll() is not None:
                    raise RuntimeError("redis-server did not start") from None
                time.sleep(0.05)
        yield url, proc
    finally:
        stop(proc)


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.kill()
        proc.wait(5)


def redis_env(url: str) -> dict:
    return {"VGQ_CACHE_BACKEND": "redis", "VGQ_REDIS_URL": url}


def metric(base: str, name: str) -> float:
    for line in httpx.get(f"{base}/metrics").text.splitlines():
        if line.startswith(name + " "):
            return float(line.split()[1])
    raise AssertionError(f"{name} not in /metrics")


@pytest.fixture(scope="module")
def shared(model_dir):
    """Redis + two service processes A and B sharing it."""
    with (
        redis_server() as (rurl, _),
        running_service(model_dir, env=redis_env(rurl)) as a,
        running_service(model_dir, env=redis_env(rurl)) as b,
    ):
        yield rurl, a, b


def test_image_uploaded_on_a_is_scored_on_b(shared):
    _, a, b = shared
    depth, g = table_scene() + 0.004, grasps_at()
    with ServiceClient(a) as ca, ServiceClient(b) as cb:
        iid = ca.upload(depth)
        p_a = ca.score(iid, g)
        fetched = httpx.get(f"{b}/v1/cache").json()["windows_fetched"]
        assert np.allclose(cb.score_details(iid, g)["p_success"], p_a, atol=1e-6)
    stats = httpx.get(f"{b}/v1/cache").json()
    assert stats["hits"] >= 1 and stats["windows_fetched"] == fetched + 1  # A's window read, not encoded again


def test_two_workers_serve_an_upload_on_any_connection(model_dir):
    """``--workers 2`` (which needs the Redis cache): an image uploaded through one connection is
    scored through fresh connections, whichever worker accepts them."""
    with redis_server() as (rurl, _), running_service(model_dir, "--workers", "2", env=redis_env(rurl)) as url:
        # /readyz answered once: a worker still loading accepts no connection (no 503 from it)
        codes = [httpx.get(f"{url}/readyz").status_code for _ in range(10)]
        for i in range(6):
            with ServiceClient(url) as c:
                iid = c.upload(table_scene() + 0.001 * i)
            for _ in range(4):
                with httpx.Client(base_url=url) as fresh:  # a new connection each time
                    r = fresh.post(f"/v1/images/{iid}/scores", json={"grasps": grasps_at(k=2).tolist()})
                codes.append(r.status_code)
        assert codes == [200] * 34, (codes, r.text)


def test_one_shot_on_a_fills_the_cache_of_b(shared):
    _, a, b = shared
    depth, g = table_scene() + 0.005, grasps_at(k=4)
    with ServiceClient(a) as ca, ServiceClient(b) as cb:
        p = ca.score_once(depth, g)
        up = httpx.post(f"{b}/v1/images", content=cb._npy(depth), headers={"content-type": "application/x-npy"}).json()
        assert up["cached"] is True
        assert np.allclose(cb.score(up["image_id"], g), p, atol=1e-6)


def test_image_uploaded_on_a_is_planned_on_b_with_the_windows_a_encoded(shared):
    pytest.importorskip("trimesh")
    from tests.planning_scenes import boxes_scene

    _, a, b = shared
    depth = boxes_scene()[0]
    with ServiceClient(a, timeout=60) as ca, ServiceClient(b, timeout=60) as cb:
        iid = ca.upload(depth)
        on_a = ca.plan(image_id=iid, k=3, seed=3)
        fetched = httpx.get(f"{b}/v1/cache").json()["windows_fetched"]
        on_b = cb.plan(image_id=iid, k=3, seed=3)
    assert on_a.grasps and on_b.grasps == on_a.grasps
    n = on_b.answer["counts"]["windows"]
    assert on_a.answer["counts"]["windows_reused"] == 0 and on_b.answer["counts"]["windows_reused"] == n
    assert httpx.get(f"{b}/v1/cache").json()["windows_fetched"] == fetched + n  # read from Redis, not encoded


def test_entries_are_bytes_with_a_ttl(shared):
    import redis

    rurl, a, _ = shared
    with ServiceClient(a) as ca:
        iid = ca.upload(table_scene() + 0.006)
    r = redis.Redis.from_url(rurl)
    key = f"vgq:img:{iid}"
    assert 0 < r.pttl(key) <= 86400 * 1000
    assert 1000 < r.strlen(key) < 300 * 300 * 4  # the depth image, compressed, + its camera
    with ServiceClient(a) as ca:
        ca.score(iid, grasps_at(k=2))
    (wkey,) = r.keys(f"{key}:w:*")
    assert 0 < r.pttl(wkey) <= 86400 * 1000
    assert 4096 < r.strlen(wkey) < 4200  # 1024 float32 + a small header
    assert metric(a, "vgq_cache_backend_errors_total") == 0


def test_service_degrades_when_redis_goes_away_and_recovers(model_dir):
    import redis

    from service.redis_cache import RedisCache

    with redis_server() as (rurl, rproc), running_service(model_dir, env=redis_env(rurl)) as s, ServiceClient(s) as c:
        held = c.upload(table_scene() + 0.007)  # in S's local LRU and in Redis
        other = RedisCache(rurl, 8, 1 << 20)  # another replica's upload: in Redis only
        other_id = "f" * 32
        other.put(other_id, entry(h=300, w=300))
        assert len(c.score(other_id, grasps_at(k=2))) == 2

        stop(rproc)
        other_id2 = "e" * 32
        with pytest.raises(ServiceError) as e:
            c.score(other_id2, grasps_at(k=2))
        assert e.value.status == 404 and "upload" in e.value.message
        assert len(c.score(held, grasps_at(k=2))) == 2  # still held locally
        fresh = c.upload(table_scene() + 0.008)  # encoded and cached locally
        assert len(c.score(fresh, grasps_at(k=2))) == 2
        assert metric(s, "vgq_cache_backend_errors_total") >= 1
        stats = httpx.get(f"{s}/v1/cache").json()
        assert stats["available"] is False and stats["errors"] >= 1
        assert httpx.get(f"{s}/readyz").status_code == 200

        port = int(rurl.rsplit(":", 1)[1].split("/")[0])
        with redis_server(port) as (rurl2, _):
            time.sleep(1.1)  # the service retries Redis at most once a second while it is down
            iid = c.upload(table_scene() + 0.009)
            assert redis.Redis.from_url(rurl2).exists(f"vgq:img:{iid}")
            assert httpx.get(f"{s}/v1/cache").json()["available"] is True


# ---- RedisCache in-process, on a real server ---------------------------------------------------------------------------
@pytest.fixture()
def rurl():
    with redis_server() as (url, proc):
        yield url, proc


def entry(seed=0, h=40, w=48) -> CachedImage:
    """A small image entry (H x W px at the model's focal length) with one encoded window."""
    rng = np.random.default_rng(seed)
    cam = Intrinsics(cx=(w - 1) / 2, cy=(h - 1) / 2, width=w, height=h)
    e = CachedImage(rng.uniform(0.5, 0.8, (h, w)).astype(np.float32), cam, cam, ("fx", "fy", "cx", "cy"))
    e.windows[(-24, -28)] = EncodedWindow(rng.standard_normal((1, 1024)).astype(np.float32), 0.0)
    return e


class ListHandler(logging.Handler):
    def __init__(self):
        super().__init__()
        self.records: list[logging.LogRecord] = []

    def emit(self, record):
        self.records.append(record)


def test_two_replicas_share_entries_and_count_hits(rurl):
    from service.redis_cache import RedisCache

    a, b = RedisCache(rurl[0], 8, 1 << 20), RedisCache(rurl[0], 8, 1 << 20)
    e = entry()
    a.put("k1", e)
    got = b.get("k1")
    assert np.array_equal(got.depth, e.depth) and got.camera == e.camera and got.image_shape == (40, 48)
    assert got.windows == {}  # windows are read when a grasp needs them
    b.fetch_windows("k1", got, [(-24, -28), (48, -28)])
    assert list(got.windows) == [(-24, -28)] and np.array_equal(
        got.windows[(-24, -28)].term, e.windows[(-24, -28)].term
    )
    assert b.stats()["windows_fetched"] == 1 and b.stats()["windows_encoded"] == 0
    assert b.get("nope") is None
    assert (b.stats()["hits"], b.stats()["misses"], b.stats()["errors"]) == (1, 1, 0)
    assert len(b) == 1  # the hit is now held in b's local LRU


def test_windows_reach_redis_once_each_whether_encoded_before_or_after_the_put(rurl):
    import redis

    from service.redis_cache import RedisCache, window_key

    c, r = RedisCache(rurl[0], 8, 1 << 20), redis.Redis.from_url(rurl[0])
    e = entry()
    first = {(-24, -28): e.windows.pop((-24, -28))}
    writes = []
    put_windows = c._put_windows
    c._put_windows = lambda key, windows: (writes.append(sorted(windows)), put_windows(key, windows))
    c.add_windows("k", e, first)  # encoded before the entry is put (a one-shot's, beside its analysis)
    assert writes == [] and not r.exists(window_key(c.prefix, "k", (-24, -28)))
    c.put("k", e)  # the entry with its windows
    later = {(0, 0): EncodedWindow(np.ones((1, 1024), np.float32), 0.0)}
    c.add_windows("k", e, later)  # encoded for an entry the cache holds: shared at once
    assert writes == [[(-24, -28)], [(0, 0)]]
    assert r.exists(window_key(c.prefix, "k", (-24, -28))) and r.exists(window_key(c.prefix, "k", (0, 0)))
    assert c.stats()["windows_encoded"] == 2


def test_local_lru_is_bounded_but_redis_still_serves(rurl):
    from service.redis_cache import RedisCache

    c = RedisCache(rurl[0], 2, 1 << 20)
    for i in range(3):
        c.put(f"k{i}", entry(i))
    assert len(c) == 2 and c.stats()["evictions"] == 1
    assert c.get("k0") is not None  # evicted locally, fetched back from Redis


def test_corrupt_redis_value_is_a_miss(rurl):
    import redis

    from service.redis_cache import RedisCache

    redis.Redis.from_url(rurl[0]).set("vgq:img:bad", b"not an entry")
    c = RedisCache(rurl[0], 8, 1 << 20)
    assert c.get("bad") is None and c.stats()["misses"] == 1


def test_outage_is_counted_logged_once_and_does_not_stall(rurl):
    from service.redis_cache import RedisCache

    url, proc = rurl
    log = logging.getLogger("test.redis_cache")
    h = ListHandler()
    log.addHandler(h)
    c = RedisCache(url, 64, 1 << 20, log, retry_s=30)
    c.put("k", entry())
    stop(proc)
    t0 = time.perf_counter()
    assert c.get("other") is None
    for i in range(50):
        c.put(f"x{i}", entry(i))  # local only, no waiting on a dead server
    assert time.perf_counter() - t0 < 2.0
    assert c.get("k") is not None and c.get("x3") is not None
    assert c.stats()["errors"] == 1 and c.stats()["available"] is False
    msgs = [r.getMessage() for r in h.records]
    assert msgs == [
        "redis cache unavailable: serving from the local cache only; ids not held here answer 404 (upload again)"
    ]
    log.removeHandler(h)


def test_unreachable_at_start_is_not_fatal():
    from service.redis_cache import RedisCache

    c = RedisCache(f"redis://127.0.0.1:{free_port()}/0", 8, 1 << 20, timeout_s=0.2)
    c.put("k", entry())
    assert c.get("k") is not None and c.get("z") is None
    assert c.errors >= 1
