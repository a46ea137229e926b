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
