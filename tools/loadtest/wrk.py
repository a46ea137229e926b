"""Cached score calls driven by wrk (a C load generator: Debian package ``wrk``), so the
service's capacity is measured without a Python client taking a core of its own:

    python -m tools.loadtest.wrk --url http://127.0.0.1:8000 --connections 8 --duration 20
    python -m tools.loadtest.topology --engine wrk --replicas 2 -- --connections 8 --duration 20

One fresh image is uploaded and its grasps scored once (the windows encoded) before the run;
then ``--connections`` keep-alive connections POST the same k grasps to
``/v1/images/{id}/scores`` (binary float32 in and out, as ``python -m tools.loadtest --mix
upload=0,score=N`` does) for ``--duration`` seconds after ``--warmup`` unrecorded seconds.
wrk counts an answer with status >= 400 and every socket error or timeout as an error; the
answer's size is checked before the run, not per request.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from .client import check_target
from .workload import OCTET, FreshImages, load_workload

# wrk's Lua: POST the body file to the URL's path; at the end print one JSON line of totals
LUA = r"""
local f = assert(io.open(os.getenv("VGQ_WRK_BODY"), "rb"))
wrk.method = "POST"
wrk.body = f:read("*all")
f:close()
wrk.headers["Content-Type"] = "application/octet-stream"
wrk.headers["Accept"] = "application/octet-stream"

function done(summary, latency, requests)
  local e = summary.errors
  io.write(string.format(
    'VGQ_WRK {"requests": %d, "duration_us": %d, "connect": %d, "read": %d, "write": %d, "status": %d, ' ..
    '"timeout": %d, "p50_us": %d, "p90_us": %d, "p99_us": %d, "p999_us": %d, "max_us": %d, "mean_us": %.1f}\n',
    summary.requests, summary.duration, e.connect, e.read, e.write, e.status, e.timeout,
    latency:percentile(50), latency:percentile(90), latency:percentile(99), latency:percentile(99.9),
    latency.max, latency.mean))
end
"""


def find_wrk() -> str | None:
    return shutil.which("wrk")


def pin_image(url: str, k: int, timeout: float = 30.0) -> tuple[str, bytes]:
    """Upload a fresh image and score k grasps against it once; returns (image id, grasp bytes).
    RuntimeError when the service refuses either call or answers the wrong size."""
    import httpx

    work = load_workload(k)
    body = np.ascontiguousarray(work.grasps, "<f4").tobytes()
    with httpx.Client(base_url=url, timeout=timeout) as http:
        r = http.post(
            "/v1/images", content=FreshImages(work.depth).next_npy(), headers={"content-type": "application/x-npy"}
        )
        if r.status_code != 200:
            raise RuntimeError(f"upload answered {r.status_code}: {r.text[:160]}")
        image_id = r.json()["image_id"]
        r = http.post(f"/v1/images/{image_id}/scores", content=body, headers={"content-type": OCTET, "accept": OCTET})
        if r.status_code != 200 or len(r.content) != 4 * k:
            raise RuntimeError(f"score answered {r.status_code} with {len(r.content)} bytes (expected {4 * k})")
    return image_id, body


def parse_summary(stdout: str) -> dict:
    """The totals line our Lua ``done`` prints; ValueError when wrk printed none."""
    m = re.search(r"^VGQ_WRK (\{.*\})$", stdout, re.M)
    if not m:
        raise ValueError(f"wrk printed no summary: {stdout[-400:]!r}")
    return json.loads(m.group(1))


def run_wrk(
    url: str, path: str, body: bytes, connections: int, duration: float, threads: int = 1, timeout: float = 10.0
) -> dict:
    """One wrk run of POST ``path`` with ``body``; returns parse_summary's totals."""
    wrk = find_wrk()
    if not wrk:
        raise FileNotFoundError("needs wrk (apt-get install -y wrk)")
    with tempfile.TemporaryDirectory(prefix="vgq-wrk-") as tmp:
        (Path(tmp) / "body").write_bytes(body)
        (Path(tmp) / "score.lua").write_text(LUA)
        cmd = [
            wrk,
            f"--threads={threads}",
            f"--connections={connections}",
            f"--duration={max(1, round(duration))}s",
            f"--timeout={max(1, round(timeout))}s",
            f"--script={Path(tmp) / 'score.lua'}",
            url.rstrip("/") + path,
        ]
        env = {**os.environ, "VGQ_WRK_BODY": str(Path(tmp) / "body")}
        done = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=duration + timeout + 30)
    if done.returncode:
        raise RuntimeError(f"wrk exited with {done.returncode}: {done.stderr[-400:]}")
    return parse_summary(done.stdout)


def report(totals: dict, k: int) -> dict:
    """Requests, errors, grasps/s and latency percentiles (ms) from wrk's totals."""
    seconds = totals["duration_us"] / 1e6
    errors = sum(totals[e] for e in ("connect", "read", "write", "status", "timeout"))
    ok = totals["requests"] - totals["status"]
    return {
        "engine": "wrk",
        "requests": totals["requests"],
        "errors": errors,
        "errors_by_kind": {e: totals[e] for e in ("connect", "read", "write", "status", "timeout")},
        "seconds": round(seconds, 3),
        "req_per_s": round(totals["requests"] / seconds, 1),
        "grasps_per_s": round(ok * k / seconds),
        **{f"{q}_ms": round(totals[f"{q}_us"] / 1e3, 3) for q in ("p50", "p90", "p99", "p999", "max", "mean")},
    }


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(
        prog="python -m tools.loadtest.wrk", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--url", default="http://127.0.0.1:8000", help="service (or balancer) base URL, loopback only")
    p.add_argument("--connections", type=int, default=8, help="concurrent keep-alive connections (default 8)")
    p.add_argument("--threads", type=int, default=1, help="wrk threads (default 1)")
    p.add_argument("--duration", type=float, default=10.0, help="measured seconds (default 10)")
    p.add_argument("--warmup", type=float, default=2.0, help="unrecorded seconds of the same load first (default 2)")
    p.add_argument("--k", type=int, default=128, help="grasps per score call (default 128)")
    p.add_argument("--timeout", type=float, default=10.0, help="per-request timeout, seconds (default 10)")
    p.add_argument("--json", help="also write the report as JSON to this file")
    a = p.parse_args(argv)
    if a.connections < 1 or a.threads < 1 or a.threads > a.connections or a.k < 1:
        p.error("--connections and --k must be >= 1, 1 <= --threads <= --connections")
    if not 1 <= a.duration <= 24 * 3600 or a.warmup < 0 or not a.timeout > 0:
        p.error("--duration must be 1 s to 24 h, --warmup >= 0, --timeout > 0")
    try:
        url = check_target(a.url, False)
    except ValueError as e:
        p.error(str(e))
    if not find_wrk():
        print("loadtest.wrk: needs wrk (apt-get install -y wrk)", file=sys.stderr)
        sys.exit(2)
    import httpx

    try:
        image_id, body = pin_image(url, a.k, a.timeout)
        path = f"/v1/images/{image_id}/scores"
        if a.warmup >= 1:
            run_wrk(url, path, body, a.connections, a.warmup, a.threads, a.timeout)
        rep = report(run_wrk(url, path, body, a.connections, a.duration, a.threads, a.timeout), a.k)
    except (OSError, RuntimeError, ValueError, subprocess.TimeoutExpired, httpx.HTTPError) as e:
        print(f"loadtest.wrk: {type(e).__name__}: {e}", file=sys.stderr)
        sys.exit(1)
    rep.update(connections=a.connections, wrk_threads=a.threads, k=a.k)
    print(
        f"wrk, {a.connections} connections, {a.duration:g} s, k = {a.k}: {rep['requests']} cached score calls, "
        f"{rep['errors']} errors, {rep['req_per_s']:.0f} req/s, {rep['grasps_per_s']:,} grasps/s; latency ms "
        f"p50 {rep['p50_ms']:.2f}, p90 {rep['p90_ms']:.2f}, p99 {rep['p99_ms']:.2f}, max {rep['max_ms']:.2f}"
    )
    if a.json:
        from vgq import atomic

        atomic.write_json(a.json, rep)
    return rep


if __name__ == "__main__":
    main()
