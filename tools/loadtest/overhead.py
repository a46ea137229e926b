"""What HTTP adds to the model: in-process model time, in-process route steps and HTTP latency of
a one-shot call and a cached score call, measured interleaved in one run (issue 14's ratios).

    python -m tools.loadtest.overhead --model-dir models/fast-vgqcnn-default --rounds 10 --calls 30
    python -m tools.loadtest.overhead --service before=/tmp/base --service after=.   # A/B, one run

Rows (k grasps, one onnxruntime thread unless ``--threads``):

* ``model encoder + head`` / ``model head``: the service's ``FastModel`` in this process, one crop
  encoded then k grasps scored / k grasps against a cached image term (export.benchmark's
  "Fast-VGQ-CNN prediction" and "head only" rows).
* ``steps one-shot`` / ``steps cached score``: the route's work once its body is in memory
  (``service.routes.score_one_shot`` / ``score_cached``: parse, image id, cache, place, windows,
  model, OOD flags, calibration, the answer), in this process.
* ``HTTP one-shot`` / ``HTTP cached score`` per service: a real ``python -m service`` (uvicorn) on
  loopback, one sequential keep-alive client on a blocking socket. One-shot: a fresh image each
  call (.npz body, float32 answer), so the encoder runs; cached score: float32 grasps against an
  image uploaded and scored once before timing, so its windows are encoded (head only).
* ``HTTP floor: one-shot`` / ``HTTP floor: cached score``: the same bodies and answer sizes sent to
  ``tools.loadtest.floor_app`` (reads the body, answers zeros) on the same uvicorn stack: what
  uvicorn and loopback cost with no app work. ``model + floor`` ratios: the best the service
  could reach if its route did nothing but run the model.

``--service NAME=ROOT`` (repeatable; default ``this=`` this checkout) starts one service per
source tree (its PYTHONPATH and working directory), e.g. the previous commit unpacked with
``git archive``: every row is measured in each of ``--rounds`` rounds, ``--calls`` calls per row
per round, so the machine's load hits all alike. Ratios: HTTP one-shot p50 / model encoder + head
median, HTTP cached score p50 - model head median.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .workload import ROOT, FreshImages, load_workload

NPZ, OCTET, NPY = "application/x-npz", "application/octet-stream", "application/x-npy"


class BlockingHTTP:
    """A minimal HTTP/1.1 keep-alive client on one blocking socket (least client CPU: the
    client shares the cores with the service)."""

    def __init__(self, port: int, timeout: float = 30.0):
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=timeout)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.file = self.sock.makefile("rb")
        self.port = port

    def post(
        self, path: str, body: bytes, content_type: str, accept: str = OCTET, extra: str = ""
    ) -> tuple[int, bytes]:
        head = (
            f"POST {path} HTTP/1.1\r\nhost: 127.0.0.1:{self.port}\r\ncontent-type: {content_type}\r\n"
            f"accept: {accept}\r\n{extra}content-length: {len(body)}\r\n\r\n"
        ).encode()
        self.sock.sendall(head + body)
        status = int(self.file.readline().split()[1])
        length = 0
        while (line := self.file.readline()) not in (b"\r\n", b""):
            name, _, value = line.partition(b":")
            if name.strip().lower() == b"content-length":
                length = int(value)
        return status, self.file.read(length)

    def close(self) -> None:
        self.file.close()
        self.sock.close()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_service(
    root: Path, model_dir: str, threads: int, timeout: float = 120.0, cmd: list[str] | None = None
) -> tuple[subprocess.Popen, int]:
    """``python -m service`` from source tree ``root`` on a free loopback port, once /readyz is 200
    (``cmd``: another server command line, ``--port`` appended, answering 200 to GET /readyz)."""
    port = _free_port()
    if cmd is None:
        cmd = [sys.executable, "-m", "service", "--threads", str(threads), "--model-dir", model_dir]
    cmd = [*cmd, "--port", str(port)]
    proc = subprocess.Popen(
        cmd, cwd=root, env={**os.environ, "PYTHONPATH": str(root)}, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"service from {root} exited with {proc.returncode}")
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=1) as s:
                s.sendall(b"GET /readyz HTTP/1.1\r\nhost: x\r\nconnection: close\r\n\r\n")
                if s.recv(64).startswith(b"HTTP/1.1 200"):
                    return proc, port
        except OSError:
            pass
        time.sleep(0.2)
    proc.kill()
    raise RuntimeError(f"service from {root} did not become ready within {timeout:g} s")


@dataclass(frozen=True)
class Task:
    """One row: ``fn(prepare())`` is timed (``prepare``, e.g. making a fresh body, is not);
    ``cpu()`` reads the CPU seconds of whoever does the work (this thread, or the service)."""

    fn: Callable
    prepare: Callable | None = None
    cpu: Callable[[], float] = time.thread_time


def process_cpu_seconds(pid: int) -> float:
    """CPU seconds of every thread of process ``pid`` so far (/proc/<pid>/task/*/schedstat, ns; Linux)."""
    total = 0
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/schedstat") as f:
                total += int(f.read().split()[0])
        except (OSError, ValueError, IndexError):
            pass  # a thread that ended meanwhile
    return total / 1e9


def model_seconds(port: int) -> dict[str, tuple[float, float]]:
    """(sum of seconds, count) of the service's own encoder and head timings (its /metrics)."""
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(b"GET /metrics HTTP/1.1\r\nhost: x\r\nconnection: close\r\n\r\n")
        text = b"".join(iter(lambda: s.recv(65536), b"")).decode("utf-8", "replace")
    out = {}
    for name in ("encoder", "head"):
        vals = {}
        for line in text.splitlines():
            for part in ("sum", "count"):
                if line.startswith(f"vgq_{name}_seconds_{part} "):
                    vals[part] = float(line.split()[-1])
        out[name] = (vals.get("sum", 0.0), vals.get("count", 0.0))
    return out


def _clock(task: Task) -> tuple[float, float]:
    """(wall seconds, CPU seconds) of one call of ``task``."""
    arg = task.prepare() if task.prepare else None
    c = task.cpu()
    t = time.perf_counter()
    task.fn(arg) if task.prepare else task.fn()
    t = time.perf_counter() - t
    return t, task.cpu() - c


def http_calls(port: int, fresh: FreshImages, grasps: np.ndarray) -> dict:
    """The two timed HTTP calls of one service: name -> zero-argument function (checks its answer)."""
    http = BlockingHTTP(port)
    k = len(grasps)
    gbytes = np.ascontiguousarray(grasps, "<f4").tobytes()
    status, answer = http.post("/v1/images", fresh.next_npy(), NPY, accept="application/json")
    if status != 200:
        raise RuntimeError(f"upload answered {status}: {answer[:200]!r}")
    path = f"/v1/images/{json.loads(answer)['image_id']}/scores"

    def check(status: int, answer: bytes) -> None:
        if status != 200 or len(answer) != 4 * k:
            raise RuntimeError(f"answer {status} of {len(answer)} bytes: {answer[:200]!r}")

    def cached():
        check(*http.post(path, gbytes, OCTET))

    cached()  # encodes the image's windows: every timed call is head only

    def one_shot(body: bytes):
        check(*http.post("/v1/score", body, NPZ))

    def next_npz() -> bytes:
        return fresh.next_npz(grasps)

    return {"HTTP one-shot": Task(one_shot, next_npz), "HTTP cached score": Task(cached)}, http


def floor_calls(port: int, fresh: FreshImages, grasps: np.ndarray) -> dict:
    """The floor rows: the one-shot and cached-score bodies and answer sizes against ``floor_app``."""
    http = BlockingHTTP(port)
    gbytes = np.ascontiguousarray(grasps, "<f4").tobytes()
    answer = f"x-answer-bytes: {4 * len(grasps)}\r\n"

    def call(body: bytes, content_type: str):
        status, out = http.post("/", body, content_type, extra=answer)
        if status != 200 or len(out) != 4 * len(grasps):
            raise RuntimeError(f"floor answer {status} of {len(out)} bytes")

    return {
        "HTTP floor: one-shot": Task(lambda body: call(body, NPZ), lambda: fresh.next_npz(grasps)),
        "HTTP floor: cached score": Task(lambda: call(gbytes, OCTET)),
    }, http


def in_process_calls(model_dir: str, threads: int, k: int) -> dict:
    """The model and route-step rows, in this process."""
    from export.benchmark import fast_preprocess
    from service.config import Settings
    from service.routes import score_cached, score_one_shot
    from service.scoring import Service

    svc = Service(Settings(model_dir=model_dir, threads=threads, cache_entries=64, log_level="warning"))
    svc.load()
    if not svc.ready:
        raise RuntimeError(f"cannot load the model: {svc.load_error}")
    model = svc.model
    work = load_workload(k)
    depth, grasps = work.depth, work.grasps.astype(np.float64)
    center = np.array([(depth.shape[1] - 1) / 2, (depth.shape[0] - 1) / 2])
    crop, poses = fast_preprocess(depth, grasps, model.geometry, center)
    crop = crop[0, 0]
    if model.card.placement_columns:  # a placement head reads each grasp's row after its pose columns
        from service import placement

        rows = placement.rows(placement.analyse(depth, model.card.intrinsics), grasps)
        poses = np.c_[poses, rows].astype(np.float32)
    term = model.encode(crop)
    fresh = FreshImages(depth, seed=1)
    gbytes = np.ascontiguousarray(work.grasps, "<f4").tobytes()
    first = score_one_shot(svc, fresh.next_npz(work.grasps), NPZ, OCTET, False)
    key = first.headers["x-image-id"]
    return {
        "model encoder + head": Task(lambda: model.score(model.encode(crop), poses)),
        "model head": Task(lambda: model.score(term, poses)),
        "steps one-shot": Task(
            lambda body: score_one_shot(svc, body, NPZ, OCTET, False), lambda: fresh.next_npz(work.grasps)
        ),
        "steps cached score": Task(lambda: score_cached(svc, key, gbytes, OCTET, OCTET, False)),
    }


def measure(tasks: dict[str, Task], rounds: int, calls: int, warmup: int = 10) -> dict[str, np.ndarray]:
    """Each task ``calls`` times per round, tasks in turn, ``rounds`` rounds: (n, 2) wall and
    CPU seconds per call."""
    for task in tasks.values():
        for _ in range(warmup):
            _clock(task)
    out = {name: [] for name in tasks}
    for _ in range(rounds):
        for name, task in tasks.items():
            out[name] += [_clock(task) for _ in range(calls)]
    return {name: np.asarray(v) for name, v in out.items()}


def report(times: dict[str, np.ndarray], services: list[str]) -> dict:
    """Medians (wall), p90 (wall), mean CPU per call (this thread in process, the service's
    process over HTTP), and issue 14's ratios from wall medians and from CPU means."""
    ms = {name: float(np.median(t[:, 0]) * 1e3) for name, t in times.items()}
    cpu = {name: float(np.mean(t[:, 1]) * 1e3) for name, t in times.items()}
    out = {
        "median_ms": ms,
        "p90_ms": {n: float(np.percentile(t[:, 0], 90) * 1e3) for n, t in times.items()},
        "mean_ms": {n: float(np.mean(t[:, 0]) * 1e3) for n, t in times.items()},
        "cpu_mean_ms": cpu,
    }

    def ratios(one_shot: str, cached: str) -> dict:
        return {
            "one_shot_over_model": ms[one_shot] / ms["model encoder + head"],
            "cached_minus_head_ms": ms[cached] - ms["model head"],
            "cpu_one_shot_over_model": cpu[one_shot] / cpu["model encoder + head"],
            "cpu_cached_minus_head_ms": cpu[cached] - cpu["model head"],
        }

    out["steps"] = ratios("steps one-shot", "steps cached score")
    out["services"] = {s: ratios(f"{s}: HTTP one-shot", f"{s}: HTTP cached score") for s in services}
    if "HTTP floor: one-shot" in ms:  # the model's time plus uvicorn's alone: the best reachable
        floor_one, floor_cached = ms["HTTP floor: one-shot"], ms["HTTP floor: cached score"]
        out["floor"] = {
            "one_shot_over_model": (ms["model encoder + head"] + floor_one) / ms["model encoder + head"],
            "cached_minus_head_ms": floor_cached,
        }
    return out


def table(rep: dict, config: dict) -> str:
    lines = [
        f"k = {config['k']}, {config['threads']} onnxruntime thread(s), {config['rounds']} rounds x "
        f"{config['calls']} calls per row; load average {config['load_before']} -> {config['load_after']}; "
        f"{config['date']}",
        "",
        "| row | median ms | p90 ms | mean ms | CPU ms / call (mean; HTTP: the service process) |",
        "|---|---:|---:|---:|---:|",
    ]
    for name, m in rep["median_ms"].items():
        lines.append(
            f"| {name} | {m:.2f} | {rep['p90_ms'][name]:.2f} | {rep['mean_ms'][name]:.2f} | "
            f"{rep['cpu_mean_ms'][name]:.2f} |"
        )

    def line(name: str, r: dict, what: str) -> str:
        return (
            f"{name}: {what} one-shot / model encoder + head = {r['one_shot_over_model']:.2f}x wall p50 "
            f"({r['cpu_one_shot_over_model']:.2f}x CPU); {what} cached score - model head = "
            f"{r['cached_minus_head_ms']:+.2f} ms wall p50 ({r['cpu_cached_minus_head_ms']:+.2f} ms CPU)"
        )

    for name, m in rep.get("service_model_mean_ms", {}).items():
        lines.append(
            f"| {name}: the service's own encoder / head time (its /metrics) | | | "
            + " / ".join("-" if m[p] is None else f"{m[p]:.2f}" for p in ("encoder", "head"))
            + " | |"
        )
    lines += ["", line("in process", rep["steps"], "steps")]
    lines += [line(name, r, "HTTP") for name, r in rep["services"].items()]
    if "floor" in rep:
        f = rep["floor"]
        lines.append(
            f"model + floor (uvicorn with no app work): one-shot {f['one_shot_over_model']:.2f}x, "
            f"cached score {f['cached_minus_head_ms']:+.2f} ms"
        )
    lines.append("targets (issue 14): HTTP one-shot <= 1.5x, HTTP cached score <= +0.5 ms")
    return "\n".join(lines)


def _service_arg(text: str) -> tuple[str, Path]:
    name, sep, root = text.partition("=")
    if not sep or not name or not (Path(root or ".") / "service" / "__main__.py").is_file():
        raise argparse.ArgumentTypeError(
            f"--service must be NAME=ROOT with ROOT a source tree holding service/, got {text!r}"
        )
    return name, Path(root or ".").resolve()


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(
        prog="python -m tools.loadtest.overhead",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--model-dir", default=str(ROOT / "models" / "fast-vgqcnn-default"))
    p.add_argument("--k", type=int, default=128, help="grasps per call (default 128)")
    p.add_argument("--threads", type=int, default=1, help="onnxruntime threads, in process and in each service")
    p.add_argument("--rounds", type=int, default=10)
    p.add_argument("--calls", type=int, default=30, help="calls per row per round")
    p.add_argument("--service", type=_service_arg, action="append", help="NAME=ROOT (repeatable; default this=.)")
    p.add_argument("--json", help="also write the report as JSON to this file")
    a = p.parse_args(argv)
    if min(a.k, a.threads, a.rounds, a.calls) < 1:
        p.error("--k, --threads, --rounds and --calls must be >= 1")
    if not Path(a.model_dir, "model_card.json").is_file():
        p.error(f"--model-dir {a.model_dir!r} holds no model_card.json")
    services = a.service or [("this", ROOT)]
    if len({n for n, _ in services}) != len(services):
        p.error("--service names must differ")
    load_before = round(os.getloadavg()[0], 2)
    procs, conns, ports = [], [], []
    try:
        tasks = in_process_calls(a.model_dir, a.threads, a.k)
        work = load_workload(a.k)
        for i, (name, root) in enumerate(services):
            proc, port = start_service(root, str(Path(a.model_dir).resolve()), a.threads)
            procs.append(proc)
            ports.append(port)
            calls, http = http_calls(port, FreshImages(work.depth, seed=10 + i), work.grasps)
            conns.append(http)
            cpu = functools.partial(process_cpu_seconds, proc.pid)
            tasks.update({f"{name}: {row}": dataclasses.replace(t, cpu=cpu) for row, t in calls.items()})
        floor = [sys.executable, "-m", "uvicorn", "tools.loadtest.floor_app:app", "--loop", "uvloop"]
        proc, port = start_service(ROOT, "", 1, cmd=[*floor, "--http", "httptools", "--log-level", "warning"])
        procs.append(proc)
        calls, http = floor_calls(port, FreshImages(work.depth, seed=99), work.grasps)
        conns.append(http)
        cpu = functools.partial(process_cpu_seconds, proc.pid)
        tasks.update({row: dataclasses.replace(t, cpu=cpu) for row, t in calls.items()})
        before = [model_seconds(port) for port in ports]
        times = measure(tasks, a.rounds, a.calls)
        served = {}
        for (name, _), port, b in zip(services, ports, before):
            after = model_seconds(port)
            served[name] = {
                part: ((after[part][0] - b[part][0]) / (after[part][1] - b[part][1]) * 1e3)
                if after[part][1] > b[part][1]
                else None
                for part in ("encoder", "head")
            }
    finally:
        for c in conns:
            c.close()
        for proc in procs:
            proc.terminate()
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
    config = {
        "k": a.k,
        "threads": a.threads,
        "rounds": a.rounds,
        "calls": a.calls,
        "services": {n: str(r) for n, r in services},
        "model_dir": a.model_dir,
        "load_before": load_before,
        "load_after": round(os.getloadavg()[0], 2),
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
    }
    rep = {**report(times, [n for n, _ in services]), "service_model_mean_ms": served, "config": config}
    print(table(rep, config))
    if a.json:
        Path(a.json).write_text(json.dumps(rep, indent=2) + "\n")
    return rep


if __name__ == "__main__":
    main()
