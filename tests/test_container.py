"""The service container (Dockerfile), checked statically: slim base, non-root user, the
service's port exposed and health-checked, no torch / training code, and the same install
step as scripts/serve.sh."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest
import tomllib

from service.config import Settings

ROOT = Path(__file__).resolve().parent.parent
TRAINING_ONLY = {"training", "export", "datagen", "tests", "data", "runs", "scripts", ".venv"}


def instructions(text: str) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) of a Dockerfile, continuation lines joined, comments dropped."""
    out, buf = [], ""
    for line in text.splitlines():
        if not buf and (not line.strip() or line.lstrip().startswith("#")):
            continue
        if line.rstrip().endswith("\\"):
            buf += line.rstrip()[:-1] + " "
            continue
        buf += line
        word, _, rest = buf.strip().partition(" ")
        out.append((word.upper(), rest.strip()))
        buf = ""
    return out


@pytest.fixture(scope="module")
def final_stage() -> list[tuple[str, str]]:
    ins = instructions((ROOT / "Dockerfile").read_text())
    last_from = max(i for i, (k, _) in enumerate(ins) if k == "FROM")
    return ins[last_from:]


def args(stage, kind: str) -> list[str]:
    return [a for k, a in stage if k == kind]


def env_of(stage) -> dict[str, str]:
    env = {}
    for a in args(stage, "ENV"):
        for tok in shlex.split(a):
            if "=" in tok:
                k, v = tok.split("=", 1)
                env[k] = v
    return env


def test_base_image_is_slim(final_stage):
    image = final_stage[0][1].split()[0]
    assert re.fullmatch(r"python:3\.\d+-slim(-\w+)?", image), image


def test_runs_as_a_non_root_user(final_stage):
    users = args(final_stage, "USER")
    assert users, "no USER instruction: the container would run as root"
    user = users[-1].split(":")[0]
    assert user not in ("root", "0")
    created = re.findall(r"useradd\b[^&;]*?--uid (\d+)[^&;]*?\s(\w+)\s*(?:&&|;|$)", " ".join(args(final_stage, "RUN")))
    assert any(user in (uid, name) for uid, name in created), f"USER {user} is not created by useradd: {created}"


def test_exposes_and_health_checks_the_port_the_service_listens_on(final_stage):
    port = env_of(final_stage).get("VGQ_PORT", str(Settings().port))
    assert env_of(final_stage).get("VGQ_HOST") == "0.0.0.0"  # reachable from outside the container
    assert port in " ".join(args(final_stage, "EXPOSE")).split()
    health = args(final_stage, "HEALTHCHECK")
    assert health and f":{port}/readyz" in health[-1]


def test_copies_no_training_code_and_installs_no_torch(final_stage):
    for a in args(final_stage, "COPY") + args(final_stage, "ADD"):
        parts = [p for p in shlex.split(a) if not p.startswith("--")]
        for src in parts[:-1]:
            top = src.strip("./").split("/")[0]
            assert src.strip() not in (".", "./"), "COPY . would bring the whole repository (training code, data)"
            assert top not in TRAINING_ONLY, f"COPY {src}"
    runs = " ".join(args(final_stage, "RUN"))
    assert "torch" not in runs and "[all]" not in runs and "[train]" not in runs
    service_deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]["service"]
    assert not any(d.lower().startswith("torch") for d in service_deps)


def test_installs_the_same_extra_as_serve_sh(final_stage):
    def extras(text: str) -> set[str]:
        return set(re.findall(r"pip install[^\n]*?\.\[([\w,]+)\]", text))

    docker = extras(" ".join(args(final_stage, "RUN")))
    serve = extras((ROOT / "scripts" / "serve.sh").read_text())
    assert docker == serve == {"service"}


def test_model_directory_comes_from_configuration(final_stage):
    model_dir = env_of(final_stage)["VGQ_MODEL_DIR"]
    copied = [shlex.split(a)[-1] for a in args(final_stage, "COPY")]
    workdir = args(final_stage, "WORKDIR")[-1]
    assert any(str(Path(workdir) / c).rstrip("/") == model_dir.rstrip("/") for c in copied)


def test_copies_every_first_party_package_the_service_imports(final_stage):
    """What ``vgq-serve`` imports (the app, in a fresh interpreter) must be in the image."""
    import subprocess
    import sys

    first_party = {p.parent.name for p in ROOT.glob("*/__init__.py")}
    code = "import sys, service.__main__, service.app; print(' '.join(sorted({m.split('.')[0] for m in sys.modules})))"
    r = subprocess.run(
        [sys.executable, "-c", code],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"},
    )
    assert r.returncode == 0, r.stderr
    imported = set(r.stdout.split()) & first_party
    assert {"service", "vgq", "planning"} <= imported
    copied = {shlex.split(a)[-1].strip("./").split("/")[0] for a in args(final_stage, "COPY")}
    assert imported <= copied, f"the service imports {sorted(imported - copied)}, not copied into the image"
