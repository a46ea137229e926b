"""The scale-out topology of deploy/ without Docker: nginx (deploy/nginx/proxy.conf) in front of
two service processes sharing a redis-server, all on loopback ports. Uploads on one replica are
scored on the other; the load test runs through the balancer; a replica killed mid-load costs no
request the client does not see (nginx retries it on the other replica)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import threading
import time
from contextlib import ExitStack, contextmanager
from pathlib import Path

import httpx
import numpy as np
import pytest
import yaml

from conftest import table_scene
from servers import free_port, grasps_at
from service.client import ServiceClient

ROOT = Path(__file__).resolve().parent.parent
DEPLOY = ROOT / "deploy"
IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")


def need(binary: str, package: str) -> str:
    """Path of ``binary``; in CI (CI=true) a missing one fails the test, elsewhere it skips."""
    path = shutil.which(binary) or next((p for p in (f"/usr/sbin/{binary}", f"/usr/local/sbin/{binary}") if os.access(p, os.X_OK)), None)
    if path is None:
        msg = f"{binary} not installed (apt-get install -y {package}; .ci/run installs it)"
        pytest.fail(msg) if IN_CI else pytest.skip(msg)
    return path


def wait_until(ok, what: str, timeout: float = 60.0, proc: subprocess.Popen | None = None) -> None:
    deadline = time.monotonic() + timeout
    while True:
        if proc is not None and proc.poll() is not None:
            out = proc.stdout.read().decode(errors="replace")[-2000:] if proc.stdout else ""
            raise RuntimeError(f"{what}: process exited with {proc.returncode}: {out}")
        try:
            if ok():
                return
        except (httpx.HTTPError, OSError):
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
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, **kw)
    try:
        yield proc
    finally:
        stop(proc)


def replica(stack: ExitStack, model_dir, redis_url: str) -> tuple[str, subprocess.Popen]:
    port = free_port()
    env = {**os.environ, "PYTHONPATH": str(ROOT), "VGQ_CACHE_BACKEND": "redis", "VGQ_REDIS_URL": redis_url}
    proc = stack.enter_context(process([sys.executable, "-m", "service", "--model-dir", str(model_dir), "--port", str(port),
                                        "--threads", "1"], cwd=ROOT, env=env))
    url = f"http://127.0.0.1:{port}"
    wait_until(lambda: httpx.get(url + "/readyz", timeout=1).status_code == 200, "service replica", proc=proc)
    return url, proc


def nginx_conf(tmp: Path, port: int, upstreams: list[str]) -> str:
    """nginx.conf of the test: the upstream block of deploy/nginx/nginx.conf with loopback
    replicas, the deployed proxy settings (included), state and logs under ``tmp``."""
    servers = "\n".join(f"        server {u.removeprefix('http://')} max_fails=1 fail_timeout=2s;" for u in upstreams)
    temp = "\n".join(f"    {name}_temp_path {tmp / name};" for name in ("client_body", "proxy", "fastcgi", "uwsgi", "scgi"))
    # as root, keep the worker root too: it must reach the temp folders under pytest's 0700 tmp dir
    user = "user root root;\n" if os.geteuid() == 0 else ""
    return f"""{user}daemon off;
worker_processes 1;
pid {tmp / 'nginx.pid'};
error_log {tmp / 'error.log'} warn;
events {{ worker_connections 512; }}
http {{
{temp}
    log_format upstreams '$request_method $uri $status upstream=$upstream_addr status=$upstream_status';
    access_log {tmp / 'access.log'} upstreams;
    upstream vgq {{
        least_conn;
{servers}
        keepalive 16;
    }}
    server {{
        listen 127.0.0.1:{port};
        location / {{
            proxy_pass http://vgq;
            include {DEPLOY / 'nginx' / 'proxy.conf'};
        }}
    }}
}}
"""


@contextmanager
def topology(model_dir, tmp: Path):
    """redis-server + 2 replicas + nginx; yields (balancer url, [(replica url, process)] x 2, access log)."""
    nginx = need("nginx", "nginx-light")
    need("redis-server", "redis-server")
    from test_service_redis import redis_server

    with ExitStack() as stack:
        rurl, _ = stack.enter_context(redis_server())
        reps = [replica(stack, model_dir, rurl) for _ in range(2)]
        port = free_port()
        tmp.mkdir(parents=True, exist_ok=True)
        (tmp / "nginx.conf").write_text(nginx_conf(tmp, port, [u for u, _ in reps]))
        proc = stack.enter_context(process([nginx, "-p", str(tmp), "-c", str(tmp / "nginx.conf")]))
        lb = f"http://127.0.0.1:{port}"
        wait_until(lambda: httpx.get(lb + "/readyz", timeout=1).status_code == 200, "nginx", timeout=20, proc=proc)
        yield lb, reps, tmp / "access.log"


@pytest.fixture(scope="module")
def topo(model_dir, tmp_path_factory):
    with topology(model_dir, tmp_path_factory.mktemp("lb")) as t:
        yield t


def test_upload_on_one_replica_is_scored_on_the_other_and_through_the_balancer(topo):
    lb, ((a, _), (b, _)), _ = topo
    depth, g = table_scene() + 0.011, grasps_at(k=32)
    with ServiceClient(a) as ca, ServiceClient(b) as cb, ServiceClient(lb) as clb:
        iid = ca.upload(depth)
        pa = ca.score(iid, g)
        assert np.allclose(cb.score(iid, g), pa, atol=1e-6)
        assert np.allclose(clb.score(iid, g), pa, atol=1e-6)


def test_balancer_spreads_requests_over_both_replicas(topo):
    lb, reps, log = topo
    with httpx.Client(base_url=lb) as c:
        assert all(c.get("/v1/model").status_code == 200 for _ in range(20))
    used = {m for m in re.findall(r"upstream=(\S+)", log.read_text())}
    assert {u.removeprefix("http://") for u, _ in reps} <= used


def test_loadtest_through_the_balancer_has_no_errors(topo):
    from tools.loadtest.cli import main

    lb, _, _ = topo
    report = main(["--url", lb, "--clients", "4", "--duration", "3", "--warmup", "0.5", "--k", "32",
                   "--mix", "upload=1,score=2,once=1"])
    assert report["errors"] == 0, report["error_messages"]
    assert all(e["requests"] > 0 for e in report["endpoints"].values()) and report["grasps_per_s"] > 0


def test_killing_a_replica_mid_load_loses_no_request_silently(model_dir, tmp_path):
    """Kill -9 one replica while 4 clients load the balancer: nginx resends what was in flight
    (and what it sends before it marks the replica down) to the other one. Every request the
    clients sent is in nginx's log, and each was either answered or counted as an error by the
    client; with the retry none fails."""
    from tools.loadtest.cli import main

    with topology(model_dir, tmp_path / "lb") as (lb, ((a, proc_a), _), log):
        out = {}
        load = threading.Thread(target=lambda: out.setdefault("report", main(
            ["--url", lb, "--clients", "4", "--duration", "4", "--warmup", "0", "--k", "32", "--mix", "upload=1,score=4,once=1"])))
        load.start()
        time.sleep(1.5)
        proc_a.kill()
        proc_a.wait(5)
        load.join(60)
        assert not load.is_alive() and "report" in out
        report = out["report"]
        time.sleep(0.2)  # nginx writes the last log lines
        lines = [line for line in log.read_text().splitlines() if line.startswith("POST ")]
    assert len(lines) == report["requests"] + report["errors"]  # no request vanished between client and nginx
    assert report["errors"] == 0, report["error_messages"]
    retried = [line for line in lines if ", " in line.partition("upstream=")[2]]
    assert retried, "no request was retried on the other replica after the kill"
    assert all(line.split()[2] == "200" for line in retried)
    assert a.removeprefix("http://") in retried[0]


# ---- the deployment files -----------------------------------------------------------------------------
def test_compose_runs_replicas_behind_nginx_with_redis():
    c = yaml.safe_load((DEPLOY / "docker-compose.yml").read_text())["services"]
    assert set(c) == {"redis", "service", "nginx"}
    assert c["service"]["environment"]["VGQ_CACHE_BACKEND"] == "redis" and "redis:6379" in c["service"]["environment"]["VGQ_REDIS_URL"]
    assert c["service"]["deploy"]["replicas"] >= 2
    mounts = " ".join(c["nginx"]["volumes"])
    assert "nginx/proxy.conf:/etc/nginx/vgq-proxy.conf" in mounts and "nginx/nginx.conf:/etc/nginx/nginx.conf" in mounts
    conf = (DEPLOY / "nginx" / "nginx.conf").read_text()
    assert "include /etc/nginx/vgq-proxy.conf;" in conf and "server service:8000" in conf
    assert "proxy_next_upstream error timeout http_502 http_503 non_idempotent;" in (DEPLOY / "nginx" / "proxy.conf").read_text()


def test_kubernetes_manifests_probe_scale_and_share_redis():
    docs = [d for f in sorted((DEPLOY / "k8s").glob("*.yaml")) if f.name != "kustomization.yaml"
            for d in yaml.safe_load_all(f.read_text())]
    by = {(d["kind"], d["metadata"]["name"]): d for d in docs}
    dep = by[("Deployment", "vgq-service")]["spec"]["template"]["spec"]["containers"][0]
    assert dep["readinessProbe"]["httpGet"]["path"] == "/readyz" and dep["livenessProbe"]["httpGet"]["path"] == "/healthz"
    env = {e["name"]: e["value"] for e in dep["env"]}
    assert env["VGQ_CACHE_BACKEND"] == "redis" and "vgq-redis:6379" in env["VGQ_REDIS_URL"]
    assert ("Service", "vgq-service") in by and ("Deployment", "vgq-redis") in by and ("Service", "vgq-redis") in by
    hpa = by[("HorizontalPodAutoscaler", "vgq-service")]["spec"]
    assert hpa["scaleTargetRef"]["name"] == "vgq-service" and hpa["metrics"][0]["resource"]["name"] == "cpu"
    assert dep["resources"]["requests"]["cpu"]  # CPU utilisation is relative to the request
    kust = yaml.safe_load((DEPLOY / "k8s" / "kustomization.yaml").read_text())
    assert sorted(kust["resources"]) == sorted(f.name for f in (DEPLOY / "k8s").glob("*.yaml") if f.name != "kustomization.yaml")
