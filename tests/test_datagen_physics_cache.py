"""datagen.physics_cache: recorded physics trials replayed by a later generation, with the
same dataset as a run that simulates them, and never used where they do not fit."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from datagen import pipeline
from datagen.__main__ import main
from datagen.config import DatagenConfig
from datagen.physics_cache import PhysicsCache, PhysicsCacheError, PoseTrials, config_key, from_dataset
from datagen.storage import open_dataset

OVER = {
    "cameras_per_pose": 2,
    "max_stable_poses": 2,
    "antipodal.num_samples": 10,
    "quality.num_samples": 3,
    "label.kind": "physics",
    "label.trials": 3,
    "label.early_stop": True,
    "mesh.rescale": "keep",
}


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    """A physics-labelled run over two boxes, and its cache."""
    root = tmp_path_factory.mktemp("phys")
    meshes = root / "meshes"
    meshes.mkdir()
    for name, ext in (("a", [0.035, 0.04, 0.10]), ("b", [0.03, 0.05, 0.07])):
        trimesh.creation.box(extents=ext).export(str(meshes / f"{name}.stl"))
    cfg = DatagenConfig().with_overrides({**OVER, "source": str(meshes)})
    pipeline.run_generate(root / "ref", cfg, workers=1, progress=False, log=lambda s: None)
    return cfg, root, from_dataset(root / "ref")


def _simulations(monkeypatch) -> list:
    calls = []
    real = pipeline._physics_success

    def counted(*a, **kw):
        calls.append(1)
        return real(*a, **kw)

    monkeypatch.setattr(pipeline, "_physics_success", counted)
    return calls


def _same_datasets(a, b) -> None:
    for sa, sb in zip(open_dataset(a), open_dataset(b), strict=True):
        for part in ("images", "grasps"):
            x, y = getattr(sa, part), getattr(sb, part)
            for k in x:
                np.testing.assert_array_equal(x[k], y[k], err_msg=f"{sa.name} {k}")


def test_a_replayed_generation_writes_the_same_dataset_without_simulating(generated, tmp_path, monkeypatch):
    cfg, root, cache = generated
    assert cache.num_poses >= 2 and any(t.run.any() for p in cache.objects.values() for t in p.values())
    calls = _simulations(monkeypatch)
    m = pipeline.run_generate(tmp_path, cfg, workers=1, progress=False, log=lambda s: None, physics_cache=cache)
    assert calls == []
    assert all(p["cached"] for o in m["objects"] for p in o["physics"])
    _same_datasets(root / "ref", tmp_path)


def test_the_cache_survives_a_save_and_load(generated, tmp_path, monkeypatch):
    cfg, root, cache = generated
    cache.save(tmp_path / "c.npz")
    back = PhysicsCache.load(tmp_path / "c.npz")
    assert back.key == cache.key == config_key(cfg)
    assert back.num_poses == cache.num_poses
    calls = _simulations(monkeypatch)
    pipeline.run_generate(tmp_path / "out", cfg, workers=1, progress=False, log=lambda s: None, physics_cache=back)
    assert calls == []
    _same_datasets(root / "ref", tmp_path / "out")


def test_a_pose_whose_grasps_moved_is_simulated_again(generated, tmp_path, monkeypatch):
    cfg, root, cache = generated
    name = sorted(cache.objects)[0]
    moved = {k: dict(v) for k, v in cache.objects.items()}
    pose_id, t = next(iter(moved[name].items()))
    moved[name][pose_id] = PoseTrials(t.grasp_id, t.tcp + np.float16(0.005), t.held, t.run, t.record)
    calls = _simulations(monkeypatch)
    pipeline.run_generate(
        tmp_path, cfg, workers=1, progress=False, log=lambda s: None, physics_cache=PhysicsCache(cache.key, moved)
    )
    assert len(calls) == 1  # only that pose
    _same_datasets(root / "ref", tmp_path)


def test_a_cache_of_other_physics_settings_is_not_used(generated, tmp_path, monkeypatch):
    cfg, _, cache = generated
    other = cfg.with_overrides({"label.trials": 4})
    logs: list[str] = []
    calls = _simulations(monkeypatch)
    pipeline.run_generate(tmp_path, other, workers=1, progress=False, log=logs.append, physics_cache=cache)
    assert calls and any("not used" in s for s in logs)
    with pytest.raises(PhysicsCacheError, match="different"):
        cache.merge(PhysicsCache(config_key(other)))


def test_replay_refuses_a_needed_grasp_that_had_no_trials():
    t = PoseTrials(
        np.array([0, 1]), np.zeros((2, 3), np.float16), np.array([1, 0], np.uint8), np.array([2, 0], np.uint8)
    )
    T = np.tile(np.eye(4), (2, 1, 1))
    np.testing.assert_array_equal(t.replay(T, np.array([True, False])), [0.5, 0.0])
    assert t.replay(T, np.array([True, True])) is None  # grasp 1 collided then: no recorded trials
    assert t.replay(np.tile(np.eye(4), (3, 1, 1)), np.array([False, False, True])) is None  # not recorded


def test_cli_writes_and_merges_a_cache_and_names_bad_input(generated, tmp_path, capsys):
    _, root, cache = generated
    out = tmp_path / "c.npz"
    assert main(["physics-cache", "--in", str(root / "ref"), "--out", str(out)]) == 0
    assert main(["physics-cache", "--in", str(root / "ref"), "--out", str(out), "--merge"]) == 0
    assert PhysicsCache.load(out).num_poses == cache.num_poses
    capsys.readouterr()
    assert main(["physics-cache", "--in", str(tmp_path / "nope"), "--out", str(out)]) == 2
    (tmp_path / "bad.npz").write_bytes(b"not a cache")
    args = ["generate", "--out", str(tmp_path / "g"), "--objects", "1", "--physics-cache", str(tmp_path / "bad.npz")]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "nope" in err[0] and "bad.npz" in err[1] and "physics cache" in err[1]
