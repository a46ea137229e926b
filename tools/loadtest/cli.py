"""Command line of the load test (``python -m tools.loadtest``); see the package doc."""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
import time
from dataclasses import asdict
from pathlib import Path

from . import __doc__ as DOC
from .client import check_target, run_load
from .report import server_rss_bytes, summarize, table
from .workload import Mix, load_workload


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(
        prog="python -m tools.loadtest", description=DOC, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--url", default="http://127.0.0.1:8000", help="service base URL (loopback only unless --allow-remote)"
    )
    p.add_argument("--clients", type=int, default=8, help="concurrent clients, one connection each (default 8)")
    p.add_argument("--duration", type=float, default=10.0, help="measured seconds (default 10)")
    p.add_argument("--warmup", type=float, default=1.0, help="seconds of unrecorded load first (default 1)")
    p.add_argument("--k", type=int, default=128, help="grasps per score call (default 128)")
    p.add_argument(
        "--mix",
        default="upload=1,score=8,once=1",
        help="requests per client cycle (default upload=1,score=8,once=1; also plan=N, bad=N); upload=0,score=N,"
        "once=0: cached score calls only, against one image per client uploaded and scored once before the run",
    )
    p.add_argument("--timeout", type=float, default=10.0, help="per-request timeout, seconds (default 10)")
    p.add_argument("--server-pid", type=int, help="record this process's (and its children's) RSS before and after")
    p.add_argument("--json", help="also write the report as JSON to this file")
    p.add_argument("--allow-remote", action="store_true", help="allow a non-loopback --url")
    p.add_argument("--seed", type=int, help="seed of the fresh-image salt (default: random)")
    p.add_argument(
        "--transport",
        choices=("auto", "httpx", "raw"),
        default="auto",
        help="HTTP client: httpx, or raw (minimal keep-alive HTTP/1.1, least client overhead); "
        "auto = raw for --clients 1 over http, else httpx",
    )
    a = p.parse_args(argv)
    if a.clients < 1 or a.k < 1 or not a.duration > 0 or a.warmup < 0 or not a.timeout > 0:
        p.error("--clients and --k must be >= 1, --duration and --timeout > 0, --warmup >= 0")
    if a.duration > 24 * 3600:
        p.error("--duration is limited to 24 h")
    try:
        url = check_target(a.url, a.allow_remote)
        mix = Mix.parse(a.mix)
        before = server_rss_bytes(a.server_pid) if a.server_pid else None
    except ValueError as e:
        p.error(str(e))
    transport = a.transport
    if transport == "auto":
        transport = "raw" if a.clients == 1 and url.startswith("http://") else "httpx"
    if transport == "raw" and not url.startswith("http://"):
        p.error("--transport raw speaks plain http only")
    work = load_workload(a.k)
    try:
        rec, wall = asyncio.run(run_load(url, a.clients, a.duration, work, mix, a.warmup, a.timeout, a.seed, transport))
    except (RuntimeError, OSError, asyncio.TimeoutError) as e:
        print(f"loadtest: {type(e).__name__}: {e}", file=sys.stderr)
        sys.exit(1)
    except Exception as e:  # httpx connection errors on /readyz
        print(f"loadtest: cannot reach {url}: {type(e).__name__}: {e}", file=sys.stderr)
        sys.exit(1)
    report = summarize(rec, wall, mix.endpoints())
    report["config"] = {
        "url": url,
        "clients": a.clients,
        "transport": transport,
        "duration_s": a.duration,
        "warmup_s": a.warmup,
        "k": a.k,
        "mix": asdict(mix),
        "workload": work.source,
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "load_average": list(os.getloadavg()),
        "cpu_count": os.cpu_count(),
    }
    if a.server_pid:
        try:
            report["server_rss"] = {"before": before, "after": server_rss_bytes(a.server_pid)}
        except ValueError as e:
            report["server_rss_error"] = str(e)
    print(table(report))
    if a.json:
        Path(a.json).write_text(json.dumps(report, indent=2) + "\n")
    return report


if __name__ == "__main__":
    main()
