"""The load test's report: what it records per request, the summary, the Markdown table, and
what it reads from the server (its /metrics latency totals, its resident memory)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

#: report rows: ``score_first`` is the first score call after an upload (it encodes the image's
#: windows), ``score`` the cached ones (windows encoded: head only)
ENDPOINTS = ("upload", "score_first", "score", "score_once", "plan", "bad")
#: the service's /metrics endpoint label of each row (it does not tell first and cached score calls apart)
SERVER_ENDPOINT = {
    "upload": "upload",
    "score_first": "score",
    "score": "score",
    "score_once": "score_once",
    "plan": "plan",
    "bad": "bad",
}


@dataclass
class Recorder:
    latencies: dict[str, list[float]] = field(default_factory=lambda: {e: [] for e in ENDPOINTS})
    errors: dict[str, int] = field(default_factory=lambda: {e: 0 for e in ENDPOINTS})
    messages: dict[str, int] = field(default_factory=dict)
    grasps: int = 0
    recording: bool = True
    server_mean_ms: dict[str, float | None] = field(default_factory=dict)  # from /metrics, server side

    def error(self, endpoint: str, message: str) -> None:
        if self.recording:
            self.errors[endpoint] += 1
            self.messages[message[:200]] = self.messages.get(message[:200], 0) + 1


def _children(pid: int) -> list[int]:
    out = []
    try:
        for tid in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{tid}/children") as f:
                out += [int(c) for c in f.read().split()]
    except OSError:
        pass
    return out


def server_rss_bytes(pid: int) -> dict:
    """Resident memory of ``pid`` and its descendants (bytes, from /proc; Linux)."""
    pids, seen, total, peak = [pid], set(), 0, 0
    while pids:
        p = pids.pop()
        if p in seen:
            continue
        seen.add(p)
        try:
            with open(f"/proc/{p}/status") as f:
                st = dict(line.split(":", 1) for line in f if ":" in line)
        except OSError:
            if p == pid:
                raise ValueError(f"no process with pid {pid} (or /proc not readable)") from None
            continue
        total += int(st.get("VmRSS", "0 kB").split()[0]) * 1024
        peak += int(st.get("VmHWM", "0 kB").split()[0]) * 1024
        pids += _children(p)
    return {"pids": sorted(seen), "rss_bytes": total, "peak_rss_bytes": peak}


def server_latency_totals(metrics_text: str) -> dict[str, tuple[float, float]]:
    """endpoint -> (sum of seconds, count) of ``vgq_request_seconds`` in a /metrics page."""
    out: dict[str, list[float]] = {}
    for line in metrics_text.splitlines():
        for suffix, i in (("_sum{", 0), ("_count{", 1)):
            head = "vgq_request_seconds" + suffix
            if line.startswith(head):
                labels, _, value = line[len(head) :].rpartition("} ")
                ep = labels.partition('endpoint="')[2].partition('"')[0]
                out.setdefault(ep, [0.0, 0.0])[i] += float(value)
    return {k: (v[0], v[1]) for k, v in out.items()}


# ---- report ---------------------------------------------------------------------------------
def summarize(rec: Recorder, wall: float, endpoints: tuple[str, ...] | None = None) -> dict:
    """Per row of ``endpoints`` (default: every row with a request or an error) and in all."""
    eps = {}
    for e in ENDPOINTS:
        if (e not in endpoints) if endpoints is not None else not (rec.latencies[e] or rec.errors[e]):
            continue
        lat = np.asarray(rec.latencies[e]) * 1e3
        n = len(lat)
        eps[e] = {
            "requests": n,
            "errors": rec.errors[e],
            "per_s": n / wall if wall > 0 else 0.0,
            **(
                {f"p{q}_ms": float(np.percentile(lat, q)) for q in (50, 90, 99)}
                if n
                else {"p50_ms": None, "p90_ms": None, "p99_ms": None}
            ),
            "max_ms": float(lat.max()) if n else None,
            "server_mean_ms": rec.server_mean_ms.get(e),
        }
    total = sum(v["requests"] for v in eps.values())
    return {
        "endpoints": eps,
        "requests": total,
        "errors": sum(rec.errors.values()),
        "error_messages": rec.messages,
        "wall_s": wall,
        "requests_per_s": total / wall if wall > 0 else 0.0,
        "grasps_per_s": rec.grasps / wall if wall > 0 else 0.0,
    }


def table(report: dict) -> str:
    def f(x):
        return "-" if x is None else f"{x:.2f}"

    c = report["config"]
    lines = [
        f"{c['clients']} client(s) ({c['transport']}), {report['wall_s']:.1f} s, k = {c['k']}, mix {c['mix']}, image: {c['workload']}",
        "",
        "| endpoint | requests | errors | req/s | p50 ms | p90 ms | p99 ms | max ms | server mean ms |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for e, v in report["endpoints"].items():
        lines.append(
            f"| {e} | {v['requests']} | {v['errors']} | {v['per_s']:.1f} | {f(v['p50_ms'])} | {f(v['p90_ms'])} | "
            f"{f(v['p99_ms'])} | {f(v['max_ms'])} | {f(v['server_mean_ms'])} |"
        )
    lines += [
        "",
        f"total: {report['requests']} requests ({report['requests_per_s']:.0f}/s), "
        f"{report['grasps_per_s']:.0f} grasps/s, {report['errors']} errors",
    ]
    if {"score_first", "score"} <= set(report["endpoints"]):
        lines.append(
            "score_first: the first score call after an upload (encodes the image's windows); score: cached "
            "windows (head only); the server mean of both is over all score calls"
        )
    for msg, n in list(report["error_messages"].items())[:5]:
        lines.append(f"  error x{n}: {msg}")
    if "server_rss" in report:
        b, a = report["server_rss"]["before"], report["server_rss"]["after"]
        lines.append(
            f"server RSS (pids {a['pids']}): {b['rss_bytes'] / 2**20:.1f} MiB before, {a['rss_bytes'] / 2**20:.1f} MiB after "
            f"(peak {a['peak_rss_bytes'] / 2**20:.1f} MiB)"
        )
    return "\n".join(lines)
