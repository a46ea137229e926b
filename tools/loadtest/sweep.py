"""Latency and throughput against the number of clients for several worker x thread settings of
the service, all measured in one run on this machine, with a plot.

    python -m tools.loadtest.sweep --clients 1,2,4,8 --workers 1,2 --threads 1,2 --duration 5 \\
        --plot docs/img/latency_vs_clients.png --json sweep.json

For each (workers, threads) a service is started on a free loopback port (``python -m service``;
one worker: the memory cache; several: the Redis cache on a throw-away ``redis-server``, as the
service requires, since each worker has its own memory), then the load test runs for each client
count with the raw HTTP client (least client CPU). The machine's load average is recorded with
every point.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

from .client import run_load
from .report import ENDPOINTS, summarize
from .workload import ROOT, Mix, load_workload


def _ints(text: str, name: str) -> list[int]:
    try:
        v = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{name} must be comma-separated integers, got {text!r}") from None
    if not v or min(v) < 1:
        raise argparse.ArgumentTypeError(f"{name} must be integers >= 1, got {text!r}")
    return v


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_service(
    workers: int, threads: int, model_dir: str | None, timeout: float = 90.0, redis_url: str | None = None
) -> tuple[subprocess.Popen, str]:
    """A service process on a free loopback port, once /readyz answers 200 (``redis_url``: its
    cache backend is that Redis server; needed for ``workers`` > 1)."""
    import httpx

    port = _free_port()
    cmd = [sys.executable, "-m", "service", "--port", str(port), "--workers", str(workers), "--threads", str(threads)]
    cmd += ["--model-dir", model_dir] if model_dir else []
    cmd += ["--cache-backend", "redis", "--redis-url", redis_url] if redis_url else []
    proc = subprocess.Popen(
        cmd, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + timeout
    while proc.poll() is None and time.monotonic() < deadline:
        try:
            if httpx.get(url + "/readyz", timeout=1).status_code == 200:
                return proc, url
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    stop(proc)
    raise RuntimeError(f"service --workers {workers} --threads {threads} did not become ready")


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


def _ms(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"


def sweep(
    clients: list[int],
    workers: list[int],
    threads: list[int],
    duration: float,
    k: int,
    mix: Mix,
    model_dir: str | None = None,
    log=print,
) -> list[dict]:
    """One point per (workers, threads, clients): the load test's summary plus its settings."""
    from contextlib import ExitStack

    from .topology import find_binary, redis

    work = load_workload(k)
    points = []
    with ExitStack() as stack:
        redis_url = None
        if max(workers) > 1:
            binary = find_binary("redis-server")
            if binary is None:
                raise FileNotFoundError("--workers > 1 needs redis-server (apt-get install -y redis-server)")
            redis_url = redis(stack, binary)
        for w in workers:
            for t in threads:
                points += _measure(w, t, clients, duration, work, mix, model_dir, redis_url if w > 1 else None, log)
    return points


def _measure(w, t, clients, duration, work, mix, model_dir, redis_url, log) -> list[dict]:
    """The points of one (workers, threads) service, one per client count."""
    points = []
    proc, url = start_service(w, t, model_dir, redis_url=redis_url)
    try:
        for c in clients:
            rec, wall = asyncio.run(run_load(url, c, duration, work, mix, warmup=1.0, transport="raw"))
            rows = tuple(e for e in ENDPOINTS if (e != "bad" or mix.bad) and (e != "plan" or mix.plan))  # for the plot
            s = summarize(rec, wall, rows)
            s.update(workers=w, threads=t, clients=c, cache=("redis" if redis_url else "memory"))
            s["load_average"] = list(os.getloadavg())
            points.append(s)
            e = s["endpoints"]
            log(
                f"workers {w} threads {t} clients {c}: {s['grasps_per_s']:.0f} grasps/s, score p50/p99 "
                f"{_ms(e['score']['p50_ms'])}/{_ms(e['score']['p99_ms'])} ms, one-shot p50 {_ms(e['score_once']['p50_ms'])} ms, "
                f"{s['errors']} errors, load {os.getloadavg()[0]:.1f}"
            )
    finally:
        stop(proc)
    return points


def title(points: list[dict], k: int, mix: str, duration: float) -> str:
    loads = [p["load_average"][0] for p in points]
    return (
        f"{os.cpu_count()} cores, k = {k}, mix {mix}, {duration:g} s per point, raw HTTP clients, load average "
        f"{min(loads):.1f}-{max(loads):.1f}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}"
    )


def plot(points: list[dict], path: str | Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    for w, t in sorted({(p["workers"], p["threads"]) for p in points}):
        pts = sorted((p for p in points if (p["workers"], p["threads"]) == (w, t)), key=lambda p: p["clients"])
        x = [p["clients"] for p in pts]
        label = f"{w} worker(s) x {t} thread(s)"
        axes[0].plot(x, [p["endpoints"]["score_once"]["p50_ms"] for p in pts], "o-", label=label)
        axes[1].plot(x, [p["endpoints"]["score"]["p99_ms"] for p in pts], "o-", label=label)
        axes[2].plot(x, [p["grasps_per_s"] / 1e3 for p in pts], "o-", label=label)
    for ax, ylabel in zip(axes, ("one-shot p50, ms", "cached score p99, ms", "thousand grasps / s")):
        ax.set_xlabel("concurrent clients")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    axes[1].set_yscale("log")
    axes[0].legend(fontsize=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(
        prog="python -m tools.loadtest.sweep", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--clients", type=lambda s: _ints(s, "--clients"), default=[1, 2, 4, 8])
    p.add_argument("--workers", type=lambda s: _ints(s, "--workers"), default=[1, 2])
    p.add_argument("--threads", type=lambda s: _ints(s, "--threads"), default=[1, 2])
    p.add_argument("--duration", type=float, default=5.0, help="measured seconds per point (default 5)")
    p.add_argument("--k", type=int, default=128)
    p.add_argument("--mix", default="upload=1,score=8,once=1")
    p.add_argument("--model-dir", help="model folder (default: the service's default)")
    p.add_argument("--plot", help="write the plot (PNG) here")
    p.add_argument("--json", help="write the points as JSON here")
    a = p.parse_args(argv)
    if not a.duration > 0 or a.k < 1:
        p.error("--duration must be > 0 and --k >= 1")
    try:
        mix = Mix.parse(a.mix)
    except ValueError as e:
        p.error(str(e))
    points = sweep(
        a.clients, a.workers, a.threads, a.duration, a.k, mix, a.model_dir, log=lambda s: print(s, file=sys.stderr)
    )
    if a.json:
        Path(a.json).write_text(json.dumps(points, indent=2) + "\n")
    if a.plot:
        plot(points, a.plot, title(points, a.k, a.mix, a.duration))
    return points


if __name__ == "__main__":
    main()
