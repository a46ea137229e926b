"""planning.calibration: the planner's p_hold, fitted on a judged pool, carried by the model folder."""

import json
import shutil

import numpy as np
import pytest

from planning import calibration as pc
from planning.features import PLAN_FEATURES
from planning.linear import sigmoid
from service.runtime import FastModel, ModelError

MODEL_DIR = "models/fast-vgqcnn-default"


def _pool(path, seed: int = 0, scenes: int = 200, per: int = 20):
    """Candidates that hold with probability sigmoid(0.5 logit(score) - 80 centre_offset): a score
    that overstates, and a centre offset (m) that decides more."""
    rng = np.random.default_rng(seed)
    n = scenes * per
    rows = {f"plan_{k}": rng.uniform(0, 1, n) for k in PLAN_FEATURES}
    rows["plan_score"] = rng.uniform(0.02, 0.98, n)
    rows["plan_centre_offset"] = rng.uniform(0.0, 0.05, n)
    z = 0.5 * np.log(rows["plan_score"] / (1 - rows["plan_score"])) - 80 * rows["plan_centre_offset"]
    held = (rng.uniform(size=n) < sigmoid(z)).astype(float)
    out = {k: v.tolist() for k, v in rows.items()}
    out.update(held=held.tolist(), scene=np.repeat(np.arange(scenes), per).tolist())
    path.write_text(json.dumps({"candidate_rows": out}))
    return path


def test_fit_recovers_the_map_and_writes_it_beside_the_model(tmp_path, capsys):
    model = tmp_path / "model"
    model.mkdir()
    (model / "model_card.json").write_text("{}")
    fit, judge = _pool(tmp_path / "fit.json"), _pool(tmp_path / "j.json", 1)
    assert pc.main([str(fit), "--model", str(model), "--judge", str(judge)]) == 0
    m = pc.load(model)
    w = dict(zip(m.features, m.weights / m.std))  # per unit of each feature
    assert w["score"] == pytest.approx(0.5, abs=0.12) and w["centre_offset"] == pytest.approx(-80, abs=10)
    assert max(abs(w[k]) for k in ("width", "table_clearance", "tcp_height")) < 0.6  # noise columns
    rec = json.loads((model / pc.FILE).read_text())["judged_on"]
    assert rec["ece_p_hold"] < 0.04 < rec["ece_score"] and rec["auc_p_hold"] > rec["auc_score"] + 0.05
    assert "ROC AUC" in capsys.readouterr().out


def test_a_platt_map_of_the_score_is_still_read(tmp_path):
    old = {
        "calibration": {
            "method": "platt",
            "slope": 0.25,
            "intercept": -1.2,
            "fit_positivity": 0.3,
            "target_positivity": 0.3,
        }
    }
    (tmp_path / pc.FILE).write_text(json.dumps(old))
    m = pc.load(tmp_path)
    s = np.array([0.2, 0.9])
    feats = {k: np.zeros(2) for k in PLAN_FEATURES} | {"score": s}
    assert np.allclose(pc.p_hold(m, feats), sigmoid(0.25 * np.log(s / (1 - s)) - 1.2))


def test_bad_inputs_exit_2_naming_them(tmp_path, capsys):
    assert pc.main([str(_pool(tmp_path / "fit.json")), "--model", str(tmp_path)]) == 2
    assert "not a model folder" in capsys.readouterr().err
    (tmp_path / "model_card.json").write_text("{}")
    (tmp_path / "old.json").write_text(json.dumps({"candidate_rows": {"score": [0.5], "held": [1.0], "scene": [0]}}))
    assert pc.main([str(tmp_path / "old.json"), "--model", str(tmp_path)]) == 2
    assert "plan_score" in capsys.readouterr().err and not (tmp_path / pc.FILE).exists()
    one = _pool(tmp_path / "one.json", scenes=2, per=3)
    d = json.loads(one.read_text())
    d["candidate_rows"]["held"] = [1.0] * 6
    one.write_text(json.dumps(d))
    assert pc.main([str(one), "--model", str(tmp_path)]) == 2
    assert "6 of 6 held" in capsys.readouterr().err and not (tmp_path / pc.FILE).exists()


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
    params = PlanParams(num_candidates=64)
    assert all(g.p_hold is None for g in plan(depth, DEFAULT_INTRINSICS, bare, k=2, params=params).grasps)
    assert pc.main([str(_pool(tmp_path / "fit.json")), "--model", str(model)]) == 0
    m = FastModel(model, threads=1, head_precision="fp32", encoder_precision="fp32")
    res = plan(depth, DEFAULT_INTRINSICS, m, k=2, params=params)
    for g in res.grasps:
        i = int(np.flatnonzero(np.all(np.isclose(res.candidates["frames"], g.pose), axis=(1, 2)))[0])
        from planning.features import plan_features
        from planning.sampler import Candidates

        c = res.candidates
        one = Candidates(c["frames"][i : i + 1], c["contacts"][i : i + 1], c["widths"][i : i + 1], c["seen"][i : i + 1])
        feats = plan_features(one, c["scores"][i : i + 1], c["scene"], params.gripper)
        assert g.p_hold == pytest.approx(float(pc.p_hold(m.planner_calibration, feats)[0]))
        assert g.to_dict()["p_hold"] == g.p_hold and 0 < g.p_hold < 1
    (model / pc.FILE).write_text("{}")
    with pytest.raises(ModelError, match="not a planner calibration"):
        FastModel(model, threads=1, head_precision="fp32", encoder_precision="fp32")
