"""planning.calibration: the planner's p_hold, fitted on a judged pool, carried by the model folder."""

import json
import shutil

import numpy as np
import pytest

from planning import calibration as pc
from service.runtime import FastModel, ModelError

MODEL_DIR = "models/fast-vgqcnn-default"


def _pool(path, seed: int = 0, n: int = 4000):
    """Candidates that hold with probability sigmoid(0.5 logit(score) - 1): a score that overstates."""
    rng = np.random.default_rng(seed)
    score = rng.uniform(0.02, 0.98, n)
    z = 0.5 * np.log(score / (1 - score)) - 1.0
    held = (rng.uniform(size=n) < 1 / (1 + np.exp(-z))).astype(float)
    path.write_text(json.dumps({"candidate_rows": {"plan_score": score.tolist(), "held": held.tolist()}}))
    return path


def test_fit_recovers_the_map_and_writes_it_beside_the_model(tmp_path, capsys):
    model = tmp_path / "model"
    model.mkdir()
    (model / "model_card.json").write_text("{}")
    assert (
        pc.main(
            [str(_pool(tmp_path / "fit.json")), "--model", str(model), "--judge", str(_pool(tmp_path / "j.json", 1))]
        )
        == 0
    )
    cal = pc.load(model)
    assert cal.slope == pytest.approx(0.5, abs=0.1) and cal.intercept == pytest.approx(-1.0, abs=0.15)
    rec = json.loads((model / pc.FILE).read_text())
    assert rec["judged_on"]["ece_p_hold"] < 0.05 < rec["judged_on"]["ece_score"]
    assert "ECE" in capsys.readouterr().out


def test_bad_inputs_exit_2_naming_them(tmp_path, capsys):
    assert pc.main([str(_pool(tmp_path / "fit.json")), "--model", str(tmp_path)]) == 2
    assert "not a model folder" in capsys.readouterr().err
    (tmp_path / "model_card.json").write_text("{}")
    (tmp_path / "old.json").write_text(json.dumps({"candidate_rows": {"score": [0.5], "held": [1.0]}}))
    assert pc.main([str(tmp_path / "old.json"), "--model", str(tmp_path)]) == 2
    assert "not a pool JSON" in capsys.readouterr().err and not (tmp_path / pc.FILE).exists()


def test_a_model_folder_with_one_plans_with_p_hold(tmp_path):
    pytest.importorskip("trimesh")
    from planning.policy import plan
    from planning.types import PlanParams
    from tests.planning_scenes import boxes_scene
    from vgq.camera import DEFAULT_INTRINSICS

    depth = boxes_scene()[0]
    model = tmp_path / "model"
    shutil.copytree(MODEL_DIR, model, ignore=shutil.ignore_patterns(pc.FILE))
    bare = FastModel(model, threads=1, head_precision="fp32", encoder_precision="fp32")
    assert bare.planner_calibration is None
    assert all(
        g.p_hold is None
        for g in plan(depth, DEFAULT_INTRINSICS, bare, k=2, params=PlanParams(num_candidates=64)).grasps
    )
    assert pc.main([str(_pool(tmp_path / "fit.json")), "--model", str(model)]) == 0
    m = FastModel(model, threads=1, head_precision="fp32", encoder_precision="fp32")
    res = plan(depth, DEFAULT_INTRINSICS, m, k=2, params=PlanParams(num_candidates=64))
    for g in res.grasps:
        assert g.p_hold == pytest.approx(float(m.planner_calibration.apply(np.array([g.score]))[0]))
        assert g.to_dict()["p_hold"] == g.p_hold and 0 < g.p_hold < g.score
    (model / pc.FILE).write_text("{}")
    with pytest.raises(ModelError, match="not a planner calibration"):
        FastModel(model, threads=1, head_precision="fp32", encoder_precision="fp32")
