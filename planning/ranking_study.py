"""Could a ranker on what the planner knows pick better than the network's score alone?

Input: the judged pools ``python -m planning.bench pool --json`` writes (``candidate_rows``: each
judged candidate's scene, its plan-time features ``plan_*`` from :mod:`planning.features` and
the fraction of its physics trials that held). A within-scene ranker (conditional logit: a
softmax over each scene's candidates, fitted to the scene's share of trials held) is fitted on
one pool (objects of the training split) and judged on another (test objects), against the
network's score alone and a random pick:

* ``p_at_1``: the top-ranked judged candidate of a scene held in more than half its trials,
  averaged over scenes (precision@1 among the judged candidates, not over the whole pool);
* ``within_scene_auc``: each feature's ROC AUC for "held in more than half" inside a scene,
  averaged over scenes with both outcomes; ranking only ever compares grasps of one scene.

Run: ``python -m planning.ranking_study FIT.json JUDGE.json [JUDGE2.json ...]``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from .features import PLAN_FEATURES
from .linear import FEATURES, design
from .ranker import fit, pool_rows, precision_at_1

#: the feature sets tried, by name (score: its logit)
RANKERS: dict[str, tuple[str, ...]] = {
    "score": ("score",),
    "width": ("width",),
    "score + width": ("score", "width"),
    "all plan features": FEATURES,  # the planner's ranker (planning.ranker)
}


def within_scene_auc(x: np.ndarray, positive: np.ndarray, scene: np.ndarray) -> tuple[float, int]:
    """(mean ROC AUC of ``x`` inside each scene with both outcomes, number of such scenes)."""
    from training.metrics import auc

    a = [auc(x[scene == s], positive[scene == s]) for s in np.unique(scene) if 0 < positive[scene == s].mean() < 1]
    return (float(np.mean(a)) if a else float("nan")), len(a)


def study(fit_path, judge_path) -> dict:
    """Each of :data:`RANKERS` fitted on ``fit_path``'s pool and judged on ``judge_path``'s (a
    path or a list of paths: their pools together)."""
    _, ha, sa = pool_rows(fit_path)
    fb, hb, sb = pool_rows(judge_path)
    pos = hb > 0.5
    out = {
        "fit": {"candidates": int(len(ha)), "scenes": int(len(np.unique(sa)))},
        "judge": {"candidates": int(len(hb)), "scenes": int(len(np.unique(sb)))},
        "random_p_at_1": float(np.mean([pos[sb == s].mean() for s in np.unique(sb)])),
        "ceiling_p_at_1": float(np.mean([pos[sb == s].any() for s in np.unique(sb)])),
        "within_scene_auc": {},
        "rankers": {},
    }
    for k in PLAN_FEATURES:
        a, n = within_scene_auc(design(fb, (k,))[:, 0], pos, sb)  # NaN filled; the score's logit ranks alike
        out["within_scene_auc"][k] = {"auc": a, "scenes": n}
    for name, names in RANKERS.items():
        ranker = fit(fit_path, names)
        r = ranker.value(fb)
        out["rankers"][name] = {
            "features": list(names),
            "weights": ranker.weights.tolist(),
            "p_at_1": precision_at_1(r, pos, sb),
            "mean_held_of_top": precision_at_1(r, hb, sb),
        }
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m planning.ranking_study", description=__doc__.splitlines()[0])
    ap.add_argument("fit", help="pool JSON to fit on (planning.bench pool --split train --json ...)")
    ap.add_argument(
        "judge", nargs="+", help="pool JSON(s) to judge on, together (planning.bench pool --split test --json ...)"
    )
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args(argv)
    try:
        out = study(args.fit, args.judge)
    except ValueError as e:
        print(f"planning.ranking_study: {e}", file=sys.stderr)
        return 2
    j = out["judge"]
    print(f"judged on {j['candidates']} candidates of {j['scenes']} scenes (fitted on {out['fit']['candidates']})")
    for k, v in out["within_scene_auc"].items():
        print(f"  within-scene AUC {k:16s} {v['auc']:.3f}  ({v['scenes']} scenes with both outcomes)")
    for name, r in out["rankers"].items():
        print(
            f"  ranker {name:18s} precision@1 among judged {100 * r['p_at_1']:5.1f}%  (top's trials held {100 * r['mean_held_of_top']:.1f}%)"
        )
    print(
        f"  random pick {100 * out['random_p_at_1']:.1f}%; a positive among the judged: {100 * out['ceiling_p_at_1']:.1f}% of scenes"
    )
    if args.json:
        from vgq import atomic

        atomic.write_bytes(Path(args.json), json.dumps(out, indent=1).encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
