"""planning.ranker: the planner's ordering, fitted on a judged pool, carried by the model folder."""

import json
import shutil

import numpy as np
import pytest

from planning import ranker as pr
from planning.features import PLAN_FEATURES
from planning.linear import LinearModel
from service.runtime import FastModel, ModelError

MODEL_DIR = "models/fast-vgqcnn-default"


def _pool(path, seed: int, scenes: int = 30, per: int = 12):
    """Scenes where the grasps closer to the table's normal (small approach tilt) hold and the
    score is noise."""
    rng = np.random.default_rng(seed)
    n = scenes * per
    rows = {f"plan_{k}": rng.uniform(0, 1, n) for k in PLAN_FEATURES}
    rows["plan_approach_tilt"] = rng.uniform(0, 60, n)
    rows["plan_table_clearance"][rng.uniform(size=n) < 0.2] = np.nan  # scenes without a table estimate
    held = (rng.uniform(size=n) < 1 / (1 + np.exp((rows["plan_approach_tilt"] - 30) / 5))).astype(float)
    out = {k: v.tolist() for k, v in rows.items()}
    out.update(held=held.tolist(), scene=np.repeat(np.arange(scenes), per).tolist())
    path.write_text(json.dumps({"candidate_rows": out}).replace("NaN", "null"))
    return path


def test_fit_finds_what_decides_and_writes_it_beside_the_model(tmp_path, capsys):
    model = tmp_path / "model"
    model.mkdir()
    (model / "model_card.json").write_text("{}")
    fit, judge = _pool(tmp_path / "fit.json", 0), _pool(tmp_path / "judge.json", 1)
    assert pr.main([str(fit), "--model", str(model), "--judge", str(judge)]) == 0
    ranker = pr.load(model)
    w = dict(zip(ranker.features, ranker.weights))
    assert w["approach_tilt"] < 0 and abs(w["approach_tilt"]) > 3 * max(
        abs(v) for k, v in w.items() if k != "approach_tilt"
    )
    rec = json.loads((model / pr.FILE).read_text())["judged_on"]
    assert rec["p_at_1_ranker"] > rec["p_at_1_random"] + 0.2 and rec["p_at_1_ranker"] > rec["p_at_1_score"]
    assert "precision@1" in capsys.readouterr().out
    feats = {k: np.array([0.5, 0.5]) for k in PLAN_FEATURES} | {"approach_tilt": np.array([10.0, 50.0])}
    feats["table_clearance"] = np.array([np.nan, np.nan])  # missing: counts as the mean
    u = ranker.value(feats)
    assert np.isfinite(u).all() and u[0] > u[1]


def test_bad_inputs_exit_2_naming_them(tmp_path, capsys):
    fit = _pool(tmp_path / "fit.json", 0)
    assert pr.main([str(fit), "--model", str(tmp_path)]) == 2
    assert "not a model folder" in capsys.readouterr().err
    (tmp_path / "model_card.json").write_text("{}")
    (tmp_path / "old.json").write_text(json.dumps({"candidate_rows": {"score": [0.5], "held": [1.0], "scene": [0]}}))
    assert pr.main([str(tmp_path / "old.json"), "--model", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "plan_score" in err and "old.json" in err and not (tmp_path / pr.FILE).exists()
    assert pr.main([str(fit), "--model", str(tmp_path), "--features", "score,grip"]) == 2
    assert "--features: ['grip']" in capsys.readouterr().err and not (tmp_path / pr.FILE).exists()
    assert pr.main([str(fit), "--model", str(tmp_path), "--features", "width, approach_tilt"]) == 0
    assert pr.load(tmp_path).features == ("width", "approach_tilt")


def test_the_model_folder_decides_the_planner_order(tmp_path):
    pytest.importorskip("trimesh")
    from planning.policy import plan
    from planning.types import PlanParams
    from tests.planning_scenes import boxes_scene
    from vgq.camera import DEFAULT_INTRINSICS

    depth = boxes_scene()[0]
    params = PlanParams(num_candidates=64)
    model = tmp_path / "model"
    shutil.copytree(MODEL_DIR, model, ignore=shutil.ignore_patterns(pr.FILE))
    bare = FastModel(model, threads=1, head_precision="fp32", encoder_precision="fp32")
    res = plan(depth, DEFAULT_INTRINSICS, bare, k=3, params=params)
    assert bare.planner_ranker is None and res.ranked_by == "score" and res.to_dict()["ranked_by"] == "score"
    assert [g.score for g in res.grasps] == sorted((g.score for g in res.grasps), reverse=True)
    # a ranker that only wants wide grasps: the widest candidate comes first
    wide = LinearModel(("width",), np.array([0.03]), np.array([0.01]), np.array([1.0]))
    (model / pr.FILE).write_text(json.dumps({"ranker": wide.to_dict()}))
    m = FastModel(model, threads=1, head_precision="fp32", encoder_precision="fp32")
    res = plan(depth, DEFAULT_INTRINSICS, m, k=3, params=params)
    assert res.ranked_by == "ranker" and res.grasps[0].width == pytest.approx(res.candidates["widths"].max())
    assert [g.width for g in res.grasps] == sorted((g.width for g in res.grasps), reverse=True)
    (model / pr.FILE).write_text(json.dumps({"ranker": {**wide.to_dict(), "std": [0.0]}}))
    with pytest.raises(ModelError, match="not a planner ranker"):
        FastModel(model, threads=1, head_precision="fp32", encoder_precision="fp32")
