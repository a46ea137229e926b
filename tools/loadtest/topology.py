"""The scale-out topology of deploy/ on one machine without Docker: a redis-server, N service
replicas sharing it, and nginx in front (deploy/nginx/proxy.conf included as deployed), all on
free loopback ports. Used by tests/test_deploy_nginx.py and to measure through the balancer:

    python -m tools.loadtest.topology --replicas 2 -- --clients 8 --duration 20
    python -m tools.loadtest.topology --replicas 2 --kill-after 5 -- --clients 8 --duration 15
    python -m tools.loadtest.topology --engine wrk --replicas 2 -- --connections 8 --duration 20

Arguments after ``--`` go to ``python -m tools.loadtest`` (its ``--url`` is the balancer's), or
with ``--engine wrk`` to ``python -m tools.loadtest.wrk`` (cached score calls from wrk, a C load
generator, so the client does not take a core from the replicas).
``--kill-after S`` kills (SIGKILL) the first replica S seconds into the run and then reports how
many requests nginx resent to another replica (from its access log). Needs ``nginx`` and
``redis-server`` (Debian: nginx-light, redis-server).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from contextlib import ExitStack, contextmanager
from pathlib import Path

from .workload import ROOT

PROXY_CONF = ROOT / "deploy" / "nginx" / "proxy.conf"


def find_binary(name: str) -> str | None:
    """``name`` on PATH or in the sbin folders (where Debian puts nginx)."""
    return shutil.which(name) or next(
        (p for p in (f"/usr/sbin/{name}", f"/usr/local/sbin/{name}") if os.access(p, os.X_OK)), None
    )


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until(ok, what: str, timeout: float = 60.0, proc: subprocess.Popen | None = None) -> None:
    """Poll ``ok()`` every 0.1 s until it is true (an exception counts as not yet); RuntimeError
    after ``timeout`` s or when ``proc`` exits."""
    deadline = time.monotonic() + timeout
    while True:
        if proc is not None and proc.poll() is not None:
            out = proc.stdout.read().decode(errors="replace")[-2000:] if proc.stdout else ""
            raise RuntimeError(f"{what}: process exited with {proc.returncode}: {out}")
        try:
            if ok():
                return
        except Exception:  # connection refused and the like while the server starts
            pass
        if time.monotonic() > deadline:
            raise RuntimeError(f"{what} not ready within {timeout} s")
        time.sleep(0.1)


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


@contextmanager
def process(cmd: list[str], **kw):
    """A subprocess (stdout + stderr piped) stopped on exit."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, **kw)
    try:
        yield proc
    finally:
        stop(proc)


def redis(stack: ExitStack, binary: str = "redis-server") -> str:
    """A throw-away redis-server on loopback (no persistence, 256 MB LRU); returns its URL."""
    import redis as redis_py

    port = free_port()
    proc = stack.enter_context(
        process(
            [
                binary,
                "--port",
                str(port),
                "--bind",
                "127.0.0.1",
                "--save",
                "",
                "--appendonly",
                "no",
                "--maxmemory",
                "256mb",
                "--maxmemory-policy",
                "allkeys-lru",
            ]
        )
    )
    url = f"redis://127.0.0.1:{port}/0"
    wait_until(lambda: redis_py.Redis.from_url(url, socket_timeout=0.2).ping(), "redis-server", 10, proc)
    return url


def replica(stack: ExitStack, model_dir, redis_url: str, *args: str) -> tuple[str, subprocess.Popen]:
    """A ``python -m service`` process with the Redis cache; returns (url, process) once ready."""
    import httpx

    port = free_port()
    env = {**os.environ, "PYTHONPATH": str(ROOT), "VGQ_CACHE_BACKEND": "redis", "VGQ_REDIS_URL": redis_url}
    cmd = [
        sys.executable,
        "-m",
        "service",
        "--port",
        str(port),
        *(["--model-dir", str(model_dir)] if model_dir else []),
        *args,
    ]
    proc = stack.enter_context(process(cmd, cwd=ROOT, env=env))
    url = f"http://127.0.0.1:{port}"
    wait_until(lambda: httpx.get(url + "/readyz", timeout=1).status_code == 200, "service replica", proc=proc)
    return url, proc


def nginx_conf(tmp: Path, port: int, upstreams: list[str]) -> str:
    """nginx.conf: the upstream block of deploy/nginx/nginx.conf with loopback replicas, the
    deployed proxy settings (included), state and logs under ``tmp``."""
    servers = "\n".join(f"        server {u.removeprefix('http://')} max_fails=1 fail_timeout=2s;" for u in upstreams)
    temp = "\n".join(
        f"    {name}_temp_path {tmp / name};" for name in ("client_body", "proxy", "fastcgi", "uwsgi", "scgi")
    )
    # as root, keep the worker root too: it must reach the temp folders under a 0700 tmp dir
    user = "user root root;\n" if os.geteuid() == 0 else ""
    return f"""{user}daemon off;
worker_processes 1;
pid {tmp / "nginx.pid"};
error_log {tmp / "error.log"} warn;
events {{ worker_connections 1024; }}
http {{
{temp}
    log_format upstreams '$request_method $uri $status upstream=$upstream_addr status=$upstream_status';
    access_log {tmp / "access.log"} upstreams;
    upstream vgq {{
        least_conn;
{servers}
        keepalive 32;
    }}
    server {{
        listen 127.0.0.1:{port};
        location / {{
            proxy_pass http://vgq;
            include {PROXY_CONF};
        }}
    }}
}}
"""


@contextmanager
def topology(
    model_dir,
    tmp: Path,
    replicas: int = 2,
    service_args: tuple[str, ...] = ("--threads", "1"),
    nginx: str | None = None,
    redis_server: str | None = None,
):
    """redis-server + ``replicas`` services + nginx; yields (balancer url, [(replica url, process)], access log path)."""
    import httpx

    nginx = nginx or find_binary("nginx")
    redis_server = redis_server or find_binary("redis-server")
    if not nginx or not redis_server:
        raise FileNotFoundError("needs nginx and redis-server (apt-get install -y nginx-light redis-server)")
    with ExitStack() as stack:
        rurl = redis(stack, redis_server)
        reps = [replica(stack, model_dir, rurl, *service_args) for _ in range(replicas)]
        port = free_port()
        tmp.mkdir(parents=True, exist_ok=True)
        (tmp / "nginx.conf").write_text(nginx_conf(tmp, port, [u for u, _ in reps]))
        # -e: the start-up error log too (before nginx.conf is read it would open /var/log/nginx/error.log)
        proc = stack.enter_context(
            process([nginx, "-p", str(tmp), "-e", str(tmp / "error.log"), "-c", str(tmp / "nginx.conf")])
        )
        lb = f"http://127.0.0.1:{port}"
        wait_until(lambda: httpx.get(lb + "/readyz", timeout=1).status_code == 200, "nginx", timeout=20, proc=proc)
        yield lb, reps, tmp / "access.log"


def retried(log: Path) -> list[str]:
    """Access-log lines of requests nginx sent to more than one replica."""
    return [line for line in log.read_text().splitlines() if ", " in line.partition("upstream=")[2]]


def main(argv=None) -> dict:
    argv = list(sys.argv[1:] if argv is None else argv)
    rest = argv[argv.index("--") + 1 :] if "--" in argv else []
    own = argv[: argv.index("--")] if "--" in argv else argv
    p = argparse.ArgumentParser(
        prog="python -m tools.loadtest.topology",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--replicas", type=int, default=2)
    p.add_argument("--model-dir", help="model folder (default: the service's default)")
    p.add_argument("--threads", type=int, default=1, help="onnxruntime threads per replica (default 1)")
    p.add_argument("--kill-after", type=float, help="SIGKILL the first replica this many seconds into the run")
    p.add_argument(
        "--engine",
        choices=("python", "wrk"),
        default="python",
        help="load generator: python (tools.loadtest, any mix) or wrk (cached score calls)",
    )
    a = p.parse_args(own)
    if a.replicas < 1 or a.threads < 0 or (a.kill_after is not None and a.kill_after < 0):
        p.error("--replicas must be >= 1, --threads >= 0, --kill-after >= 0")
    if a.engine == "wrk":
        from .wrk import main as loadtest
    else:
        from .cli import main as loadtest

    with tempfile.TemporaryDirectory(prefix="vgq-topology-") as tmp:
        try:
            with topology(a.model_dir, Path(tmp), a.replicas, ("--threads", str(a.threads))) as (lb, reps, log):
                print(f"balancer {lb}, replicas {[u for u, _ in reps]}", file=sys.stderr)
                if a.kill_after is not None:
                    threading.Timer(a.kill_after, reps[0][1].kill).start()
                report = loadtest(["--url", lb, *rest])
                time.sleep(0.2)
                posts = sum(1 for line in log.read_text().splitlines() if line.startswith("POST "))
                n_retried = len(retried(log))
        except (FileNotFoundError, RuntimeError) as e:
            print(f"topology: {e}", file=sys.stderr)
            sys.exit(2)
    print(
        f"nginx: {posts} POST requests logged, warm-up included (client, measured: {report['requests']} answered + {report['errors']} errors); "
        f"{n_retried} resent to another replica"
    )
    report["balancer"] = {"posts_logged": posts, "retried": n_retried}
    return report


if __name__ == "__main__":
    main()
