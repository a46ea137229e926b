"""/docs (Swagger UI) and /redoc render offline: their scripts and styles come from the
service itself (the fastapi-offline package's files), never a CDN. Headless Chromium (the
Debian package ``chromium``; .ci/run installs it) loads each page with every other host
unresolvable and the rendered DOM must list the service's operations."""

from __future__ import annotations

import re
import shutil
import subprocess

import httpx
import pytest
from servers import running_service

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
OFFLINE = "MAP * ~NOTFOUND, EXCLUDE 127.0.0.1"  # any host but loopback fails to resolve


def rendered_dom(url: str) -> str:
    if CHROMIUM is None:
        pytest.skip("chromium not installed (apt-get install chromium; .ci/run does)")
    r = subprocess.run(
        [
            CHROMIUM,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-dev-shm-usage",
            f"--host-resolver-rules={OFFLINE}",
            "--virtual-time-budget=15000",
            "--dump-dom",
            url,
        ],
        capture_output=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr.decode()[-2000:]
    return r.stdout.decode()


@pytest.fixture(scope="module")
def url(model_dir):
    with running_service(model_dir) as u:
        yield u


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_docs_pages_load_only_local_assets(url, page):
    html = httpx.get(url + page).text
    assets = re.findall(r'(?:src|href)="([^"]+)"', html) + re.findall(r"url: '([^']+)'", html)
    assert assets and all(a.startswith("/") for a in assets), assets
    for a in assets:
        assert httpx.get(url + a).status_code == 200, a


def test_swagger_ui_renders_the_operations_offline(url):
    dom = rendered_dom(url + "/docs")
    assert 'class="swagger-ui' in dom
    for op in ("/v1/images", "/v1/images/{image_id}/scores", "/v1/score", "/healthz", "Upload a depth image"):
        assert op in dom, op


def test_redoc_renders_the_operations_offline(url):
    dom = rendered_dom(url + "/redoc")
    for op in ("Upload a depth image", "Score k grasps against an uploaded image", "One-shot"):
        assert op in dom, op
