"""Redis cache backend: encoded images shared by every replica (workers, containers).

An id uploaded to one replica can be scored on any other. Entries are immutable (the id is
a content address of the bytes, crop parameters and model version), so a small in-process
LRU (``MemoryCache``, bounded by ``max_entries`` / ``max_bytes``) sits in front of Redis
with no invalidation needed. Redis holds one string per image, ``<prefix><id>`` ->
``pack_entry`` bytes (the depth image at the model's focal length, zlib-compressed, and its
camera; for a placement model also the upload's placement analysis, its region map
zlib-compressed after the depth), and one string per encoded window, ``<prefix><id>:w:<ou>,<ov>`` -> ``pack_window``
bytes (about 4.1 kB), each written with a TTL that each hit renews (GETEX), so idle images
expire; a window another replica encoded is read, not encoded again; give the Redis server a ``maxmemory`` and ``maxmemory-policy
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
import zlib
from urllib.parse import urlsplit, urlunsplit

import numpy as np
import orjson

from planning.placement import ImagePlacement
from vgq.camera import Intrinsics

from . import logs
from .cache import CachedImage, EncodedWindow, MemoryCache

MAGIC = b"VGQ3"
_HEADER = struct.Struct("<4sI")  # magic, length of the JSON metadata that follows; then zlib(float32 depth)
_WINDOW = struct.Struct("<4sdI")  # magic, missing fraction, n float32 values
WINDOW_MAGIC = b"VGW1"
KEY_PREFIX = "vgq:img:"


def window_key(prefix: str, key: str, origin) -> str:
    """Redis key of one window's encoder term: ``<prefix><id>:w:<ou>,<ov>``."""
    return f"{prefix}{key}:w:{int(origin[0])},{int(origin[1])}"


def _pack_placement(p: ImagePlacement) -> tuple[dict, bytes]:
    """(JSON metadata, zlib-compressed region map or b"") of a placement analysis; its ``intr`` is
    the entry's camera (not stored again)."""
    meta = {
        "normal": None if p.normal is None else [float(x) for x in p.normal],
        "offset": float(p.offset),
        "centres": None if p.centres is None else np.asarray(p.centres, np.float64).tolist(),
        "tops": None if p.tops is None else np.asarray(p.tops, np.float64).tolist(),
    }
    if p.region is None:
        return meta, b""
    region = np.ascontiguousarray(p.region)
    meta["region"] = {"shape": list(region.shape), "dtype": region.dtype.newbyteorder("<").str}
    return meta, zlib.compress(region.astype(meta["region"]["dtype"], copy=False).tobytes(), 1)


def _unpack_placement(meta: dict, camera: Intrinsics, blob: bytes) -> ImagePlacement:
    r = meta.get("region")
    region = None
    if r is not None:
        h, w = (int(x) for x in r["shape"])
        dtype = np.dtype(r["dtype"])
        if dtype.kind not in "iu":
            raise ValueError(f"placement region map of type {dtype}")
        raw = zlib.decompress(blob)
        if len(raw) != dtype.itemsize * h * w:
            raise ValueError("placement region map has a wrong length")
        region = np.frombuffer(raw, dtype=dtype).astype(dtype.newbyteorder("="), copy=True).reshape(h, w)

    def arr(name):
        return None if meta[name] is None else np.asarray(meta[name], np.float64)

    return ImagePlacement(camera, arr("normal"), float(meta["offset"]), region, arr("centres"), arr("tops"))


def pack_entry(entry: CachedImage) -> bytes:
    """Bytes of an image entry (without its windows): JSON metadata (shape, intrinsics, window
    mode, a placement model's placement analysis) + the zlib-compressed little-endian float32
    depth image at the model's focal length (+ the analysis's zlib-compressed region map)."""
    meta = {
        "shape": list(entry.depth.shape),
        "camera": entry.camera.to_dict(),
        "resampled": entry.resampled.to_dict(),
        "assumed": list(entry.assumed),
        "fixed_center": None if entry.fixed_center is None else [float(x) for x in entry.fixed_center],
        "up": None if entry.up is None else list(entry.up),
        "roll": entry.roll,
        "up_from": entry.up_from,
    }
    region = b""
    if entry.placement is not None:
        meta["placement"], region = _pack_placement(entry.placement)
    m = orjson.dumps(meta)
    depth = zlib.compress(np.ascontiguousarray(entry.depth, dtype="<f4").tobytes(), 1)
    return _HEADER.pack(MAGIC, len(m)) + m + depth + region


def unpack_entry(data: bytes) -> CachedImage:
    """Inverse of ``pack_entry``; raises ValueError for bytes that are not an entry."""
    if len(data) < _HEADER.size:
        raise ValueError(f"cache entry of {len(data)} bytes is shorter than its header")
    magic, n = _HEADER.unpack_from(data)
    if magic != MAGIC or len(data) < _HEADER.size + n:
        raise ValueError("cache entry has a wrong magic or length")
    try:
        meta = orjson.loads(data[_HEADER.size : _HEADER.size + n])
        h, w = (int(x) for x in meta["shape"])
        z = zlib.decompressobj()
        raw = z.decompress(data[_HEADER.size + n :])
        if len(raw) != 4 * h * w or not z.eof:
            raise ValueError("depth has a wrong length")
        depth = np.frombuffer(raw, dtype="<f4").astype(np.float32).reshape(h, w)
        fc = meta["fixed_center"]
        camera = Intrinsics.from_dict(meta["camera"])
        placement = None
        if meta.get("placement") is not None:  # after the depth: the region map, when the image has one
            placement = _unpack_placement(meta["placement"], camera, z.unused_data)
        elif z.unused_data:
            raise ValueError("bytes after the depth image")
        return CachedImage(
            depth,
            camera,
            Intrinsics.from_dict(meta["resampled"]),
            tuple(meta["assumed"]),
            None if fc is None else np.array(fc, dtype=np.float64),
            None if meta.get("up") is None else tuple(float(x) for x in meta["up"]),
            float(meta.get("roll", 0.0)),  # entries of replicas that predate the up direction: level
            meta.get("up_from", None if meta.get("up") is None else "client"),
            placement=placement,
        )
    except (orjson.JSONDecodeError, zlib.error, KeyError, TypeError) as e:
        raise ValueError(f"cache entry is corrupt: {e}") from None


def pack_window(win: EncodedWindow) -> bytes:
    term = np.ascontiguousarray(win.term, dtype="<f4").reshape(-1)
    return _WINDOW.pack(WINDOW_MAGIC, float(win.missing_fraction), term.size) + term.tobytes()


def unpack_window(data: bytes) -> EncodedWindow:
    if len(data) < _WINDOW.size:
        raise ValueError(f"window entry of {len(data)} bytes is shorter than its header")
    magic, missing, n = _WINDOW.unpack_from(data)
    if magic != WINDOW_MAGIC or len(data) != _WINDOW.size + 4 * n:
        raise ValueError("window entry has a wrong magic or length")
    term = np.frombuffer(data, dtype="<f4", count=n, offset=_WINDOW.size).astype(np.float32).reshape(1, n)
    return EncodedWindow(term, missing)


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

    def __init__(
        self,
        url: str,
        max_entries: int,
        max_bytes: int,
        log: logging.Logger | None = None,
        *,
        ttl_s: float = 24 * 3600,
        timeout_s: float = 0.5,
        retry_s: float = 1.0,
        prefix: str = KEY_PREFIX,
    ):
        import redis  # the [service] extra; imported here so the memory backend never needs it
        from redis.backoff import NoBackoff
        from redis.retry import Retry

        self.url = url
        self.ttl_ms = max(1, int(ttl_s * 1000))
        self.retry_s = retry_s
        self.prefix = prefix
        self.log = log or logging.getLogger("vgq.service")
        self.local = MemoryCache(max_entries, max_bytes)
        self.redis = redis.Redis.from_url(
            url,
            socket_timeout=timeout_s,
            socket_connect_timeout=timeout_s,
            health_check_interval=30,
            retry=Retry(NoBackoff(), 1),
        )  # 1 quick reconnect
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
                    logs.event(
                        self.log,
                        "cache entry in redis is corrupt; treated as a miss",
                        logging.WARNING,
                        key=key,
                        error=str(err),
                    )
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
        if entry.windows:
            self._put_windows(key, entry.windows)

    def fetch_windows(self, key: str, entry: CachedImage, origins) -> None:
        """Windows of ``entry`` another replica encoded: read from Redis into ``entry`` (TTL renewed)."""
        want = [o for o in origins if o not in entry.windows]
        if not want:
            return
        pipe = self.redis.pipeline(transaction=False)
        for o in want:
            pipe.getex(window_key(self.prefix, key, o), px=self.ttl_ms)
        got = self._call("fetch windows", pipe.execute) or [None] * len(want)
        found = {}
        for o, data in zip(want, got):
            if data is None:
                continue
            try:
                found[o] = unpack_window(data)
            except ValueError as err:
                logs.event(
                    self.log,
                    "window entry in redis is corrupt; encoded again",
                    logging.WARNING,
                    key=key,
                    error=str(err),
                )
        if found:
            self.local.add_windows(key, entry, found)
            with self._lock:
                self.local.windows_encoded -= len(found)  # fetched, not encoded here
                self.local.windows_fetched += len(found)

    def add_windows(self, key: str, entry: CachedImage, new: dict) -> None:
        """As :meth:`MemoryCache.add_windows`; shared through Redis for an entry this cache holds. An
        entry not put yet (a one-shot's, its windows encoded beside its analysis) is written with its
        windows by :meth:`put`: each window once."""
        self.local.add_windows(key, entry, new)
        if key in self.local:
            self._put_windows(key, new)

    def _put_windows(self, key: str, windows: dict) -> None:
        pipe = self.redis.pipeline(transaction=False)
        for o, win in windows.items():
            pipe.set(window_key(self.prefix, key, o), pack_window(win), px=self.ttl_ms)
        self._call("put windows", pipe.execute)

    def __len__(self) -> int:
        return len(self.local)

    def stats(self) -> dict:
        s = self.local.stats()
        s.update(
            backend=self.backend,
            hits=self.hits,
            misses=self.misses,
            errors=self.errors,
            available=self.available,
            redis_url=redacted(self.url),
            ttl_s=self.ttl_ms / 1000,
        )
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
                logs.event(
                    self.log,
                    "redis cache unavailable: serving from the local cache only; ids not held here "
                    "answer 404 (upload again)",
                    logging.ERROR,
                    op=op,
                    redis_url=redacted(self.url),
                    error=repr(e),
                )
            return None
        if not self.available:
            with self._lock:
                self.available = True
            logs.event(self.log, "redis cache available again", logging.WARNING, redis_url=redacted(self.url))
        return out
