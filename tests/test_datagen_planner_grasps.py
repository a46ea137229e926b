"""`datagen planner-grasps`: the planner's candidates on a small real grasp dataset (made here:
3 random_urdfs objects and 2 procedural cylinders, 1 stable pose, 2 cameras, 1 physics trial),
labelled by pybullet trials on the true mesh."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from datagen import storage
from datagen.__main__ import main
from datagen.collision import CollisionChecker
from datagen.config import DatagenConfig
from datagen.gripper import grasp_frames
from datagen.mesh import load_object, stable_poses
from datagen.pipeline import run_generate
from datagen.planner_grasps import (
    PlannerGraspParams,
    depth_mismatch,
    grasp_omega,
    grasp_rows,
    mesh_source,
    planner_candidates,
    run_planner_grasps,
    unscaled_frames,
)
from datagen.sampling import split_by_family
from vgq.pose import matrix_from_quaternion, quaternion_from_matrix
from vgq.schema import GRASP_FIELDS, GRASP_LABEL_FIELDS, IMAGE_FIELDS, check_fields

TINY = {
    "num_objects": 3,
    "families": {"cylinder": 2},
    "cameras_per_pose": 2,
    "max_stable_poses": 1,
    "antipodal.num_samples": 8,
    "quality.num_samples": 3,
    "label.trials": 1,
}
PARAMS = PlannerGraspParams(images_per_object=2, candidates=5, trials=1)
QUIET = {"progress": False, "log": lambda s: None}


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """(source dataset, planner-grasps dataset of all its objects) folders."""
    root = tmp_path_factory.mktemp("planner_grasps")
    src, out = root / "src", root / "out"
    run_generate(src, DatagenConfig().with_overrides(TINY), **QUIET)
    run_planner_grasps(src, out, PARAMS, **QUIET)
    return src, out


def _arrays(root: Path) -> dict:
    return {sh.object_id: {**sh.images, **sh.grasps} for sh in storage.open_dataset(root)}


def _cli(capsys, *argv):
    rc = main([str(a) for a in argv])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def test_output_is_a_grasp_dataset_of_the_same_objects(made):
    src, out = made
    ds, s = storage.open_dataset(out), storage.open_dataset(src)
    m = ds.manifest
    assert m["complete"] and m["counts"]["objects_done"] >= 4 and m["counts"]["grasps"] > 0
    key = ("object_id", "name", "family", "params")
    assert [{k: o.get(k) for k in key} for o in m["objects"]] == [{k: o.get(k) for k in key} for o in s.objects]
    assert m["config"] == s.manifest["config"]  # a physics SRC, same trials: the same config
    assert m["label_threshold"] == s.label_threshold == 0.5
    assert m["planner_grasps"]["source"] == str(src.resolve())
    assert m["planner_grasps"]["params"]["candidates"] == 5
    assert m["split_object_ids"] == s.object_ids
    src_arrays = _arrays(src)
    for sh in ds:
        n_img = check_fields(IMAGE_FIELDS, sh.images, "images")
        n = check_fields({**GRASP_FIELDS, **GRASP_LABEL_FIELDS}, sh.grasps, "grasps")
        assert 1 <= n_img <= 2 and 1 <= n <= 5 * n_img
        np.testing.assert_array_equal(sh.grasps["grasp_id"], np.arange(n))
        # the image rows are the source's rows (clean depth), not the sensor's image
        for i in range(n_img):
            same = [
                j
                for j in range(len(src_arrays[sh.object_id]["depth"]))
                if np.array_equal(src_arrays[sh.object_id]["T_world_camera"][j], sh.images["T_world_camera"][i])
            ]
            assert len(same) == 1
            for k in IMAGE_FIELDS:
                np.testing.assert_array_equal(sh.images[k][i], src_arrays[sh.object_id][k][same[0]])


def test_rows_are_the_labelled_grasps(made):
    """Rebuild each grasp from its row (TCP pixel, depth, quaternion) and the camera: the true
    mesh's collision check agrees with ``collision_free``; labels are success rates in [0, 1],
    0 (and no trials) where the grasp collides."""
    src, out = made
    ds = storage.open_dataset(out)
    cfg = DatagenConfig.from_dict(ds.manifest["config"])
    intr = cfg.intrinsics
    agree, total = 0, 0
    for sh in ds:
        g, im = sh.grasps, sh.images
        q, cf, sr = g["quality"], g["collision_free"], g["success_rate"]
        assert np.all((q >= 0) & (q <= 1))
        assert np.all(q[~cf] == 0) and np.all(np.isnan(sr[~cf]))
        np.testing.assert_array_equal(q[cf], sr[cf])
        assert np.all(np.isnan(g["fc_quality"]))
        assert np.all(np.isfinite(g["p_collision_free"][cf])) and np.all(np.isnan(g["p_collision_free"][~cf]))
        assert np.all((g["u"] >= -0.5) & (g["u"] < 299.5) & (g["v"] >= -0.5) & (g["v"] < 299.5))
        assert np.all(g["psi"] < np.radians(80) + 1e-4)  # the planner's approach limit
        obj = load_object(mesh_source(ds.objects[sh.object_id]), cfg.mesh)
        T_wo = stable_poses(obj, cfg.stable_pose_min_probability, cfg.max_stable_poses)[0]
        for i in range(len(im["depth"])):
            rows = g["image_index"] == i
            T_wc = im["T_world_camera"][i]
            mesh_world = obj.mesh.copy()
            mesh_world.apply_transform(T_wo[im["stable_pose_id"][i]])
            z = g["z"][rows].astype(np.float64)
            T_cg = np.tile(np.eye(4), (int(rows.sum()), 1, 1))
            T_cg[:, :3, :3] = matrix_from_quaternion(g["q"][rows].astype(np.float64))
            T_cg[:, :3, 3] = np.stack(
                [(g["u"][rows] - intr.cx) * z / intr.fx, (g["v"][rows] - intr.cy) * z / intr.fy, z], axis=1
            )
            free = ~CollisionChecker(mesh_world, cfg.gripper).collides(T_wc @ T_cg)
            agree += int((free == cf[rows]).sum())
            total += int(rows.sum())
            # the TCP lies within the jaw opening of the surface seen at its pixel
            d = im["depth"][i][np.rint(g["v"][rows]).astype(int), np.rint(g["u"][rows]).astype(int)]
            assert np.all(np.abs(d - z) < 0.05)
    assert total > 0 and agree >= total - 1  # float32 rows: at most one borderline grasp flips
    assert 0 < ds.manifest["counts"]["collision_free"] < total or total < 3


def test_grasp_rows_project_planner_candidates_to_their_pixels(made):
    """The rows of real planner candidates (camera frame) put the TCP at its pixel and depth, the
    orientation at its quaternion, and omega rebuilds the frame from datagen's base frame."""
    src, _ = made
    ds = storage.open_dataset(src)
    cfg = DatagenConfig.from_dict(ds.manifest["config"])
    intr = cfg.intrinsics
    sh = ds.load(ds.shard_entries[3])  # a cylinder
    obj = load_object(mesh_source(ds.objects[sh.object_id]), cfg.mesh)
    T_wo = stable_poses(obj, cfg.stable_pose_min_probability, cfg.max_stable_poses)[0][0]
    T_wc = sh.images["T_world_camera"][0]
    cands, counts = planner_candidates(sh.images["depth"][0], intr, np.random.default_rng(0))
    assert len(cands) > 0, counts
    F = cands.frames
    rows, inside = grasp_rows(T_wc @ F, T_wc, T_wo, intr)
    t = F[:, :3, 3]
    np.testing.assert_allclose(rows["u"], intr.fx * t[:, 0] / t[:, 2] + intr.cx, atol=1e-3)
    np.testing.assert_allclose(rows["v"], intr.fy * t[:, 1] / t[:, 2] + intr.cy, atol=1e-3)
    np.testing.assert_allclose(rows["z"], t[:, 2], atol=1e-6)
    np.testing.assert_allclose(rows["q"], quaternion_from_matrix(F[:, :3, :3]), atol=1e-6)
    np.testing.assert_allclose(rows["psi"], np.arccos(np.clip(F[:, 2, 2], -1, 1)), atol=1e-5)  # vs the principal ray
    assert inside.all()
    T_og = np.linalg.inv(T_wo) @ T_wc @ F
    om = grasp_omega(T_og)
    np.testing.assert_allclose(grasp_frames(T_og[:, :3, 3], T_og[:, :3, 0], om), T_og, atol=1e-9)
    # a depth-scale error moves the TCP along its ray: same pixel, 1 / scale of the depth
    moved = unscaled_frames(F, 1.03)
    r2, _ = grasp_rows(T_wc @ moved, T_wc, T_wo, intr)
    np.testing.assert_allclose(r2["u"], rows["u"], atol=1e-3)
    np.testing.assert_allclose(r2["z"], rows["z"] / 1.03, rtol=1e-6)


def test_depth_mismatch_counts_the_object_pixels():
    table = np.full((20, 20), 0.7)
    stored = table.copy()
    stored[5:10, 5:10] = 0.65
    assert depth_mismatch(stored, stored, table, 1e-3) == 0.0
    moved = table.copy()
    moved[5:10, 7:12] = 0.65  # the object two pixels to the side: 20 of 35 object pixels differ
    assert depth_mismatch(moved, stored, table, 1e-3) == pytest.approx(20 / 35)
    assert depth_mismatch(table, table, table, 1e-3) == 1.0  # no object at all: nothing matches


def test_wrong_pose_is_caught_and_named(made, tmp_path, capsys):
    """Object 000's image seen from a camera turned 90 deg about the table normal (the stored
    depth no longer shows the mesh at the recorded pose): the object fails, named, unlabelled."""
    src, _ = made
    bad = tmp_path / "bad"
    shutil.copytree(src, bad)
    m = json.loads((bad / "manifest.json").read_text())
    entry = m["shards"][0]
    images, grasps = storage.read_shard(bad / entry["file"])
    Rz = np.eye(4)
    Rz[:2, :2] = [[0.0, -1.0], [1.0, 0.0]]
    images["T_world_camera"] = Rz @ images["T_world_camera"]
    m["shards"][0] = storage.write_shard(bad, 0, images, grasps, m["label_threshold"])
    storage.write_manifest(bad, m)
    rc, _, err = _cli(
        capsys, "planner-grasps", "--grasps", bad, "--out", tmp_path / "o", "--objects", 1, "--workers", 1,
        "--candidates", 2, "--trials", 1, "--quiet",
    )  # fmt: skip
    assert rc == 1
    assert "000" in err and "self-check" in err
    o = json.loads((tmp_path / "o" / "manifest.json").read_text())
    assert o["objects"][0]["failed"] and o["objects"][0]["status"] == "skipped"
    assert not o["shards"] and not (tmp_path / "o" / storage.shard_relpath(0)).exists()


def test_resume_skips_done_objects_and_matches_a_full_run(made, tmp_path):
    """--objects 2 first (one per family), then the rest with 2 workers: the finished shards are
    not rewritten, and the whole equals the single-process run of the fixture."""
    src, full = made
    out = tmp_path / "o"
    m = run_planner_grasps(src, out, PARAMS, max_objects=2, **QUIET)
    first = {s["object_id"]: s["sha256"] for s in m["shards"]}
    assert len(first) == 2 and {m["objects"][i]["family"] for i in first} == {"random_urdfs", "cylinder"}
    assert not m["complete"]
    mtimes = {i: (out / storage.shard_relpath(i)).stat().st_mtime_ns for i in first}
    logs: list[str] = []
    m = run_planner_grasps(src, out, PARAMS, workers=2, progress=False, log=logs.append)
    assert m["complete"] and any("resuming" in s and "3 to go" in s for s in logs)
    assert {i: (out / storage.shard_relpath(i)).stat().st_mtime_ns for i in first} == mtimes
    a, b = _arrays(out), _arrays(full)
    assert sorted(a) == sorted(b)
    for oid in a:
        for k in a[oid]:
            np.testing.assert_array_equal(a[oid][k], b[oid][k], err_msg=f"object {oid} field {k}")
    with pytest.raises(Exception, match="another source or settings"):
        run_planner_grasps(src, out, PlannerGraspParams(candidates=6, trials=1), **QUIET)


def test_sample_keeps_each_objects_split(made, tmp_path, capsys):
    """`datagen sample` on a planner-grasps run of a subset puts each object into the split that
    sampling the source gives it (with the same seed), also where the subset alone would differ."""
    src, _ = made
    ds = storage.open_dataset(src)
    fams = {int(o["object_id"]): o["family"] for o in ds.objects}
    # a seed for which object 0 is not in train when the source's 3 random_urdfs are split
    seed = next(s for s in range(50) if split_by_family(ds.object_ids, fams, seed=s)[0] != "train")
    assert split_by_family([0, 3], fams, seed=seed)[0] == "train"  # what the subset alone would give
    sub = tmp_path / "sub"
    run_planner_grasps(src, sub, PARAMS, max_objects=2, **QUIET)
    splits = {}
    for name, folder in (("src", src), ("sub", sub)):
        rc, _, err = _cli(
            capsys, "sample", "--in", folder, "--out", tmp_path / f"s_{name}", "--seed", seed, "--no-plots"
        )
        assert rc == 0, err
        sm = json.loads((tmp_path / f"s_{name}" / "manifest.json").read_text())
        splits[name] = {i: s for s, ids in sm["splits"].items() for i in ids}
    assert sorted(splits["sub"]) == [0, 3]
    assert splits["sub"] == {i: splits["src"][i] for i in (0, 3)}
    assert splits["sub"][0] != "train"
    rc, _, err = _cli(
        capsys, "crops", "--in", tmp_path / "s_sub", "--out", tmp_path / "c", "--arch", "fast_vgqcnn", "--workers", 1,
        "--quiet",
    )  # fmt: skip
    assert rc == 0, err
    cm = json.loads((tmp_path / "c" / "manifest.json").read_text())
    assert sum(c["n"] for c in cm["counts"].values()) > 0


@pytest.mark.parametrize(
    "extra, needle",
    [
        (["--candidates", "0"], "--candidates must be >= 1"),
        (["--images-per-object", "-1"], "--images-per-object must be >= 1"),
        (["--trials", "0"], "--trials must be >= 1"),
    ],
)
def test_bad_counts_are_usage_errors(made, tmp_path, capsys, extra, needle):
    with pytest.raises(SystemExit) as e:
        main(["planner-grasps", "--grasps", str(made[0]), "--out", str(tmp_path / "o"), *extra])
    assert e.value.code == 2 and needle in capsys.readouterr().err


def test_bad_sources_exit_2_naming_them(made, tmp_path, capsys):
    src, _ = made
    rc, _, err = _cli(capsys, "planner-grasps", "--grasps", tmp_path / "nope", "--out", tmp_path / "o")
    assert rc == 2 and "nope" in err and "does not exist" in err and len(err.strip().splitlines()) == 1
    crops = tmp_path / "crops"
    crops.mkdir()
    (crops / "manifest.json").write_text(json.dumps({"format": "vgq-crops", "format_version": 1}))
    rc, _, err = _cli(capsys, "planner-grasps", "--grasps", crops, "--out", tmp_path / "o")
    assert rc == 2 and "vgq-crops" in err
    paper = tmp_path / "paper"
    shutil.copytree(src, paper)
    m = json.loads((paper / "manifest.json").read_text())
    m["config"]["label"]["kind"] = "paper"
    (paper / "manifest.json").write_text(json.dumps(m))
    rc, _, err = _cli(capsys, "planner-grasps", "--grasps", paper, "--out", tmp_path / "o")
    assert rc == 2 and "not physics-labelled" in err and "--trials" in err
    assert not (tmp_path / "o").exists()


def test_objects_the_source_finishes_later_are_picked_up(made, tmp_path):
    """A source still being generated: an object it has not finished is skipped as not in the
    source, and done once the source has it (the split population follows the source)."""
    src, _ = made
    part = tmp_path / "part"
    shutil.copytree(src, part)
    m = json.loads((part / "manifest.json").read_text())
    full = json.loads(json.dumps(m))
    m["shards"] = [s for s in m["shards"] if s["object_id"] != 4]
    m["objects"][4]["status"] = "pending"
    storage.update_counts(m)
    storage.write_manifest(part, m)
    out = tmp_path / "o"
    o = run_planner_grasps(part, out, PARAMS, max_objects=2, **QUIET)
    assert o["objects"][4]["status"] == "skipped" and "not in the source" in o["objects"][4]["reason"]
    assert o["split_object_ids"] == [0, 1, 2, 3]
    storage.write_manifest(part, full)
    o = run_planner_grasps(part, out, PARAMS, max_objects=2, **QUIET)
    assert o["objects"][4]["status"] == "pending" and o["split_object_ids"] == [0, 1, 2, 3, 4]
    o = run_planner_grasps(part, out, PARAMS, **QUIET)
    assert o["complete"] and o["objects"][4]["status"] == "done"
