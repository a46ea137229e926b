"""planning.ranking_study: a feature that decides which grasps hold is found and ranks them first."""

import json

import numpy as np

from planning.features import PLAN_FEATURES
from planning.ranking_study import main, study


def _pool(path, seed: int, scenes: int = 12, per: int = 10):
    """Scenes where the wider half of the grasps hold and the score is noise."""
    rng = np.random.default_rng(seed)
    n = scenes * per
    width = rng.uniform(0.005, 0.05, n)
    scene = np.repeat(np.arange(scenes), per)
    held = np.zeros(n)
    for s in range(scenes):
        m = np.flatnonzero(scene == s)
        held[m[np.argsort(width[m])[per // 2 :]]] = rng.uniform(0.6, 1.0, per // 2)
    rows = {f"plan_{k}": rng.uniform(0, 1, n).tolist() for k in PLAN_FEATURES}
    rows.update(plan_width=width.tolist(), held=held.tolist(), scene=scene.tolist())
    path.write_text(json.dumps({"candidate_rows": rows}))
    return path


def test_the_feature_that_decides_is_ranked_first(tmp_path):
    out = study(_pool(tmp_path / "fit.json", 0), _pool(tmp_path / "judge.json", 1))
    assert out["within_scene_auc"]["width"]["auc"] == 1.0 and out["within_scene_auc"]["width"]["scenes"] == 12
    assert out["rankers"]["width"]["p_at_1"] == 1.0 and out["rankers"]["width"]["weights"][0] > 0
    assert out["random_p_at_1"] == 0.5 and out["ceiling_p_at_1"] == 1.0
    assert out["rankers"]["score"]["p_at_1"] < 1.0  # noise does not rank
    two = study(tmp_path / "fit.json", [tmp_path / "judge.json", _pool(tmp_path / "judge2.json", 2)])
    assert two["judge"] == {"candidates": 240, "scenes": 24}  # the pools' scenes kept apart


def test_a_pool_without_plan_features_exits_2_naming_them(tmp_path, capsys):
    old = tmp_path / "old.json"
    old.write_text(json.dumps({"candidate_rows": {"held": [1.0], "scene": [0], "score": [0.5]}}))
    assert main([str(old), str(old)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "plan_score" in err and "old.json" in err
