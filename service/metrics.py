"""Prometheus metrics of one service instance (own registry, so several apps can coexist)."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

LATENCY_BUCKETS = (
    0.0002,
    0.0005,
    0.001,
    0.0015,
    0.002,
    0.003,
    0.005,
    0.0075,
    0.01,
    0.015,
    0.025,
    0.05,
    0.1,
    0.25,
    0.5,
    1.0,
    2.5,
)
GRASP_BUCKETS = (1, 8, 16, 32, 64, 128, 256, 512, 1024, 2048, 4096)
PLAN_BUCKETS = (0.025, 0.05, 0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 1.5, 2.5, 5.0, 10.0)


class _CacheCollector:
    def __init__(self, cache):
        self.cache = cache

    def collect(self):
        s = self.cache.stats()
        for name in ("entries", "bytes"):
            g = GaugeMetricFamily(f"vgq_cache_{name}", f"cached images: {name}")
            g.add_metric([], s[name])
            yield g
        for name in ("hits", "misses", "evictions"):
            c = CounterMetricFamily(f"vgq_cache_{name}", f"image cache {name}")
            c.add_metric([], s[name])
            yield c
        if "errors" in s:
            c = CounterMetricFamily("vgq_cache_backend_errors", "cache backend failures (e.g. Redis unreachable)")
            c.add_metric([], s["errors"])
            yield c


class Metrics:
    def __init__(self, cache):
        self.registry = CollectorRegistry()
        r = self.registry
        self.requests = Counter("vgq_requests", "HTTP requests", ["endpoint", "status"], registry=r)
        self.latency = Histogram(
            "vgq_request_seconds",
            "HTTP request latency (server side)",
            ["endpoint"],
            buckets=LATENCY_BUCKETS,
            registry=r,
        )
        self.encoder = Histogram(
            "vgq_encoder_seconds", "encoder (crop -> image term) time", buckets=LATENCY_BUCKETS, registry=r
        )
        self.head = Histogram("vgq_head_seconds", "head (k grasps) time", buckets=LATENCY_BUCKETS, registry=r)
        self.windows_encoded = Counter(
            "vgq_windows_encoded", "crop windows encoded (each once per cached image)", registry=r
        )
        self.grasps = Histogram(
            "vgq_grasps_per_request", "grasps scored per request", buckets=GRASP_BUCKETS, registry=r
        )
        self.plans = Counter("vgq_plans", "grasp plans answered (POST /v1/plan), by outcome", ["outcome"], registry=r)
        self.plan_seconds = Histogram(
            "vgq_plan_seconds", "planner time per plan (sample, check, score, select)", buckets=PLAN_BUCKETS, registry=r
        )
        self.ready = Gauge("vgq_ready", "1 when the model is loaded and warmed up", registry=r)
        r.register(_CacheCollector(cache))

    def observe_plan(self, seconds: float, n_grasps: int) -> None:
        """One answered plan: its planner time and whether it found grasps."""
        self.plans.labels("grasps" if n_grasps else "none").inc()
        self.plan_seconds.observe(seconds)

    def render(self) -> bytes:
        return generate_latest(self.registry)
