"""Cache of encoded images: id -> encoder output (+ the window it was cropped from).

``MemoryCache`` is a bounded LRU (entries and bytes) for one process. The Redis backend
(``service.redis_cache``) shares entries between replicas. Both count hits, misses and
evictions.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

ENTRY_OVERHEAD_BYTES = 256  # key, object headers, window centre


@dataclass(frozen=True)
class CachedImage:
    image_term: np.ndarray  # (1, 1024) float32 encoder output
    window_center: np.ndarray  # (2,) float64, image px (u, v)
    image_shape: tuple[int, int]  # (H, W)
    missing_fraction: float = 0.0  # fraction of the crop window without a depth reading (filled)

    @property
    def nbytes(self) -> int:
        return int(self.image_term.nbytes) + ENTRY_OVERHEAD_BYTES


def image_id(body: bytes, params: str, model_version: str) -> str:
    """Content address of an upload: hash of model version, crop parameters and bytes."""
    h = hashlib.sha256()
    h.update(model_version.encode())
    h.update(b"\0")
    h.update(params.encode())
    h.update(b"\0")
    h.update(body)
    return h.hexdigest()[:32]


class MemoryCache:
    """Thread-safe LRU bounded by entry count and bytes."""

    backend = "memory"

    def __init__(self, max_entries: int, max_bytes: int):
        self.max_entries = max_entries
        self.max_bytes = max_bytes
        self._d: OrderedDict[str, CachedImage] = OrderedDict()
        self._lock = threading.Lock()
        self.bytes = 0
        self.hits = self.misses = self.evictions = 0

    def get(self, key: str) -> CachedImage | None:
        with self._lock:
            e = self._d.get(key)
            if e is None:
                self.misses += 1
                return None
            self._d.move_to_end(key)
            self.hits += 1
            return e

    def put(self, key: str, entry: CachedImage) -> None:
        with self._lock:
            old = self._d.pop(key, None)
            if old is not None:
                self.bytes -= old.nbytes
            self._d[key] = entry
            self.bytes += entry.nbytes
            while len(self._d) > self.max_entries or (self.bytes > self.max_bytes and len(self._d) > 1):
                _, ev = self._d.popitem(last=False)
                self.bytes -= ev.nbytes
                self.evictions += 1

    def __len__(self) -> int:
        return len(self._d)

    def stats(self) -> dict:
        return {"backend": self.backend, "entries": len(self._d), "bytes": self.bytes, "max_entries": self.max_entries,
                "max_bytes": self.max_bytes, "hits": self.hits, "misses": self.misses, "evictions": self.evictions}
