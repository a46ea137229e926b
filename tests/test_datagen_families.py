"""Object families: watertight meshes of physical size, deterministic, graspable, and usable
by the datagen pipeline (load_object, stable poses, antipodal sampler)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from datagen.families import FAMILIES, FamilyError, build_mesh, family_sources, make_object, object_name, sample_params
from datagen.grasps import AntipodalParams, sample_antipodal_grasps
from datagen.mesh import MeshError, MeshParams, MeshSource, load_object, stable_poses

ALL = list(FAMILIES)


def test_at_least_ten_families():
    assert len(FAMILIES) >= 10


@pytest.mark.parametrize("family", ALL)
def test_family_meshes_are_closed_single_bodies_within_their_size_range(family):
    lo, hi = FAMILIES[family].extent_range
    for seed, index in ((0, 0), (0, 1), (7, 3)):
        mesh = make_object(family, index, seed).mesh
        assert mesh.is_watertight and mesh.is_winding_consistent and mesh.is_volume, (family, seed, index)
        assert mesh.volume > 0
        assert len(mesh.split(only_watertight=False)) == 1, f"{family} {index}: more than one body"
        ext = mesh.extents
        assert lo - 1e-9 <= ext.min() and ext.max() <= hi + 1e-9, (family, index, ext)


@pytest.mark.parametrize("family", ALL)
def test_same_family_index_seed_gives_the_same_mesh(family):
    a, b = make_object(family, 2, 5), make_object(family, 2, 5)
    assert a.params == b.params and a.name == b.name == object_name(family, 2)
    np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)
    np.testing.assert_array_equal(a.mesh.faces, b.mesh.faces)
    assert sample_params(family, 3, 5) != a.params  # another index, another object
    assert sample_params(family, 2, 6) != a.params  # another run seed, another object


def _thinnest_wall(mesh, n: int = 400) -> float:
    """Smallest distance, over sampled surface points, from the point through the solid
    along the inward normal to where the ray leaves it (metres)."""
    pts, fi = mesh.sample(n, return_index=True, seed=0)
    inward = -mesh.face_normals[fi]
    origins = pts + 1e-6 * inward
    loc, ray_idx, _ = mesh.ray.intersects_location(origins, inward, multiple_hits=False)
    d = np.linalg.norm(loc - origins[ray_idx], axis=1)
    return float(d.min())


@pytest.mark.parametrize("family", ALL)
def test_every_object_has_a_dimension_the_5cm_jaws_can_span(family):
    for index in range(3):
        assert _thinnest_wall(make_object(family, index, 0).mesh) <= 0.05, (family, index)


@pytest.mark.parametrize("family", ["cylinder", "cone", "ellipsoid", "metaball", "torus"])
def test_round_objects_lie_at_least_2cm_high_so_fingertips_clear_the_table(family):
    """The fingertips reach 1 cm past the contacts: a disc, rod, egg, blob or tube that lies
    lower has no grasp this gripper can make on a table (the first v2 run had such objects
    without a single successful grasp)."""
    from datagen.mesh import principal_extents

    for index in range(12):
        obj = make_object(family, index, 0)
        if obj.params.get("kind") == "ring":  # rings are grasped across their wall, from inside
            continue
        ext = np.sort(principal_extents(obj.mesh))
        assert ext[0] >= (0.028 if family == "metaball" else 0.0199), (family, index, obj.params)
        if family != "cone":  # and thin enough across to close the 5 cm jaws on (a cone: near its top)
            assert ext[0] <= 0.045, (family, index, obj.params)
        if family in ("metaball", "ellipsoid"):  # resting on its broad side, it is gripped across its width
            assert ext[1] <= 0.046, (family, index, obj.params)


@pytest.mark.parametrize("family", ALL)
def test_family_object_goes_through_load_stable_poses_and_the_antipodal_sampler(family):
    (src,) = family_sources({family: 1}, seed=0)
    built = make_object(family, 0, 0).mesh
    obj = load_object(src, MeshParams())  # default params rescale files, never a procedural object
    np.testing.assert_allclose(np.sort(obj.mesh.extents), np.sort(built.extents), rtol=1e-6, atol=1e-9)
    assert obj.scale == 1.0
    T, p = stable_poses(obj, 0.01)
    assert len(T) >= 1
    grasps = sample_antipodal_grasps(obj.mesh, AntipodalParams(num_samples=20), np.random.default_rng(0))
    assert len(grasps) > 0, f"{family}: no antipodal grasp"
    assert np.all(grasps.widths <= 0.05 + 1e-9)


def test_unknown_family_and_bad_parameters_are_named():
    with pytest.raises(FamilyError, match="unknown object family 'teapot'"):
        sample_params("teapot", 0)
    with pytest.raises(FamilyError, match="box: size"):
        build_mesh("box", {"size": [0.1, -0.02, 0.03]})
    with pytest.raises(FamilyError, match="cylinder: radius"):
        build_mesh("cylinder", {"radius": float("nan"), "height": 0.1})
    with pytest.raises(FamilyError, match="mug: missing parameter 'radius'"):
        build_mesh("mug", {})
    with pytest.raises(FamilyError, match="count"):
        family_sources({"box": -1})


def test_bad_family_parameters_are_a_mesh_error_for_the_pipeline(tmp_path):
    src = MeshSource("box_0000", tmp_path / "family:box_0000", 1.0, "box", {"size": [0.1, 0.02, 7.0]})
    with pytest.raises(MeshError, match="box: size"):
        load_object(src)


# ----------------------------------------------------------------------------- family-aware split


def test_split_within_every_family_puts_each_family_in_every_split():
    from datagen.sampling import split_by_family, split_objects

    fams = {i: f for i, f in enumerate(["random_urdfs"] * 20 + ["mug"] * 3 + ["box"] * 7 + ["metaball"] * 4)}
    split = split_by_family(list(fams), fams, (0.8, 0.1, 0.1), seed=1)
    assert set(split) == set(fams)
    for fam in set(fams.values()):
        got = {split[i] for i, f in fams.items() if f == fam}
        assert got == {"train", "val", "test"}, fam
    assert split == split_by_family(list(fams), fams, (0.8, 0.1, 0.1), seed=1)
    # one family (or data without families): the split of the single-family code path
    one = {i: "random_urdfs" for i in range(12)}
    assert split_by_family(list(one), one, (0.8, 0.1, 0.1), 3) == split_objects(list(one), (0.8, 0.1, 0.1), 3)
    assert split_by_family(range(12), {}, (0.8, 0.1, 0.1), 3) == split_objects(range(12), (0.8, 0.1, 0.1), 3)


def test_holdout_families_go_only_to_test():
    from datagen.sampling import split_by_family

    fams = {i: f for i, f in enumerate(["box"] * 10 + ["mug"] * 5)}
    split = split_by_family(list(fams), fams, (0.8, 0.1, 0.1), 0, holdout=("mug",))
    assert {split[i] for i in range(10, 15)} == {"test"}
    assert {split[i] for i in range(10)} == {"train", "val", "test"}
    with pytest.raises(ValueError, match="holdout family 'torus'"):
        split_by_family(list(fams), fams, (0.8, 0.1, 0.1), 0, holdout=("torus",))


def test_sample_dataset_splits_within_families_and_keeps_family_records(tmp_path):
    import json

    from datagen_fakes import fake_dataset

    from datagen import storage
    from datagen.sampling import SamplingParams, sample_dataset

    fake_dataset(tmp_path / "raw", n_objects=12, n_grasps=60, n_images=1)
    mp = tmp_path / "raw" / "manifest.json"
    m = json.loads(mp.read_text())
    for o in m["objects"]:  # 6 random_urdfs, 3 mugs, 3 boxes
        o["family"] = "random_urdfs" if o["object_id"] < 6 else ("mug" if o["object_id"] < 9 else "box")
        o["params"] = {} if o["family"] == "random_urdfs" else {"index": o["object_id"]}
    storage.write_manifest(tmp_path / "raw", m)
    logs: list[str] = []
    stats = sample_dataset(tmp_path / "raw", tmp_path / "s", SamplingParams(uniform=False), log=logs.append, plot=False)
    out = storage.open_dataset(tmp_path / "s").manifest
    assert stats["families"] == {
        f: {"train": n - 2, "val": 1, "test": 1} for f, n in (("box", 3), ("mug", 3), ("random_urdfs", 6))
    }
    for o, src in zip(out["objects"], m["objects"]):
        assert o["family"] == src["family"] and o["params"] == src["params"]
    assert any("objects per family" in line for line in logs)


# ----------------------------------------------------------------------------- config and CLI


@pytest.mark.parametrize(
    "overrides, needle",
    [
        ({"families": {"teapot": 2}}, "unknown object family 'teapot'"),
        ({"families": {"mug": -1}}, "families.mug"),
        ({"families": {"mug": 1.5}}, "families.mug"),
        ({"families": "mug"}, "families must be a JSON object"),
        ({"num_objects": 0}, "no objects"),
    ],
)
def test_bad_family_settings_are_named(overrides, needle):
    from datagen.config import ConfigError, DatagenConfig

    with pytest.raises(ConfigError, match=needle):
        DatagenConfig().with_overrides(overrides)


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["objects", "--family", "teapot", "--out", "{tmp}/o"], "unknown object family 'teapot'"),
        (["objects", "--family", "mug", "--count", "0", "--out", "{tmp}/o"], "--count must be >= 1"),
        (["objects", "--family", "mug"], "--out"),
        (["generate", "--out", "{tmp}/g", "--families", "mug"], "FAMILY=COUNT"),
        (["generate", "--out", "{tmp}/g", "--families", "mug=-2"], "FAMILY=COUNT"),
        (["generate", "--out", "{tmp}/g", "--families", "teapot=2"], "unknown object family 'teapot'"),
        (["generate", "--out", "{tmp}/g", "--objects", "0"], "no objects"),
    ],
)
def test_cli_bad_family_input_exits_2(tmp_path, capsys, argv, needle):
    """Exit code 2, the last stderr line names the problem, nothing written."""
    from datagen.__main__ import main

    try:
        rc = main([a.format(tmp=tmp_path) for a in argv])
    except SystemExit as e:  # argparse's own usage errors
        rc = e.code
    err = capsys.readouterr().err
    assert rc == 2
    assert needle in err.strip().splitlines()[-1]
    assert not (tmp_path / "o").exists() and not (tmp_path / "g").exists()


def test_cli_unknown_family_subprocess(tmp_path):
    """The real entry point: one line on stderr, no traceback."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    p = subprocess.run(
        [sys.executable, "-m", "datagen", "objects", "--family", "teapot", "--out", str(tmp_path / "o")],
        cwd=root,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert p.returncode == 2
    assert p.stderr.strip().splitlines() == [p.stderr.strip()] and "teapot" in p.stderr


def test_cli_objects_writes_meshes_parameters_and_a_contact_sheet(tmp_path):
    import json

    import trimesh
    from PIL import Image

    from datagen.__main__ import main

    assert main(["objects", "--family", "mug,box", "--count", "2", "--seed", "3", "--out", str(tmp_path)]) == 0
    rec = json.loads((tmp_path / "objects.json").read_text())
    assert [o["name"] for o in rec["objects"]] == ["mug_0000", "mug_0001", "box_0000", "box_0001"]
    for o in rec["objects"]:
        assert o["params"] == sample_params(o["family"], o["index"], 3)
        mesh = trimesh.load(tmp_path / o["file"], force="mesh")
        assert mesh.is_watertight
        np.testing.assert_allclose(mesh.extents, o["extents_m"], atol=1e-5)  # metres, physical size
    for name in ("mug.png", "box.png", "families.png"):
        img = np.asarray(Image.open(tmp_path / name).convert("L"), dtype=float)
        assert img.shape[0] > 100 and img.std() > 10  # rendered content, not a blank page


# ----------------------------------------------------------------------------- generation


TINY = {
    "cameras_per_pose": 1,
    "max_stable_poses": 1,
    "antipodal.num_samples": 8,
    "quality.num_samples": 3,
    "num_objects": 0,
    "families": {"box": 1, "torus": 1},
}


def test_tiny_generation_records_family_and_params_and_resumes(tmp_path):
    import json

    from datagen import storage
    from datagen.config import DatagenConfig
    from datagen.pipeline import run_generate

    cfg = DatagenConfig().with_overrides(TINY)
    ref = tmp_path / "ref"
    m = run_generate(ref, cfg, workers=1, progress=False, log=lambda s: None)
    assert [o["name"] for o in m["objects"]] == ["box_0000", "torus_0000"]
    for o in m["objects"]:
        assert o["status"] == "done" and o["mesh_scale"] == 1.0
        assert o["params"] == sample_params(o["family"], 0, cfg.seed)
        assert o["family"] in ("box", "torus")

    # a run that stopped after its first object (the second still pending) resumes to the same data
    out = tmp_path / "cut"
    m2 = run_generate(out, cfg, workers=1, progress=False, log=lambda s: None)
    storage.record_skip(m2, 1, "placeholder")
    m2["objects"][1]["status"] = "pending"
    m2["shards"] = [s for s in m2["shards"] if s["object_id"] != 1]
    m2["complete"] = False
    storage.update_counts(m2)
    storage.write_manifest(out, m2)
    logs: list[str] = []
    m3 = run_generate(out, cfg, workers=1, progress=False, log=logs.append)
    assert any("resuming" in s for s in logs)
    assert m3["complete"]
    ref_m = json.loads((ref / "manifest.json").read_text())
    assert [s["sha256"] for s in m3["shards"]] == [s["sha256"] for s in ref_m["shards"]]


def test_objects_made_from_an_older_family_definition_are_regenerated_on_resume(tmp_path):
    """After a family's size ranges change, resuming regenerates its done objects (their
    recorded parameters differ from the code's) and leaves the others; a manifest written
    before objects recorded parameters is trusted."""
    import json

    from datagen.config import DatagenConfig
    from datagen.pipeline import run_generate

    cfg = DatagenConfig().with_overrides(TINY)
    out = tmp_path / "run"
    ref = run_generate(out, cfg, workers=1, progress=False, log=lambda s: None)
    shas = [s["sha256"] for s in ref["shards"]]
    m = json.loads((out / "manifest.json").read_text())
    m["objects"][1]["params"] = {**m["objects"][1]["params"], "kind": "ring", "wall": 0.001}  # an old definition
    m["shards"][1]["sha256"] = "stale"
    box_shard = out / m["objects"][0]["shard"]
    mtime = box_shard.stat().st_mtime_ns
    (out / "manifest.json").write_text(json.dumps(m))
    logs: list[str] = []
    again = run_generate(out, cfg, workers=1, progress=False, log=logs.append)
    assert any("regenerating torus_0000" in s for s in logs), logs
    assert again["complete"] and [s["sha256"] for s in again["shards"]] == shas
    assert again["objects"][1]["params"] == sample_params("torus", 0, cfg.seed)
    assert box_shard.stat().st_mtime_ns == mtime  # the unchanged box was not redone

    for o in m["objects"]:
        o.pop("params")  # a manifest from before objects recorded parameters
    m["shards"][1]["sha256"] = shas[1]
    (out / "manifest.json").write_text(json.dumps(m))
    logs.clear()
    run_generate(out, cfg, workers=1, progress=False, log=logs.append)
    assert not any("regenerating" in s for s in logs)


def test_generate_resume_keeps_the_run_order_of_its_families(tmp_path):
    """The manifest's config is written with sorted keys; ``--resume`` (and anything that rebuilds a
    run's objects from a recorded config, e.g. planning.bench) must number the objects as the run
    did, not refuse the run as "a different object list". Families are numbered in the registry's
    order, whatever order they are given in."""
    from datagen.__main__ import main

    out = tmp_path / "run"
    args = ["generate", "--out", str(out), "--objects", "0", "--families", "torus=1,box=1", "--cameras", "1"]
    tiny = ["--set", "max_stable_poses=1", "--set", "antipodal.num_samples=8", "--set", "quality.num_samples=3"]
    assert main([*args, *tiny, "--workers", "1", "--quiet"]) == 0
    run_names = [o["name"] for o in json.loads((out / "manifest.json").read_text())["objects"]]
    assert main(["generate", "--out", str(out), "--resume", "--workers", "1", "--quiet"]) == 0
    names = [o["name"] for o in json.loads((out / "manifest.json").read_text())["objects"]]
    assert names == run_names == ["box_0000", "torus_0000"]
    alphabetical = {"torus": 1, "metaball": 1, "box": 1}
    assert [s.name for s in family_sources(alphabetical)] == ["box_0000", "torus_0000", "metaball_0000"]
