"""planning.bench: the oracle matches the label of the model's recipe and judges grasps by it."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from datagen.config import DatagenConfig
from planning.bench.oracle import default_oracle, judge
from planning.bench.scenes import BenchScene, recipe_config
from planning.types import PlanParams


class _Card:
    def __init__(self, config: dict):
        self.dataset = {"source": {"config": config}}


class _Model:
    def __init__(self, config: dict):
        self.card = _Card(config)


def test_a_recipe_recorded_before_the_label_setting_is_judged_by_ferrari_canny():
    old = DatagenConfig().to_dict()
    old.pop("label")  # the bundled v1 card's recipe: the paper's label
    cfg = recipe_config(_Model(old))
    assert cfg.label.kind == "paper" and default_oracle(cfg) == "fc"
    assert default_oracle(recipe_config(_Model(DatagenConfig().to_dict()))) == "physics"


def _box_scene() -> BenchScene:
    box = trimesh.creation.box(extents=[0.03, 0.04, 0.06])  # centre of mass at the origin
    T_wo = np.eye(4)
    T_wo[2, 3] = 0.03  # standing on the table
    T_wc = np.eye(4)  # camera 0.6 m above, looking down (camera z = world -z)
    T_wc[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T_wc[2, 3] = 0.6
    world = box.copy()
    world.apply_transform(T_wo)
    return BenchScene(0, box, world, T_wo, T_wc, np.zeros((4, 4)), 1.0 / 0.02)


def _grasp_cam(scene: BenchScene, z_world: float) -> np.ndarray:
    """Top-down grasp across the 3 cm side at height ``z_world``, in the camera frame."""
    T_wg = np.eye(4)
    T_wg[:3, :3] = [[1, 0, 0], [0, -1, 0], [0, 0, -1]]  # jaw axis x, approach down
    T_wg[:3, 3] = [0.0, 0.0, z_world]
    return np.linalg.inv(scene.T_world_camera) @ T_wg


def test_the_physics_oracle_runs_trials_and_skips_colliding_grasps():
    scene = _box_scene()
    cfg = DatagenConfig().with_overrides({"label.trials": 2})
    frames = np.stack([_grasp_cam(scene, 0.045), _grasp_cam(scene, 0.0)])  # held; fingers through the table
    v = judge(scene, frames, cfg, np.random.default_rng(0), oracle="physics")
    assert v["collides"].tolist() == [False, True]
    assert v["quality"][1] == 0.0 and v["quality"][0] > cfg.label.success_threshold
    assert v["positive"].tolist() == [True, False]
    with pytest.raises(ValueError, match="oracle"):
        judge(scene, frames, cfg, np.random.default_rng(0), oracle="psychic")


def test_held_out_objects_come_from_a_crop_file_or_a_crop_datasets_test_split(tmp_path):
    import json

    from planning.bench.scenes import heldout_object_ids

    np.savez(tmp_path / "crops.npz", object_id=np.array([7, 3, 7, 12]))
    assert heldout_object_ids(str(tmp_path / "crops.npz")) == [3, 7, 12]
    d = tmp_path / "crops"
    d.mkdir()
    counts = {"test": {"n": 5, "objects": [640, 12, 601]}, "train": {"n": 9, "objects": [5, 1]}}
    (d / "manifest.json").write_text(json.dumps({"format": "vgq-crops", "format_version": 1, "counts": counts}))
    assert heldout_object_ids(str(d)) == [12, 601, 640]
    assert heldout_object_ids(str(d), "train") == [1, 5]  # to fit something on objects the test never sees
    with pytest.raises(ValueError, match="no val objects"):
        heldout_object_ids(str(d), "val")


def test_unseen_objects_are_the_ones_the_recipes_dataset_never_held():
    from planning.bench.scenes import recipe_sources, scene_objects

    cfg = DatagenConfig.from_dict({**DatagenConfig().to_dict(), "num_objects": 3, "families": {"box": 2, "mug": 1}})
    ids, unseen = scene_objects("unseen", "test", cfg)
    recipe = recipe_sources(json.dumps(cfg.to_dict(), sort_keys=True))
    others = recipe_sources(json.dumps(unseen.to_dict(), sort_keys=True))
    assert [others[i].name for i in range(3)] == [s.name for s in recipe[:3]]  # the recipe's meshes come first
    picked = [others[i] for i in ids]
    meshes = [s for s in picked if s.family is None]
    assert len(meshes) == len(others) - 3 - 3 and ids[0] == 3  # every mesh past the recipe's first 3
    fams = [s for s in picked if s.family is not None]
    assert [s.name for s in fams] == [s.name for s in recipe[3:]]  # the same families and counts ...
    assert all(a.params != b.params for a, b in zip(fams, recipe[3:]))  # ... drawn anew
    assert scene_objects("examples/heldout_test_crops.npz", "test", cfg)[1] is cfg


def test_command_line_turns_the_top_view_off_with_zero():
    from planning.bench.cli import parse_args
    from planning.bench.common import plan_params

    assert plan_params(parse_args(["trials"])).top_view_cell == PlanParams().top_view_cell
    assert plan_params(parse_args(["trials", "--top-view-cell", "0"])).top_view_cell is None


def test_candidate_features_measure_the_grasp_against_the_true_scene():
    """planning.bench pool's features of a top-down grasp across a box standing on the table."""
    from planning.bench.pool import candidate_features
    from vgq.gripper import GripperGeometry

    scene = _box_scene()  # box centre of mass 3 cm above the table
    g = GripperGeometry()
    Tw = scene.T_world_camera @ _grasp_cam(scene, 0.045)
    contacts = np.array([[[-0.015, 0.0, 0.6 - 0.045], [0.015, 0.0, 0.6 - 0.045]]])
    f = candidate_features(scene, Tw[None], contacts, [0.7], g)
    assert f["fingertip_height"][0] == pytest.approx(0.045 - g.tip_offset)
    assert f["tcp_height"][0] == pytest.approx(0.045)
    assert f["width"][0] == pytest.approx(0.03)
    assert f["com_line_offset"][0] == pytest.approx(0.015)  # the jaw line passes 1.5 cm above the centre of mass
    assert f["approach_tilt"][0] == pytest.approx(0.0, abs=1e-6)
    assert f["axis_tilt"][0] == pytest.approx(90.0)
    assert f["score"][0] == 0.7


def test_command_line_sets_the_approach_tilt_and_refuses_nonsense(capsys):
    from planning.bench.cli import parse_args
    from planning.bench.common import plan_params

    assert np.isclose(plan_params(parse_args(["precision", "--max-approach-tilt", "30"])).max_approach_tilt, np.pi / 6)
    assert np.isclose(plan_params(parse_args(["precision"])).max_approach_tilt, PlanParams().max_approach_tilt)
    with pytest.raises(SystemExit) as e:
        parse_args(["precision", "--max-approach-tilt", "120"])
    assert e.value.code == 2 and "--max-approach-tilt must be in (0, 90]" in capsys.readouterr().err


def test_pool_options_parse():
    from planning.bench.cli import parse_args

    a = parse_args(["pool", "--retest", "--split", "train"])
    assert a.retest and a.split == "train" and a.scenes == 60
    assert not parse_args(["pool"]).retest and parse_args(["pool"]).split == "test"


def test_ceiling_judges_each_scenes_best_true_mesh_grasp_again_on_fresh_trials(tmp_path, capsys):
    import json

    from planning.bench.cli import main, parse_args

    out = tmp_path / "ceiling.json"
    args = ["ceiling", "--scenes", "1", "--trials", "2", "--confirm", "3", "--threads", "1", "--json", str(out)]
    assert main(args) == 0
    s = json.loads(out.read_text())
    assert len(s["confirmed_again"]) == 1 and 0 <= s["confirmed_estimate"][0] <= 1  # the pick by 8 trials
    assert s["trials"] == 2 and s["scenes"] == 1 and s["scenes_with_grasps"] == 1  # seed 0's object has free grasps
    assert 0 <= s["best_positive_again"] <= 1 and 0 <= s["best_held_again"] <= 1
    assert set(s["by_first_count"]) <= {"1/2", "2/2"}  # grasps that held in at least half, by count
    assert "fresh trials" in capsys.readouterr().out
    assert parse_args(["ceiling"]).trials is None and parse_args(["pool"]).trials == 5  # ceiling: the recipe's
    with pytest.raises(SystemExit):
        parse_args(["ceiling", "--trials", "0"])
    other = tmp_path / "trials_seed1.json"
    other.write_text(json.dumps({"seed": 1, "scenes": 1, "rows": [{"top1_held": 0, "trials": 2}]}))
    for bad in (str(other), str(tmp_path / "missing.json"), str(out)):  # another run's scenes; no file; not `trials`
        with pytest.raises(SystemExit):
            parse_args(["ceiling", "--scenes", "1", "--plan", bad])


def test_the_plans_verdicts_are_counted_per_class_of_scene_by_its_best_true_mesh_grasp():
    from planning.bench.ceiling import plan_by_ceiling

    ceiling = {"seed": 0, "scenes": 3, "success_threshold": 0.5, "rows": []}
    ceiling["rows"] = [{"scene": 0, "confirmed_estimate": 0.9}, {"scene": 2, "confirmed_estimate": 0.3}]
    plan = {"seed": 0, "scenes": 3, "rows": [{"top1_held": 5, "trials": 8}, {}, {"top1_held": 0, "trials": 0}]}
    out = plan_by_ceiling(plan, ceiling)
    assert out["holds >= 75%"] == {"scenes": 1, "positive": 1} and out["holds < 50%"] == {"scenes": 1, "positive": 0}
    assert out["holds 50-75%"] == {"scenes": 0, "positive": 0}
    with pytest.raises(ValueError, match="same --seed"):
        plan_by_ceiling({**plan, "seed": 1}, ceiling)


def test_trials_judge_the_plan_the_score_alone_and_a_random_pick_on_the_same_scenes(tmp_path, capsys):
    import json

    from planning.bench.cli import main

    out = tmp_path / "trials.json"
    assert main(["trials", "--scenes", "2", "--trials", "2", "--threads", "1", "--json", str(out)]) == 0
    s = json.loads(out.read_text())
    assert s["ranked_by"] == "ranker" and s["scenes"] == 2 and s["trials"] == 2 * (2 - s["scenes_without_grasp"])
    for r in s["rows"]:
        assert all(0 <= r[f"{k}_held"] <= r["trials"] for k in ("top1", "score_top1", "random"))
    for k in ("top1", "score_top1", "random"):
        assert s[f"{k}_success"] == pytest.approx(s[f"{k}_held"] / max(s["trials"], 1))
        assert s[f"{k}_precision_se"] == pytest.approx(np.sqrt(s[f"{k}_precision"] * (1 - s[f"{k}_precision"]) / 2))
        assert 0 <= s[f"{k}_precision"] <= 1
    assert "the network's score alone" in capsys.readouterr().out


def test_trials_judge_the_noise_averaged_score_on_the_same_trials(tmp_path):
    import json

    from planning.bench.cli import main, parse_args

    out = tmp_path / "trials.json"
    assert (
        main(["trials", "--scenes", "2", "--trials", "2", "--threads", "1", "--robust", "3", "--json", str(out)]) == 0
    )
    s = json.loads(out.read_text())
    assert 0 <= s["robust_top1_held"] <= s["trials"] and all("robust_top1_held" in r for r in s["rows"])
    with pytest.raises(SystemExit):
        parse_args(["trials", "--robust", "-1"])


def test_noisy_scores_average_the_planners_own_scores():
    """With no noise the average is the planner's score of the grasp itself."""
    import dataclasses
    import unittest.mock as mock

    from datagen.physics import PhysicsParams
    from planning.bench.common import MODEL_DIR, load_model
    from planning.bench.trials import noisy_scores
    from planning.policy import grasp_rows, plan, window_scorer
    from planning.types import PlanParams
    from tests.planning_scenes import boxes_scene
    from vgq.camera import DEFAULT_INTRINSICS as intr

    depth = boxes_scene()[0]
    model = load_model(MODEL_DIR, 1)
    res = plan(depth, intr, model, k=5, seed=0)
    frames = res.candidates["frames"][:8]
    own, _ = window_scorer(model, depth, intr, PlanParams().windows).score(grasp_rows(frames, intr))
    quiet = dataclasses.replace(PhysicsParams(), sigma_translation=0.0, sigma_rotation=0.0)
    with mock.patch("datagen.physics.PhysicsParams", return_value=quiet):
        avg = noisy_scores(model, depth, intr, frames, 4, PlanParams(), 0)
    assert np.allclose(avg, own, atol=1e-6)
    noisy = noisy_scores(model, depth, intr, frames, 4, PlanParams(), 0)
    assert noisy.shape == (8,) and not np.allclose(noisy, own)


@pytest.mark.parametrize("flag,value", [("--model", "/nonexistent"), ("--heldout", "/nonexistent.npz")])
def test_a_model_or_heldout_file_it_cannot_read_exits_2_naming_it(capsys, flag, value):
    from planning.bench.cli import main

    assert main(["timing", flag, value, "--scenes", "1", "--repeats", "2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "/nonexistent" in err[0]


def test_timing_against_another_checkout_interleaves_the_two_planners(capsys, tmp_path):
    from pathlib import Path

    from planning.bench.cli import main

    here = Path(__file__).resolve().parents[1]  # this checkout's own planner stands in for another's
    assert main(["timing", "--scenes", "1", "--repeats", "2", "--against", str(here)]) == 0
    out = capsys.readouterr().out
    assert f"against {here} (interleaved" in out and "this / that: p50" in out
    assert main(["timing", "--scenes", "1", "--repeats", "2", "--against", str(tmp_path)]) == 2
    assert "no planning/policy.py" in capsys.readouterr().err
