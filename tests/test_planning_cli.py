"""vgq-plan: grasps as JSON and an overlay PNG; bad input exits 2 with one line."""

import json
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

pytest.importorskip("trimesh")

from tests.planning_scenes import boxes_scene


def _run(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "planning", *map(str, args)], capture_output=True, text=True, timeout=120
    )


@pytest.fixture(scope="module")
def depth_file(tmp_path_factory):
    d = tmp_path_factory.mktemp("plan")
    depth, _, _ = boxes_scene()
    np.save(d / "depth.npy", depth)
    Image.fromarray(np.round(depth * 1000).astype(np.uint16)).save(d / "depth.png")
    return d


@pytest.mark.parametrize("name", ["depth.npy", "depth.png"])
def test_cli_writes_grasps_and_an_overlay(depth_file, name, tmp_path):
    out, png = tmp_path / "grasps.json", tmp_path / "overlay.png"
    r = _run(depth_file / name, "--k", 3, "--seed", 1, "--out", out, "--png", png)
    assert r.returncode == 0, r.stderr
    doc = json.loads(out.read_text())
    assert len(doc["grasps"]) == 3 and doc["reason"] is None
    g = doc["grasps"][0]
    assert len(g["row"]) == 7 and np.array(g["pose"]).shape == (4, 4) and np.array(g["contacts"]).shape == (2, 3)
    with Image.open(png) as im:
        assert im.mode == "RGB" and min(im.size) >= 100


@pytest.mark.parametrize(
    "args, words",
    [
        (["--k", "0"], "k"),
        (["--roi", "1,2,3"], "--roi"),
        (["--roi", "500,500,600,600"], "roi"),
        (["--fx", "-5"], "intrinsics"),
        (["--fx", "100"], "intrinsics"),
        (["--model", "/nonexistent"], "model"),
        (["--up", "0", "0", "0"], "up"),
    ],
)
def test_cli_bad_input_exits_2_with_one_line(depth_file, args, words):
    r = _run(depth_file / "depth.npy", *args)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and words in lines[0] and "Traceback" not in r.stderr


def test_cli_level_table_reads_the_up_from_the_table(depth_file, tmp_path):
    out = tmp_path / "g.json"
    r = _run(depth_file / "depth.npy", "--k", 1, "--level", "table", "--out", out)
    assert r.returncode == 0, r.stderr
    level = json.loads(out.read_text())["level"]
    assert level["from"] == "table" and level["roll_deg"] == 0.0 and level["tilt_deg"] == pytest.approx(20.05, abs=0.1)
    r = _run(depth_file / "depth.npy", "--k", 1, "--out", out)
    assert json.loads(out.read_text())["level"] == {"up": None, "roll_deg": 0.0, "tilt_deg": None, "from": None}


@pytest.mark.parametrize(
    "args, words",
    [(["--up", "0", "0", "-1", "--level", "table"], "not allowed with"), (["--level", "floor"], "invalid choice")],
)
def test_cli_usage_errors_exit_2_naming_the_argument(depth_file, args, words):
    r = _run(depth_file / "depth.npy", *args)
    last = r.stderr.strip().splitlines()[-1]
    assert r.returncode == 2 and last.startswith("vgq-plan: error: argument --level") and words in last


def test_cli_level_table_without_a_table_exits_2(tmp_path):
    np.save(tmp_path / "scattered.npy", np.random.default_rng(0).uniform(0.4, 1.2, (300, 300)).astype(np.float32))
    r = _run(tmp_path / "scattered.npy", "--level", "table")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "no table plane" in r.stderr, r.stderr


def test_cli_rejects_missing_and_empty_images(tmp_path):
    np.save(tmp_path / "zeros.npy", np.zeros((300, 300), np.float32))
    (tmp_path / "junk.npy").write_bytes(b"not a numpy file")
    for f, words in (
        (tmp_path / "missing.npy", "not found"),
        (tmp_path / "zeros.npy", "no valid depth"),
        (tmp_path / "junk.npy", "cannot read"),
    ):
        r = _run(f)
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and words in r.stderr, r.stderr
