"""Cache of uploaded images: id -> the image at the model's focal length and the encoder
terms of its crop windows, encoded lazily (a window the first time a grasp needs it).

``MemoryCache`` is a bounded LRU (entries and bytes) for one process; an entry's bytes are
its depth image plus its window terms, re-counted each time windows are added
(``add_windows``). The Redis backend (``service.redis_cache``) shares entries between
replicas. Both count hits, misses and evictions.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from vgq.camera import Intrinsics, footprint

from .placement import nbytes as placement_nbytes

if TYPE_CHECKING:
    from planning.placement import ImagePlacement

ENTRY_OVERHEAD_BYTES = 512  # key, object headers, intrinsics
WINDOW_OVERHEAD_BYTES = 128  # dict slot, origin tuple, missing fraction

Origin = tuple[int, int]  # top-left pixel (u, v) of a crop window in the resampled image


@dataclass(frozen=True)
class EncodedWindow:
    """One crop window's encoder output."""

    term: np.ndarray  # (1, D) float32: the encoder's output (D = 1024, more with a jaw-grid head)
    missing_fraction: float  # share of the window's pixels without a depth reading (filled before encoding)

    @property
    def nbytes(self) -> int:
        return int(self.term.nbytes) + WINDOW_OVERHEAD_BYTES


@dataclass
class CachedImage:
    """An uploaded image, resampled to the model's focal lengths (``resampled``), as the
    client's camera saw it (``camera``), and its windows encoded so far.

    ``depth`` (H', W') float32 metres, 0 = no reading (kept to encode new windows and flag
    grasps on missing pixels). ``fixed_center``: the one window centre (resampled px) when
    the upload named one (``center_u`` / ``center_v``); None = windows on the training grid.
    ``assumed``: the intrinsics the client did not send (model's focal lengths, image centre).
    ``up``: the world's up direction in the client's camera frame as sent (None: not sent);
    ``roll``: radians the image was turned about the optical axis to be level
    (``vgq.camera.level_roll``; ``resampled`` is then the level camera's canvas); ``up_from``:
    "client" (sent) or "table" (read from the image's table plane, ``level=table``).
    ``placement``: for a model whose head reads placement rows, the analysis of the image as
    uploaded (``service.placement``: client pixels and camera); None for any other model."""

    depth: np.ndarray
    camera: Intrinsics
    resampled: Intrinsics
    assumed: tuple[str, ...] = ()
    fixed_center: np.ndarray | None = None
    up: tuple[float, float, float] | None = None
    roll: float = 0.0
    up_from: str | None = None
    windows: dict[Origin, EncodedWindow] = field(default_factory=dict)
    placement: ImagePlacement | None = None
    _outside: np.ndarray | None = field(default=None, init=False, repr=False, compare=False)

    def outside(self) -> np.ndarray | None:
        """(H', W') bool: the pixels of a turned canvas (``roll`` != 0) outside the client's image,
        where no reading could be (None for an image not turned). Computed once per entry."""
        if self.roll == 0.0:
            return None
        if self._outside is None:
            self._outside = ~footprint(self.resampled, self.camera, self.roll)
        return self._outside

    @property
    def image_shape(self) -> tuple[int, int]:
        """(H, W) of the upload (client pixels)."""
        return self.camera.height, self.camera.width

    @property
    def scale(self) -> tuple[float, float]:
        """(sx, sy): resampled pixels per client pixel (the focal lengths' ratios)."""
        if self.roll == 0.0:
            return self.resampled.width / self.camera.width, self.resampled.height / self.camera.height
        return self.resampled.fx / self.camera.fx, self.resampled.fy / self.camera.fy

    @property
    def missing_fraction(self) -> float:
        """Share of the image's pixels (grid mode) or of the fixed window's (fixed mode) without a
        reading (of a level canvas: of the pixels the image covers)."""
        if self.fixed_center is not None and len(self.windows) == 1:
            return next(iter(self.windows.values())).missing_fraction
        if self.roll == 0.0:
            return float(np.mean(self.depth <= 0))
        return float(np.mean(self.depth[footprint(self.resampled, self.camera, self.roll)] <= 0))

    @property
    def nbytes(self) -> int:
        return (
            int(self.depth.nbytes)
            + ENTRY_OVERHEAD_BYTES
            + sum(w.nbytes for w in self.windows.values())
            + placement_nbytes(self.placement)
        )


def image_id(body: bytes, params: str, model_version: str) -> str:
    """Content address of an upload: hash of model version, crop / camera parameters and bytes."""
    h = hashlib.sha256()
    h.update(model_version.encode())
    h.update(b"\0")
    h.update(params.encode())
    h.update(b"\0")
    h.update(body)
    return h.hexdigest()[:32]


class MemoryCache:
    """Thread-safe LRU bounded by entry count and bytes (an entry's size as of its last
    ``put`` / ``add_windows``)."""

    backend = "memory"

    def __init__(self, max_entries: int, max_bytes: int):
        self.max_entries = max_entries
        self.max_bytes = max_bytes
        self._d: OrderedDict[str, CachedImage] = OrderedDict()
        self._size: dict[str, int] = {}
        self._lock = threading.Lock()
        self.bytes = 0
        self.hits = self.misses = self.evictions = 0
        self.windows_encoded = self.windows_fetched = 0

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
            self._put(key, entry)

    def _put(self, key: str, entry: CachedImage) -> None:
        if self._d.pop(key, None) is not None:
            self.bytes -= self._size.pop(key)
        self._d[key] = entry
        self._size[key] = entry.nbytes
        self.bytes += self._size[key]
        while len(self._d) > self.max_entries or (self.bytes > self.max_bytes and len(self._d) > 1):
            old, _ = self._d.popitem(last=False)
            self.bytes -= self._size.pop(old)
            self.evictions += 1

    def fetch_windows(self, key: str, entry: CachedImage, origins) -> None:
        """Windows of ``entry`` held elsewhere (another replica): none in one process."""

    def add_windows(self, key: str, entry: CachedImage, new: dict) -> None:
        """``new`` windows (origin -> EncodedWindow) were just encoded for ``entry``: keep
        them and re-count its bytes (may evict older images)."""
        with self._lock:
            entry.windows.update(new)
            self.windows_encoded += len(new)
            if key in self._d:
                self._put(key, entry)

    def __len__(self) -> int:
        return len(self._d)

    def __contains__(self, key: str) -> bool:
        with self._lock:
            return key in self._d

    def stats(self) -> dict:
        with self._lock:
            windows = sum(len(e.windows) for e in self._d.values())
        return {
            "backend": self.backend,
            "entries": len(self._d),
            "bytes": self.bytes,
            "max_entries": self.max_entries,
            "max_bytes": self.max_bytes,
            "hits": self.hits,
            "misses": self.misses,
            "evictions": self.evictions,
            "windows": windows,
            "windows_encoded": self.windows_encoded,
            "windows_fetched": self.windows_fetched,
        }
