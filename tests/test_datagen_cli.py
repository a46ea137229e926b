"""`python -m datagen`: bad input exits with code 2 and one message naming the problem."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from datagen.__main__ import main

ROOT = Path(__file__).resolve().parents[1]


def run_main(capsys, *argv):
    rc = main([str(a) for a in argv])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def test_missing_source_folder_subprocess(tmp_path):
    """The real entry point: exit code 2, the path in the message, no traceback."""
    p = subprocess.run(
        [sys.executable, "-m", "datagen", "generate", "--out", str(tmp_path / "o"), "--source", str(tmp_path / "nope")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert p.returncode == 2
    assert "nope" in p.stderr and "does not exist" in p.stderr
    assert "Traceback" not in p.stderr


def test_unreadable_mesh_is_named(tmp_path, capsys):
    src = tmp_path / "meshes"
    src.mkdir()
    (src / "broken.obj").write_text("this is not a mesh\nv 1 2\nf 9 9 9\n")
    rc, out, err = run_main(capsys, "generate", "--out", tmp_path / "o", "--source", src, "--workers", 1, "--quiet")
    assert rc == 2
    assert "broken.obj" in err


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--set", "camera.d_range=[1.0,0.5]"], "d_range"),
        (["--set", "stable_pose_min_probability=-1"], "stable_pose_min_probability"),
        (["--set", "gripper.nonsense=1"], "gripper.nonsense"),
        (["--set", "antipodal.num_samples"], "section.field=value"),
    ],
)
def test_nonsense_config_values(tmp_path, capsys, args, needle):
    rc, out, err = run_main(capsys, "generate", "--out", tmp_path / "o", *args)
    assert rc == 2
    assert needle in err
    assert not (tmp_path / "o").exists()  # nothing written for a bad config


def test_config_file_errors(tmp_path, capsys):
    p = tmp_path / "c.json"
    p.write_text(json.dumps({"cameras_per_pose": -3}))
    rc, _, err = run_main(capsys, "generate", "--out", tmp_path / "o", "--config", p)
    assert rc == 2 and "cameras_per_pose" in err and "c.json" in err


def test_bad_counts_are_usage_errors(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(["generate", "--out", str(tmp_path), "--cameras", "0"])
    assert e.value.code == 2
    assert "--cameras must be >= 1" in capsys.readouterr().err


def test_sample_and_crops_need_a_dataset(tmp_path, capsys):
    rc, _, err = run_main(capsys, "sample", "--in", tmp_path / "missing", "--out", tmp_path / "s")
    assert rc == 2 and "missing" in err and "does not exist" in err
    rc, _, err = run_main(capsys, "crops", "--in", tmp_path, "--out", tmp_path / "c", "--arch", "vgqcnn")
    assert rc == 2 and "no manifest.json" in err


def test_kappa_with_centred_arch_is_refused(tmp_path, capsys):
    from datagen_fakes import fake_dataset

    fake_dataset(tmp_path / "g", n_objects=1, n_images=1, n_grasps=3)
    rc, _, err = run_main(
        capsys, "crops", "--in", tmp_path / "g", "--out", tmp_path / "c", "--arch", "gqcnn", "--kappa", 10
    )
    assert rc == 2 and "fast_vgqcnn only" in err


def test_a_window_not_a_multiple_of_the_crop_is_refused(tmp_path, capsys):
    from datagen_fakes import fake_dataset

    fake_dataset(tmp_path / "g", n_objects=1, n_images=1, n_grasps=3)
    rc, _, err = run_main(
        capsys, "crops", "--in", tmp_path / "g", "--out", tmp_path / "c", "--arch", "fast_vgqcnn", "--window", 50
    )
    assert rc == 2 and "window (50) must be a multiple of out (32)" in err
    assert not (tmp_path / "c" / "manifest.json").exists()


@pytest.mark.parametrize(
    ("arch", "turns", "message"), [("fast_vgqcnn", 1, "jaw_turns must be 0"), ("gqcnn", 4, "fast_vgqcnn crops only")]
)
def test_jaw_turns_out_of_range_or_for_another_arch_is_refused(tmp_path, capsys, arch, turns, message):
    from datagen_fakes import fake_dataset

    fake_dataset(tmp_path / "g", n_objects=1, n_images=1, n_grasps=3)
    rc, _, err = run_main(
        capsys, "crops", "--in", tmp_path / "g", "--out", tmp_path / "c", "--arch", arch, "--jaw-turns", turns
    )
    assert rc == 2 and message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "c" / "manifest.json").exists()


def test_ray_missing_names_the_extra(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # as if Ray were not installed
    src = tmp_path / "meshes"
    src.mkdir()
    (src / "a.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    rc, _, err = run_main(capsys, "generate", "--out", tmp_path / "o", "--source", src, "--ray", "--quiet")
    assert rc == 2 and "pip install vgq-cnn[ray]" in err


def test_recipe_dry_run_prints_the_three_stages(tmp_path, capsys):
    rc, out, _ = run_main(capsys, "recipe", "--version", "v1", "--out", tmp_path, "--dry-run")
    assert rc == 0
    lines = out.strip().splitlines()
    assert [ln.split()[3] for ln in lines] == ["generate", "sample", "crops"]


def test_v2_recipe_adds_a_clean_test_copy_and_the_leave_family_out_split(tmp_path, capsys):
    import shlex

    from vgq.cli_config import parse_override

    rc, out, _ = run_main(capsys, "recipe", "--version", "v2", "--out", tmp_path, "--dry-run")
    assert rc == 0
    lines = [shlex.split(ln) for ln in out.strip().splitlines()]
    assert [a[3] for a in lines] == ["generate", "sample", "crops", "crops", "sample", "crops"]
    assert lines[3][lines[3].index("--sensor") + 1] == "clean" and lines[3][-2:] == ["--splits", "test"]
    holdout = parse_override(lines[4][-1])
    assert holdout == ("sampling.holdout_families", ["mug", "metaball"])
    rc, out, _ = run_main(capsys, "recipe", "--version", "v2", "--out", tmp_path, "--dry-run", "--no-leave-out")
    assert rc == 0 and [shlex.split(ln)[3] for ln in out.strip().splitlines()] == [
        "generate",
        "sample",
        "crops",
        "crops",
    ]


def test_a_recipe_with_jaw_turns_cuts_every_crop_copy_turned(tmp_path, capsys, monkeypatch):
    import shlex

    import datagen.recipe as cli

    monkeypatch.setitem(cli.RECIPES, "v2", {**cli.RECIPES["v2"], "jaw_turns": 4})
    rc, out, _ = run_main(capsys, "recipe", "--version", "v2", "--out", tmp_path, "--dry-run")
    crops = [a for a in map(shlex.split, out.strip().splitlines()) if a[3] == "crops"]
    assert rc == 0 and len(crops) == 3  # training copy, clean test copy, leave-family-out copy
    assert all(a[a.index("--jaw-turns") + 1] == "4" for a in crops)
    monkeypatch.setitem(cli.RECIPES, "v2", {**cli.RECIPES["v2"], "jaw_turns": 0})
    rc, out, _ = run_main(capsys, "recipe", "--version", "v2", "--out", tmp_path, "--dry-run")
    assert "--jaw-turns" not in out


def test_stats_counts_each_family_and_its_objects_without_a_positive(tmp_path, capsys):
    from datagen_fakes import fake_dataset

    from datagen import storage

    m = fake_dataset(tmp_path / "g", n_objects=4, n_images=1, n_grasps=10)
    for o in m["objects"]:
        o["family"] = "mug" if o["object_id"] < 2 else "box"
    m["shards"][3]["num_positive"] = 0  # one box none of whose grasps succeeds
    storage.write_manifest(tmp_path / "g", m)
    rc, out, _ = run_main(capsys, "stats", "--in", tmp_path / "g", "--json")
    assert rc == 0
    fams = json.loads(out)["families"]
    assert list(fams) == ["box", "mug"] and fams["mug"]["done"] == 2 and fams["box"]["no_positive"] == 1
    assert fams["mug"]["grasps"] == sum(s["num_grasps"] for s in m["shards"][:2])
    assert fams["box"]["positive"] == m["shards"][2]["num_positive"]
    rc, out, _ = run_main(capsys, "stats", "--in", tmp_path / "g")
    assert rc == 0 and out.splitlines()[2].split()[0] == "box"
    rc, _, err = run_main(capsys, "stats", "--in", tmp_path / "nothing")
    assert rc == 2 and "nothing" in err


def test_v2_recipe_replays_its_recorded_physics_trials_when_the_file_is_there(tmp_path, capsys, monkeypatch):
    import shlex

    import datagen.recipe as cli

    monkeypatch.setattr(cli, "RECIPE_FILES", tmp_path)
    argv = ("recipe", "--version", "v2", "--out", tmp_path / "d", "--dry-run")
    generate = lambda *extra: shlex.split(run_main(capsys, *argv, *extra)[1].splitlines()[0])  # noqa: E731
    assert "--physics-cache" not in generate()  # no recorded trials: every trial runs
    (tmp_path / cli.RECIPES["v2"]["physics_cache"]).write_bytes(b"")
    g = generate()
    assert g[g.index("--physics-cache") + 1] == str(tmp_path / cli.RECIPES["v2"]["physics_cache"])
    assert "--physics-cache" not in generate("--no-physics-cache")


def test_more_test_objects_are_new_shapes_of_every_family_all_held_out(tmp_path, capsys, monkeypatch):
    import shlex

    import datagen.recipe as cli
    from datagen.families import family_names
    from vgq.cli_config import parse_override

    argv = ("recipe", "--version", "v2", "--out", tmp_path, "--dry-run", "--no-leave-out", "--more-test", "3")
    rc, out, _ = run_main(capsys, *argv)
    lines = [shlex.split(ln) for ln in out.strip().splitlines()]
    assert rc == 0 and [a[3] for a in lines[-3:]] == ["generate", "sample", "crops"]
    gen, samp, crops = lines[-3:]
    assert gen[gen.index("--families") + 1] == "all=3" and gen[gen.index("--objects") + 1] == "0"
    assert gen[gen.index("--seed") + 1] == "1" != lines[0][lines[0].index("--seed") + 1]  # not the recipe's shapes
    assert "--physics-cache" not in gen  # the recorded trials are the recipe's objects'
    key, held = parse_override(samp[-1])
    assert key == "sampling.holdout_families" and sorted(held) == sorted(family_names())
    assert crops[-2:] == ["--splits", "test"] and crops[crops.index("--out") + 1].endswith("crops_more")
    monkeypatch.setitem(cli.RECIPES, "v2", {**cli.RECIPES["v2"], "families": "mug=5,box=2"})
    gen = shlex.split(run_main(capsys, *argv)[1].strip().splitlines()[-3])
    assert gen[gen.index("--families") + 1] == "mug=3,box=3"
    rc, _, err = run_main(capsys, "recipe", "--version", "v1", "--out", tmp_path, "--dry-run", "--more-test", "3")
    assert rc == 2 and "no procedural families" in err


def test_stacker_fit_set_is_objects_neither_the_recipe_nor_its_tests_draw(tmp_path, capsys):
    import shlex

    from datagen.families import family_names
    from datagen.recipe import RECIPES
    from vgq.cli_config import parse_override

    argv = ("recipe", "--version", "v2", "--out", tmp_path, "--dry-run", "--no-leave-out", "--more-test", "3")
    rc, out, _ = run_main(capsys, *argv, "--stacker")
    lines = [shlex.split(ln) for ln in out.strip().splitlines()]
    assert rc == 0 and [a[3] for a in lines[-3:]] == ["generate", "sample", "crops"]
    gen, samp, crops = lines[-3:]
    seeds = {g[g.index("--seed") + 1] for g in lines if g[3] == "generate"}
    assert gen[gen.index("--seed") + 1] == "2" and seeds == {"0", "1", "2"}  # new shapes: no other run's seed
    first = int(gen[gen.index("--first-object") + 1])
    assert (
        first >= RECIPES["v2"]["objects"] and gen[gen.index("--objects") + 1] == "40"
    )  # random_urdfs past the recipe's
    sets = [parse_override(samp[i + 1]) for i, a in enumerate(samp) if a == "--set"]
    assert sorted(dict(sets)["sampling.holdout_families"]) == sorted(family_names())
    assert crops[-2:] == ["--splits", "test"] and crops[crops.index("--out") + 1].endswith("crops_stacker")
    rc, _, err = run_main(capsys, "recipe", "--version", "v1", "--out", tmp_path, "--dry-run", "--stacker")
    assert rc == 2 and "no stacker fit set" in err


def test_first_object_starts_the_run_that_many_sources_in(tmp_path, capsys):
    import trimesh

    from datagen.config import ConfigError, DatagenConfig, validate
    from datagen.pipeline import run_sources

    for i in range(5):
        trimesh.creation.box((0.05, 0.04, 0.03)).export(tmp_path / f"m{i}.obj")
    cfg = DatagenConfig(source=str(tmp_path), num_objects=2, first_object=3)
    assert [s.name for s in run_sources(cfg)] == ["m3", "m4"]
    assert [s.name for s in run_sources(DatagenConfig(source=str(tmp_path), first_object=4))] == ["m4"]
    with pytest.raises(ConfigError, match="first_object"):
        validate(DatagenConfig(first_object=-1))
    with pytest.raises(SystemExit) as e:
        run_main(capsys, "generate", "--out", tmp_path / "o", "--first-object", "-1")
    assert e.value.code == 2 and "--first-object must be >= 0" in capsys.readouterr().err
