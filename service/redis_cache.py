"""Redis cache backend: encoded images shared by every replica (workers, containers).

An id uploaded to one replica can be scored on any other. Entries are immutable (the id is
a content address of the bytes, crop parameters and model version), so a small in-process
LRU (``MemoryCache``, bounded by ``max_entries`` / ``max_bytes``) sits in front of Redis
with no invalidation needed. Redis holds one string per image, ``<prefix><id>`` ->
``pack_entry`` bytes (about 4.1 kB), written with a TTL that each hit renews (GETEX), so
idle images expire; give the Redis server a ``maxmemory`` and ``maxmemory-policy
allkeys-lru`` (or volatile-lru) and it evicts the least recently used images under pressure.

If Redis is unreachable the service keeps answering: ``get`` falls back to the local LRU
(an id it lacks is a miss -> 404, upload again), ``put`` stores locally only. Each failure
counts in ``errors`` (``vgq_cache_backend_errors``); the first failure and the recovery are
logged; while Redis is down it is retried at most every ``retry_s`` seconds, so requests do
not each wait for a connection timeout.
"""

from __future__ import annotations

import logging
import struct
import threading
import time
from urllib.parse import urlsplit, urlunsplit

import numpy as np

from . import logs
from .cache import CachedImage, MemoryCache

MAGIC = b"VGQ2"
_HEADER = struct.Struct("<4sIIdddI")  # magic, H, W, window centre u, v (px), missing fraction, n float32 values
KEY_PREFIX = "vgq:img:"


def pack_entry(entry: CachedImage) -> bytes:
    """Bytes of a cache entry: header (image shape, window centre) + little-endian float32 image term."""
    term = np.ascontiguousarray(entry.image_term, dtype="<f4").reshape(-1)
    h, w = entry.image_shape
    c = entry.window_center
    return _HEADER.pack(MAGIC, int(h), int(w), float(c[0]), float(c[1]), float(entry.missing_fraction), term.size) + term.tobytes()


def unpack_entry(data: bytes) -> CachedImage:
    """Inverse of ``pack_entry``; raises ValueError for bytes that are not an entry."""
    if len(data) < _HEADER.size:
        raise ValueError(f"cache entry of {len(data)} bytes is shorter than its header")
    magic, h, w, cu, cv, missing, n = _HEADER.unpack_from(data)
    if magic != MAGIC or len(data) != _HEADER.size + 4 * n:
        raise ValueError("cache entry has a wrong magic or length")
    term = np.frombuffer(data, dtype="<f4", count=n, offset=_HEADER.size).astype(np.float32).reshape(1, n)
    return CachedImage(term, np.array([cu, cv], dtype=np.float64), (h, w), missing)


def redacted(url: str) -> str:
    """The URL without its password (for logs and stats)."""
    p = urlsplit(url)
    if p.password is None:
        return url
    netloc = f"{p.username or ''}:***@{p.hostname}" + (f":{p.port}" if p.port else "")
    return urlunsplit((p.scheme, netloc, p.path, p.query, p.fragment))


class RedisCache:
    """Two-level cache: in-process LRU in front of a shared Redis. Same interface as MemoryCache."""

    backend = "redis"

    def __init__(self, url: str, max_entries: int, max_bytes: int, log: logging.Logger | None = None, *,
                 ttl_s: float = 24 * 3600, timeout_s: float = 0.5, retry_s: float = 1.0, prefix: str = KEY_PREFIX):
        import redis  # the [service] extra; imported here so the memory backend never needs it
        from redis.backoff import NoBackoff
        from redis.retry import Retry

        self.url = url
        self.ttl_ms = max(1, int(ttl_s * 1000))
        self.retry_s = retry_s
        self.prefix = prefix
        self.log = log or logging.getLogger("vgq.service")
        self.local = MemoryCache(max_entries, max_bytes)
        self.redis = redis.Redis.from_url(url, socket_timeout=timeout_s, socket_connect_timeout=timeout_s,
                                          health_check_interval=30, retry=Retry(NoBackoff(), 1))  # 1 quick reconnect
        self._redis_errors = (redis.RedisError, OSError)
        self._lock = threading.Lock()
        self.hits = self.misses = self.errors = 0
        self.available = True
        self._down_until = 0.0

    # ---- the MemoryCache interface -------------------------------------------------------------------
    @property
    def max_entries(self) -> int:
        return self.local.max_entries

    @property
    def max_bytes(self) -> int:
        return self.local.max_bytes

    @property
    def evictions(self) -> int:
        return self.local.evictions

    def get(self, key: str) -> CachedImage | None:
        e = self.local.get(key)
        if e is None:
            data = self._call("get", self.redis.getex, self.prefix + key, px=self.ttl_ms)
            if data is not None:
                try:
                    e = unpack_entry(data)
                except ValueError as err:
                    logs.event(self.log, "cache entry in redis is corrupt; treated as a miss", logging.WARNING,
                               key=key, error=str(err))
                else:
                    self.local.put(key, e)
        with self._lock:
            if e is None:
                self.misses += 1
            else:
                self.hits += 1
        return e

    def put(self, key: str, entry: CachedImage) -> None:
        self.local.put(key, entry)
        self._call("put", self.redis.set, self.prefix + key, pack_entry(entry), px=self.ttl_ms)

    def __len__(self) -> int:
        return len(self.local)

    def stats(self) -> dict:
        s = self.local.stats()
        s.update(backend=self.backend, hits=self.hits, misses=self.misses, errors=self.errors, available=self.available,
                 redis_url=redacted(self.url), ttl_s=self.ttl_ms / 1000)
        return s

    # ---- Redis calls that never raise ---------------------------------------------------------------------
    def _call(self, op: str, fn, *args, **kw):
        """``fn(*args, **kw)`` on Redis; None (and an error counted and logged) if Redis fails.
        While Redis is down, calls are skipped until ``retry_s`` has passed since the last failure."""
        if not self.available and time.monotonic() < self._down_until:
            return None
        try:
            out = fn(*args, **kw)
        except self._redis_errors as e:
            with self._lock:
                self.errors += 1
                was_up, self.available = self.available, False
                self._down_until = time.monotonic() + self.retry_s
            if was_up:
                logs.event(self.log, "redis cache unavailable: serving from the local cache only; ids not held here "
                                     "answer 404 (upload again)", logging.ERROR, op=op, redis_url=redacted(self.url),
                           error=repr(e))
            return None
        if not self.available:
            with self._lock:
                self.available = True
            logs.event(self.log, "redis cache available again", logging.WARNING, redis_url=redacted(self.url))
        return out
