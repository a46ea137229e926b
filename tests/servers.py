"""Start the real service (uvicorn in a subprocess) on a free loopback port for tests."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def running_service(model_dir, *args: str, env: dict | None = None, timeout: float = 60.0):
    """Yield the base URL of a service subprocess once /readyz answers 200."""
    with service_process(model_dir, *args, env=env, timeout=timeout) as (url, _):
        yield url


@contextmanager
def service_process(model_dir, *args: str, env: dict | None = None, timeout: float = 60.0, log_path=None):
    """Yield (base URL, Popen) of a service subprocess once /readyz answers 200; its output goes
    to ``log_path`` when given."""
    port = free_port()
    e = {**os.environ, "PYTHONPATH": str(ROOT), **(env or {})}
    out = open(log_path, "wb") if log_path else subprocess.PIPE
    proc = subprocess.Popen(
        [sys.executable, "-m", "service", "--model-dir", str(model_dir), "--port", str(port), "--threads", "1", *args],
        cwd=ROOT,
        env=e,
        stdout=out,
        stderr=subprocess.STDOUT,
    )
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + timeout
        while True:
            if proc.poll() is not None:
                text = proc.stdout.read() if proc.stdout else open(log_path, "rb").read()
                raise RuntimeError(f"service exited with {proc.returncode}: {text.decode()[-2000:]}")
            try:
                if httpx.get(url + "/readyz", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError("service did not become ready in time")
            time.sleep(0.1)
        yield url, proc
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
        if log_path:
            out.close()


def grasps_at(center=(149.5, 149.5), k=16, seed=0) -> np.ndarray:
    """(k, 7) float32 grasps u, v, z, qw, qx, qy, qz within 30 px of ``center`` (pixels), z 0.66 m,
    random unit quaternions."""
    rng = np.random.default_rng(seed)
    g = np.zeros((k, 7), np.float32)
    g[:, :2] = np.asarray(center) + rng.uniform(-30, 30, (k, 2))
    g[:, 2] = 0.66
    q = rng.standard_normal((k, 4))
    g[:, 3:] = q / np.linalg.norm(q, axis=1, keepdims=True)
    return g
