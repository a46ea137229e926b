"""State of one service instance (settings, model, cache, metrics) and the steps a request
takes: check the camera, crop + encode + cache an image, score grasps against it."""

from __future__ import annotations

import gc
import logging

import numpy as np

from vgq.crop import window_center, window_origin
from vgq.grasps import GraspError, pose_rows

from . import logs
from .cache import CachedImage, MemoryCache
from .config import Settings
from .errors import ApiError
from .metrics import Metrics
from .preprocess import window_input
from .runtime import FastModel

INTRINSICS_TOLERANCE = 0.02  # relative focal length mismatch accepted


def grasp_error(e: GraspError) -> ApiError:
    """The contract's GraspError as the HTTP edge answers it: 422 naming the rows."""
    return ApiError(422, str(e), {"grasps": e.indices} if e.indices else None)


class Service:
    """State of one service instance: settings, model, cache, metrics."""

    def __init__(self, settings: Settings, model: FastModel | None = None, cache=None):
        self.settings = settings
        self.log = logs.setup(settings.log_level)
        self.model = model
        self.cache = cache if cache is not None else make_cache(settings, self.log)
        self.metrics = Metrics(self.cache)
        self.ready = False
        self.load_error: str | None = None

    def load(self) -> None:
        """Load (unless given) and warm up the model; then mark ready."""
        try:
            if self.model is None:
                self.model = FastModel(self.settings.model_dir, threads=self.settings.ort_threads,
                                       head_precision=self.settings.head_precision,
                                       encoder_precision=self.settings.encoder_precision)
            self.model.warm_up()
            gc.collect()
            gc.freeze()  # start-up objects out of the collector's way: no GC pauses on them later
            self.ready = True
            self.metrics.ready.set(1)
            logs.event(self.log, "ready", model_version=self.model.version, head=self.model.head_precision,
                       encoder=self.model.encoder_info,
                       threads=self.settings.ort_threads, cache=self.cache.backend)
        except Exception as e:  # reported by /readyz and the log; the process stays up for diagnosis
            self.load_error = str(e)
            logs.event(self.log, "model load failed", logging.ERROR, error=str(e))

    # ---- request steps ----------------------------------------------------------------
    def requested_center(self, shape, center_u, center_v) -> np.ndarray:
        h, w = shape
        cu = (w - 1) / 2 if center_u is None else center_u
        cv = (h - 1) / 2 if center_v is None else center_v
        if not (0 <= cu <= w - 1 and 0 <= cv <= h - 1):
            raise ApiError(422, f"window centre ({cu}, {cv}) must lie inside the {h}x{w} image (u in [0, {w - 1}], v in [0, {h - 1}])")
        return np.array([cu, cv], dtype=np.float64)

    def check_intrinsics(self, fx, fy) -> None:
        intr = self.model.card.intrinsics
        for name, given, trained in (("fx", fx, intr.fx), ("fy", fy, intr.fy)):
            if given is not None and not abs(given / trained - 1) <= INTRINSICS_TOLERANCE:
                raise ApiError(422, f"{name} = {given} px, but the model was trained for {name} = {trained} px "
                                    f"(within {INTRINSICS_TOLERANCE:.0%}); resample the image to that focal length")

    def check_grasps(self, grasps: np.ndarray, center: np.ndarray) -> None:
        """Check grasps against the window an image cropped at ``center`` gets, before encoding it."""
        geom = self.model.geometry
        self.pose_rows(grasps, window_center(window_origin(center, geom), geom))

    def pose_rows(self, grasps: np.ndarray, center: np.ndarray) -> np.ndarray:
        try:
            return pose_rows(grasps, center, self.model.geometry, self.settings.max_grasps)
        except GraspError as e:
            raise grasp_error(e) from None

    def encode_image(self, key: str, depth: np.ndarray, center) -> CachedImage:
        geom = self.model.geometry
        win = window_input(depth, window_origin(center, geom), geom, self.settings.max_missing_fraction)
        term = self.model.encode(win.image)
        self.metrics.encoder.observe(self.model.encode_seconds)
        entry = CachedImage(term, win.center, depth.shape, win.missing_fraction)
        self.cache.put(key, entry)
        return entry

    def score(self, entry: CachedImage, grasps: np.ndarray) -> np.ndarray:
        poses = self.pose_rows(grasps, entry.window_center)
        p = self.model.score(entry.image_term, poses)
        self.metrics.head.observe(self.model.score_seconds)
        self.metrics.grasps.observe(len(p))
        return p

    def image_info(self, key: str, entry: CachedImage, cached: bool) -> dict:
        c, k = entry.window_center, self.model.geometry.kappa_px
        return {"image_id": key, "cached": cached, "model_version": self.model.version,
                "image_shape": list(entry.image_shape), "window_center": [float(c[0]), float(c[1])],
                "missing_fraction": entry.missing_fraction,
                "grasp_range": {"u": [float(c[0] - k), float(c[0] + k)], "v": [float(c[1] - k), float(c[1] + k)]}}


def make_cache(settings: Settings, log: logging.Logger):
    if settings.cache_backend == "redis":
        from .redis_cache import RedisCache

        return RedisCache(settings.redis_url, settings.cache_entries, settings.cache_bytes, log, ttl_s=settings.cache_ttl_s)
    return MemoryCache(settings.cache_entries, settings.cache_bytes)
