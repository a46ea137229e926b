"""Per-object generation and the run driver on tiny real runs (pybullet_data meshes)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import skip_or_fail_in_ci

from datagen import storage
from datagen.config import ConfigError, DatagenConfig
from datagen.mesh import mesh_sources
from datagen.pipeline import generate_object, interleaved, object_seed, run_generate
from vgq.schema import GRASP_FIELDS, IMAGE_FIELDS, check_fields

ROOT = Path(__file__).resolve().parents[1]
TINY = {
    "cameras_per_pose": 2,
    "max_stable_poses": 1,
    "antipodal.num_samples": 8,
    "quality.num_samples": 3,
}
TINY_FLAGS = ["--cameras", "2"] + [a for k, v in TINY.items() if k != "cameras_per_pose" for a in ("--set", f"{k}={v}")]


def tiny(**kw) -> DatagenConfig:
    return DatagenConfig().with_overrides({**TINY, **kw})


@pytest.fixture(scope="module")
def first_object():
    cfg = tiny(max_stable_poses=2)
    src = mesh_sources()[0]
    return cfg, src, generate_object(src, cfg, 4, object_seed(0, src.name))


def test_generate_object_fields_follow_the_schema(first_object):
    cfg, _, (images, grasps) = first_object
    n_img = check_fields(IMAGE_FIELDS, images, "images")
    n = check_fields(GRASP_FIELDS, grasps, "grasps")
    assert n_img == 2 * 2  # 2 stable poses x 2 cameras
    assert n > 0
    assert np.all(images["object_id"] == 4)
    assert sorted(set(images["stable_pose_id"].tolist())) == [0, 1]
    assert np.all((grasps["image_index"] >= 0) & (grasps["image_index"] < n_img))
    assert np.all((grasps["u"] >= -0.5) & (grasps["u"] < 299.5) & (grasps["v"] >= -0.5) & (grasps["v"] < 299.5))
    assert np.all(grasps["beta"] <= np.pi / 2 + 1e-6)  # flipped towards the table side
    assert np.all(grasps["quality"][~grasps["collision_free"]] == 0)
    np.testing.assert_allclose(np.linalg.norm(grasps["q"], axis=1), 1, atol=1e-5)
    assert np.all(grasps["q"][:, 0] >= 0)
    phi = images["camera_phi"]
    assert np.all((phi >= 0) & (phi <= np.radians(70)))
    d = images["depth"]
    assert d.dtype == np.float32 and np.all(d > 0)  # table everywhere


def test_same_seed_same_arrays(first_object):
    cfg, src, (images, grasps) = first_object
    images2, grasps2 = generate_object(src, cfg, 4, object_seed(0, src.name))
    for k in images:
        np.testing.assert_array_equal(images[k], images2[k])
    for k in grasps:
        np.testing.assert_array_equal(grasps[k], grasps2[k])
    _, grasps3 = generate_object(src, cfg, 4, object_seed(1, src.name))
    assert not np.array_equal(grasps["omega"][:5], grasps3["omega"][:5])


def test_object_seed_depends_on_run_seed_and_name_only():
    assert object_seed(0, "007") == object_seed(0, "007")
    assert len({object_seed(0, "007"), object_seed(1, "007"), object_seed(0, "008")}) == 3


def _arrays(root: Path) -> dict:
    return {sh.object_id: {**sh.images, **sh.grasps} for sh in storage.open_dataset(root)}


def test_resume_after_sigkill_matches_uninterrupted_run(tmp_path):
    """Kill a real `python -m datagen generate` after its first shard, rerun it: the dataset
    equals an uninterrupted run (made here with a 2-process pool)."""
    out = tmp_path / "killed"
    cmd = [
        sys.executable,
        "-m",
        "datagen",
        "generate",
        "--out",
        str(out),
        "--objects",
        "3",
        "--workers",
        "1",
        "--quiet",
        *TINY_FLAGS,
    ]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.time() + 60
        while time.time() < deadline:
            try:
                m = json.loads((out / "manifest.json").read_text())
                if m["counts"]["objects_done"] + m["counts"]["objects_skipped"] >= 1:
                    break
            except (FileNotFoundError, json.JSONDecodeError):
                pass
            time.sleep(0.01)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
    m = json.loads((out / "manifest.json").read_text())
    assert not m["complete"], "the run finished before it could be killed"
    assert m["counts"]["objects_pending"] >= 1

    rerun = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert rerun.returncode == 0, rerun.stderr
    assert "resuming" in rerun.stdout

    ref = tmp_path / "ref"
    run_generate(ref, tiny(num_objects=3), workers=2, progress=False, log=lambda s: None)
    a, b = _arrays(out), _arrays(ref)
    assert sorted(a) == sorted(b) and len(a) >= 1
    for oid in a:
        for k in a[oid]:
            np.testing.assert_array_equal(a[oid][k], b[oid][k], err_msg=f"object {oid} field {k}")
    m_a = json.loads((out / "manifest.json").read_text())
    m_b = json.loads((ref / "manifest.json").read_text())
    assert m_a["complete"] and m_a["counts"] == m_b["counts"]
    assert [o["status"] for o in m_a["objects"]] == [o["status"] for o in m_b["objects"]]


def test_rerun_with_other_config_is_refused(tmp_path):
    cfg = tiny(num_objects=1)
    run_generate(tmp_path, cfg, progress=False, log=lambda s: None)
    with pytest.raises(ConfigError, match="cameras_per_pose"):
        run_generate(tmp_path, cfg.with_overrides({"cameras_per_pose": 3}), progress=False, log=lambda s: None)
    # the same config again: nothing to do, nothing changes
    before = (tmp_path / "shards" / "obj_00000.npz").read_bytes()
    logs = []
    run_generate(tmp_path, cfg, progress=False, log=logs.append)
    assert any("resuming" in s for s in logs)
    assert (tmp_path / "shards" / "obj_00000.npz").read_bytes() == before


def test_ray_run_writes_the_same_dataset_as_the_local_run(tmp_path):
    """`--ray`: the same per-object tasks on a local Ray instance give identical arrays."""
    try:
        import ray  # noqa: F401
    except ImportError:
        skip_or_fail_in_ci("Ray is not installed: pip install 'vgq-cnn[test]'")
    cfg = tiny(num_objects=2)
    run_generate(tmp_path / "local", cfg, workers=1, progress=False, log=lambda s: None)
    run_generate(tmp_path / "ray", cfg, workers=2, use_ray=True, progress=False, log=lambda s: None)
    a, b = _arrays(tmp_path / "local"), _arrays(tmp_path / "ray")
    assert sorted(a) == sorted(b) and len(a) >= 1
    for oid in a:
        for k in a[oid]:
            np.testing.assert_array_equal(a[oid][k], b[oid][k], err_msg=f"object {oid} field {k}")


def test_pending_objects_run_round_robin_over_families():
    fams = ["random_urdfs"] * 6 + ["mug"] * 3 + ["box"] * 3
    m = {"objects": [{"family": f} for f in fams]}
    order = interleaved(list(range(12)), m)
    assert sorted(order) == list(range(12))
    # any prefix of the work order holds the families in proportion (6 : 3 : 3)
    assert sorted(fams[i] for i in order[:4]) == ["box", "mug", "random_urdfs", "random_urdfs"]
    # within a family the manifest order is kept
    assert [i for i in order if fams[i] == "mug"] == [6, 7, 8]
