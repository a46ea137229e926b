"""Latency of one-shot scoring by the number of crop windows its grasps need (issue 11: a
request needing <= 4 new windows should stay within 2x of a one-window one-shot).

    python -m service.windows_bench --url http://127.0.0.1:8000 --reps 40 --k 64

Each request is a fresh 640 x 480 image (a unique value in one corner pixel: a cache miss)
with k grasps spread over n windows of the training grid (n = 1, 2, 4, 8): the service
resamples nothing (model intrinsics), encodes the n windows in one batched call and scores.
Prints the client-side p50 / p90 (ms) per n and the ratio of p50 to n = 1. Against a
service without window placement only n = 1 is measured (the others answer 422).
"""

from __future__ import annotations

import argparse
import io
import json
import time

import httpx
import numpy as np

STEP = 72  # 2 floor(kappa) px: the window grid's spacing for the bundled model


def scene(h: int = 480, w: int = 640, seed: int = 0) -> np.ndarray:
    d = np.full((h, w), 0.7, np.float32)
    d[200:280, 260:380] = 0.65
    d[0, 0] = 0.7 + 1e-4 * seed  # unique per request
    return d


def grasps(n_windows: int, k: int, seed: int = 0) -> np.ndarray:
    """k grasps, round robin over n windows right of the central one (centre 319.5, 239.5)."""
    rng = np.random.default_rng(seed)
    g = np.zeros((k, 7), np.float32)
    cols = np.arange(k) % n_windows
    g[:, 0] = 319.5 + STEP * (cols - n_windows // 2) + rng.uniform(-20, 20, k)
    g[:, 1] = 239.5 + rng.uniform(-20, 20, k)
    g[:, 2] = 0.66
    g[:, 3] = 1.0
    return g


def one_shot(http: httpx.Client, depth, g) -> float:
    buf = io.BytesIO()
    np.savez(buf, depth=depth, grasps=g)
    t = time.perf_counter()
    r = http.post(
        "/v1/score",
        content=buf.getvalue(),
        headers={"content-type": "application/x-npz", "accept": "application/octet-stream"},
    )
    dt = time.perf_counter() - t
    if r.status_code != 200:
        raise RuntimeError(f"HTTP {r.status_code}: {r.text[:200]}")
    return dt


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--url", default="http://127.0.0.1:8000")
    p.add_argument("--reps", type=int, default=40)
    p.add_argument("--k", type=int, default=64)
    p.add_argument("--windows", default="1,2,4,8")
    a = p.parse_args(argv)
    out, seed = {}, 0
    with httpx.Client(base_url=a.url, timeout=30) as http:
        for _ in range(5):  # warm-up
            seed += 1
            one_shot(http, scene(seed=seed), grasps(1, a.k))
        for n in (int(x) for x in a.windows.split(",")):
            times = []
            for _ in range(a.reps):
                seed += 1
                try:
                    times.append(one_shot(http, scene(seed=seed), grasps(n, a.k, seed)))
                except RuntimeError as e:
                    print(f"n={n}: {e}")
                    break
            if times:
                ms = 1000 * np.array(times)
                out[n] = {"p50_ms": round(float(np.median(ms)), 2), "p90_ms": round(float(np.percentile(ms, 90)), 2)}
    base = out.get(1, {}).get("p50_ms")
    for r in out.values():
        r["p50_vs_1_window"] = round(r["p50_ms"] / base, 2) if base else None
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
