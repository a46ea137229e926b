"""Service configuration: one dataclass, filled from defaults < environment (VGQ_*) < CLI flags
(through the shared bridge ``vgq.cli_config``)."""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass, field
from pathlib import Path

from vgq.cli_config import ConfigError, add_options, build

DEFAULT_MODEL_DIR = Path(__file__).resolve().parent.parent / "models" / "fast-vgqcnn-default"

HEAD_PRECISIONS = ("auto", "fp32", "int8")
ENCODER_PRECISIONS = ("auto", "fp32", "int8")
CACHE_BACKENDS = ("memory", "redis")


@dataclass
class Settings:
    model_dir: str = str(DEFAULT_MODEL_DIR)
    host: str = "127.0.0.1"
    port: int = 8000
    workers: int = 1
    threads: int = 0  # onnxruntime intra-op threads per session; 0 = cores / workers
    head_precision: str = field(
        default="auto",
        metadata={
            "choices": HEAD_PRECISIONS,
            "help": "auto (int8 when the model ships a checked int8 head) | fp32 | int8",
        },
    )
    encoder_precision: str = field(
        default="auto",
        metadata={
            "choices": ENCODER_PRECISIONS,
            "help": "auto (the fastest checked encoder, timed at start-up) | fp32 | int8",
        },
    )
    max_grasps: int = 2048  # grasps per request
    max_body_bytes: int = 32 * 1024 * 1024  # request body limit
    max_buffered_bytes: int = 128 * 1024 * 1024  # request bodies held in memory at once, all requests together
    max_inflight: int = 64  # requests being served at once (health, readiness and metrics not counted)
    max_header_bytes: int = 16 * 1024  # request line + headers of one request
    max_headers: int = 100  # header lines of one request
    max_url_bytes: int = 8 * 1024  # request target (path + query)
    max_image_side: int = 4096  # pixels, either dimension of an uploaded depth image
    cache_entries: int = 4096
    cache_bytes: int = 256 * 1024 * 1024  # an image: its depth (4 B/px) + its windows' encodings (70 kB each, bundle)
    cache_backend: str = field(default="memory", metadata={"choices": CACHE_BACKENDS, "help": "memory | redis"})
    redis_url: str = "redis://127.0.0.1:6379/0"
    cache_ttl_s: float = 86400.0  # redis backend: an image unused this long expires (each hit renews it)
    request_timeout_s: float = 10.0
    # plans computed at once (each in a worker thread; more wait without holding one): a plan on a
    # 4096 x 4096 image takes ~1.6 GB and ~4 s, on a 300 x 300 one ~15 ms (service.limits)
    max_concurrent_plans: int = 2
    # plans waiting for a slot at once; one more answers 503 with Retry-After at once, so that a flood
    # of plans cannot hold every in-flight place (max_inflight) the scoring routes need
    max_queued_plans: int = 16
    max_missing_fraction: float = 0.5  # a crop window with more pixels without depth (0) is refused (422)
    ood_window_missing: float = 0.25  # a window with more pixels without depth flags its grasps window_mostly_missing
    api_key: str = ""  # when set, upload and score need header X-API-Key
    log_level: str = "info"
    access_log: bool = False  # one structured line per request
    # FastAPI's native OpenTelemetry (to the globally configured providers); off: its per-request
    # check costs ~17 us even with no provider set, and /metrics has the service's own numbers
    otel: bool = False

    def __post_init__(self) -> None:
        for name, lo in (
            ("port", 0),
            ("workers", 1),
            ("threads", 0),
            ("max_grasps", 1),
            ("max_body_bytes", 1024),
            ("max_buffered_bytes", 1024),
            ("max_inflight", 1),
            ("max_header_bytes", 1024),
            ("max_headers", 8),
            ("max_url_bytes", 256),
            ("max_image_side", 32),
            ("cache_entries", 1),
            ("cache_bytes", 4096),
            ("max_concurrent_plans", 1),
            ("max_queued_plans", 0),
        ):
            v = getattr(self, name)
            if not isinstance(v, int) or v < lo:
                raise ValueError(f"setting {name} must be an integer >= {lo}, got {v!r}")
        if self.port > 65535:
            raise ValueError(f"setting port must be an integer in [0, 65535], got {self.port}")
        if self.max_buffered_bytes < self.max_body_bytes:
            raise ValueError(
                f"setting max_buffered_bytes ({self.max_buffered_bytes}) must be >= max_body_bytes "
                f"({self.max_body_bytes}): one largest body must fit"
            )
        if self.head_precision not in HEAD_PRECISIONS:
            raise ValueError(f"setting head_precision must be one of {HEAD_PRECISIONS}, got {self.head_precision!r}")
        if self.encoder_precision not in ENCODER_PRECISIONS:
            raise ValueError(
                f"setting encoder_precision must be one of {ENCODER_PRECISIONS}, got {self.encoder_precision!r}"
            )
        if self.cache_backend not in CACHE_BACKENDS:
            raise ValueError(f"setting cache_backend must be 'memory' or 'redis', got {self.cache_backend!r}")
        if self.workers > 1 and self.cache_backend == "memory":
            # uvicorn hands each new connection to whichever worker accepts it: with one memory cache
            # per worker, an image uploaded through one connection is a 404 on about (N-1)/N of the others
            raise ValueError(
                f"setting workers = {self.workers} needs cache_backend 'redis': each worker process keeps its "
                "own memory cache, so an image uploaded through one connection is unknown (404) to a request "
                "another worker accepts; set cache_backend=redis and redis_url, or run one worker per replica"
            )
        if self.cache_backend == "redis" and not self.redis_url.startswith(("redis://", "rediss://", "unix://")):
            raise ValueError(f"setting redis_url must be a redis://, rediss:// or unix:// URL, got {self.redis_url!r}")
        for name in ("max_missing_fraction", "ood_window_missing"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"setting {name} must be in [0, 1], got {getattr(self, name)!r}")
        for name in ("request_timeout_s", "cache_ttl_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"setting {name} must be > 0, got {getattr(self, name)!r}")

    @property
    def ort_threads(self) -> int:
        if self.threads:
            return self.threads
        return max(1, (os.cpu_count() or 1) // self.workers)


ENV_PREFIX = "VGQ_"


def from_env(environ=os.environ, **overrides) -> Settings:
    """Settings from VGQ_<NAME> environment variables, then keyword overrides (``None``: not given).

    Raises ``vgq.cli_config.ConfigError`` (a ``ValueError``) naming the variable or setting."""
    return build(Settings, overrides, environ=environ, env_prefix=ENV_PREFIX)


def parse_args(argv=None) -> Settings:
    """CLI flags (``--model-dir``, ``--port``, ...) over environment over defaults."""
    p = argparse.ArgumentParser(
        prog="vgq-serve", description="Serve grasp-quality scores over HTTP (Fast-VGQ-CNN on onnxruntime)."
    )
    add_options(p, Settings, env_prefix=ENV_PREFIX)  # choices from the fields' metadata
    args = p.parse_args(argv)
    try:
        return from_env(**vars(args))
    except ConfigError as e:
        p.error(str(e))
