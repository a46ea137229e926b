"""Where the Python of a cached score call goes, in process: CPU microseconds per call (the
minimum over repeats, so load from other processes on the machine counts least) of the route's
steps, each step alone, and the same without the head (its ONNX call replaced by its answer).

    python -m tools.loadtest.breakdown                                   # this checkout
    python -m tools.loadtest.breakdown --service before=/tmp/base --service after=.   # A/B

With ``--service NAME=ROOT`` (repeatable) each source tree is measured in its own process,
trees taking turns for ``--rounds`` rounds (the minimum over all of a tree's rounds is kept),
and every tree's binary answer is checked to be the same bytes. The call: k grasps (default 128)
as float32 against an image uploaded (one-shot) and scored once before timing, so its window is
encoded and cached (``service.routes.score_cached``, Accept: application/octet-stream).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
import timeit
from pathlib import Path

from tools.loadtest.workload import ROOT, FreshImages, load_workload  # absolute: the worker runs as a script

OCTET, NPZ = "application/octet-stream", "application/x-npz"


def measure(model_dir: str, k: int, number: int, repeat: int) -> tuple[dict, bytes]:
    """(step -> CPU us per call, the binary answer) in this process, for the source tree on sys.path."""
    import numpy as np

    from service.config import Settings
    from service.grasps import parse_binary
    from service.routes import score_cached, score_one_shot
    from service.scoring import Service
    from vgq.ood import ood_flags

    svc = Service(Settings(model_dir=model_dir, threads=1, cache_entries=64, log_level="warning"))
    svc.load()
    if not svc.ready:
        raise RuntimeError(f"cannot load the model: {svc.load_error}")
    work = load_workload(k)
    first = score_one_shot(svc, FreshImages(work.depth, seed=1).next_npz(work.grasps), NPZ, OCTET, False)
    key = first.headers["x-image-id"]
    entry = svc.cache.get(key)
    body = np.ascontiguousarray(work.grasps, "<f4").tobytes()
    grasps = parse_binary(body)
    placed = svc.place(entry, grasps)
    rows = placed[0]
    term = entry.windows[next(iter(entry.windows))].term
    raw = svc.model.score(term, rows)
    mapped = grasps.copy()
    mapped[:, :2] = placed[2][:, :2]  # (u, v) in the resampled image (older trees returned them alone)

    def cpu_us(fn) -> float:
        return min(timeit.repeat(fn, number=number, repeat=repeat, timer=time.thread_time)) / number * 1e6

    def cached():
        return score_cached(svc, key, body, OCTET, OCTET, False)

    out = {
        "score_cached (route steps)": cpu_us(cached),
        "model head": cpu_us(lambda: svc.model.score(term, rows)),
        "Service.place": cpu_us(lambda: svc.place(entry, grasps)),
        "vgq.ood.ood_flags": cpu_us(lambda: ood_flags(mapped, entry.depth, svc.z_range, False)),
        "Calibration.apply": cpu_us(lambda: svc.calibration.apply(raw)) if svc.calibration else float("nan"),
    }
    head = svc.model.score

    def answer(term, rows):  # the head's answer without running it: only the Python around it is timed
        svc.model.score_seconds = 1e-3
        return raw

    svc.model.score = answer
    try:
        out["Service.score without the head"] = cpu_us(lambda: svc.score(key, entry, grasps, False, placed))
        out["score_cached without the head"] = cpu_us(cached)
        out["ASGI app without the head"] = asgi_us(svc, key, body, number, repeat)
    finally:
        svc.model.score = head
    return out, bytes(cached().body)


def asgi_us(svc, key: str, body: bytes, number: int, repeat: int) -> float:
    """CPU us per call of the whole ASGI app (FastAPI, the limits middleware, the scoring fast
    path, the route's steps) on ``svc``, called as uvicorn calls it (the scope its protocol
    builds for a request whose body came with its headers), on uvloop; no socket, no uvicorn."""

    import uvloop

    from service.app import create_app

    app = create_app(svc.settings, svc.model, svc.cache)
    app.state.service = svc  # the loaded service: its cache holds the image
    path = f"/v1/images/{key}/scores"
    headers = [
        (b"host", b"127.0.0.1:8000"),
        (b"content-type", OCTET.encode()),
        (b"accept", OCTET.encode()),
        (b"content-length", str(len(body)).encode()),
    ]

    async def call() -> None:
        scope = {
            "type": "http",
            "asgi": {"version": "3.0", "spec_version": "2.3"},
            "http_version": "1.1",
            "server": ("127.0.0.1", 8000),
            "client": ("127.0.0.1", 50000),
            "scheme": "http",
            "method": "POST",
            "root_path": "",
            "path": path,
            "raw_path": path.encode(),
            "query_string": b"",
            "headers": headers,
            "state": {},
            "vgq.t0": time.perf_counter(),
            "vgq.body_complete": True,  # what service.protocol sets when the body came with the headers
        }
        messages = [{"type": "http.request", "body": body, "more_body": False}]

        async def receive():
            return messages.pop() if messages else {"type": "http.disconnect"}

        sent = []

        async def send(message):
            sent.append(message)

        await app(scope, receive, send)
        if sent[0]["status"] != 200:
            raise RuntimeError(f"the app answered {sent[0]['status']}: {sent[-1].get('body', b'')[:200]!r}")

    async def timed() -> float:
        best = float("inf")
        for _ in range(repeat):
            t = time.thread_time()
            for _ in range(number):
                await call()
            best = min(best, (time.thread_time() - t) / number * 1e6)
        return best

    return uvloop.run(timed())


def _service_arg(text: str) -> tuple[str, Path]:
    name, sep, root = text.partition("=")
    if not sep or not name or not (Path(root or ".") / "service" / "scoring.py").is_file():
        raise argparse.ArgumentTypeError(f"--service must be NAME=ROOT with ROOT a source tree, got {text!r}")
    return name, Path(root or ".").resolve()


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(
        prog="python -m tools.loadtest.breakdown",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--model-dir", default=str(ROOT / "models" / "fast-vgqcnn-default"))
    p.add_argument("--k", type=int, default=128)
    p.add_argument("--number", type=int, default=200, help="calls per timing (default 200)")
    p.add_argument("--repeat", type=int, default=7, help="timings per step per round; the minimum is kept")
    p.add_argument("--rounds", type=int, default=3, help="turns per source tree (with --service)")
    p.add_argument("--service", type=_service_arg, action="append", help="NAME=ROOT (repeatable)")
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if min(a.k, a.number, a.repeat, a.rounds) < 1:
        p.error("--k, --number, --repeat and --rounds must be >= 1")
    model_dir = str(Path(a.model_dir).resolve())
    if a.worker:  # one tree's turn, in its own process: JSON on stdout
        res, answer = measure(model_dir, a.k, a.number, a.repeat)
        print(json.dumps({"us": res, "answer": answer.hex()}))
        return res
    trees = a.service or [("this", ROOT)]
    best: dict[str, dict[str, float]] = {name: {} for name, _ in trees}
    answers = {}
    for _ in range(a.rounds):
        for name, root in trees:
            # this file as a script in the tree's own environment: its service, vgq and workload
            cmd = [sys.executable, __file__, "--worker", "--model-dir", model_dir]
            cmd += ["--k", str(a.k), "--number", str(a.number), "--repeat", str(a.repeat)]
            env = {**os.environ, "PYTHONPATH": str(root)}
            done = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True, check=False)
            if done.returncode != 0:
                raise SystemExit(f"{name}: the measurement failed:\n{done.stderr[-2000:]}")
            got = json.loads(done.stdout.strip().splitlines()[-1])
            answers[name] = got["answer"]
            for step, us in got["us"].items():
                best[name][step] = min(best[name].get(step, float("inf")), us)
    names = [n for n, _ in trees]
    steps = list(best[names[0]])
    print(f"k = {a.k}; CPU us per call, minimum of {a.rounds} x {a.repeat} timings of {a.number} calls")
    print("| step | " + " | ".join(names) + (f" | {names[-1]} - {names[0]} |" if len(names) > 1 else " |"))
    print("|---|" + "---:|" * (len(names) + (len(names) > 1)))
    for step in steps:
        vals = [best[n][step] for n in names]
        diff = f" | {vals[-1] - vals[0]:+.1f}" if len(names) > 1 else ""
        print(f"| {step} | " + " | ".join(f"{v:.1f}" for v in vals) + diff + " |")
    same = len(set(answers.values())) == 1
    print("binary answers identical across trees: " + ("yes" if same else "NO"))
    return {"us": best, "answers_identical": same}


if __name__ == "__main__":
    main()
