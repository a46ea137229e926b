"""The planner's ordering: a within-scene ranker on what the planner knows of each candidate.

The network's score alone picks, among one scene's candidates, the one that survives the
physics oracle's lift and shake only a little more often than a random pick (docs/planning.md).
A conditional logit (a softmax over one scene's candidates, fitted to the share of each scene's
trials that held) on the plan features of :mod:`planning.features` (the score's logit, the
contact distance, the gripper's clearance above the estimated table, the TCP's height, the
approach and jaw-axis tilts, the TCP's distance from the object's estimated centre of mass)
ranks them better: a :class:`planning.linear.LinearModel` whose value is the utility. Fitted on a judged pool of candidates of
training objects (``python -m planning.bench pool --split train --json``), it lives beside the
model (:data:`FILE` in the model folder); a model without one plans by the score.

Fit: ``python -m planning.ranker FIT.json --model DIR [--judge TEST.json ...]``.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np

from . import model_files
from .features import PLAN_FEATURES, read_pool
from .linear import FEATURES, LinearModel, design, fit_command

#: the ranker's file name in a model folder
FILE = "planner_ranker.json"


def fit_conditional_logit(X: np.ndarray, held: np.ndarray, scene: np.ndarray, l2: float = 0.05) -> np.ndarray:
    """Weights (d,) of a softmax over each scene's rows (X standardised by the caller) fitted by
    cross-entropy to the scene's distribution of trials held; scenes where nothing held are left out."""
    from scipy.optimize import minimize  # fitting only: the service loads a fitted ranker without scipy

    groups = [np.flatnonzero(scene == s) for s in np.unique(scene)]
    groups = [g for g in groups if held[g].sum() > 0]
    if not groups:
        raise ValueError("no scene has a candidate that held: nothing to fit")

    def loss(w):
        total, grad = 0.0, np.zeros_like(w)
        for g in groups:
            t = X[g] @ w
            t = t - t.max()
            p = np.exp(t)
            p /= p.sum()
            q = held[g] / held[g].sum()
            total -= q @ np.log(p + 1e-12)
            grad -= X[g].T @ (q - p)
        return total / len(groups) + l2 * w @ w, grad / len(groups) + 2 * l2 * w

    return minimize(loss, np.zeros(X.shape[1]), jac=True, method="L-BFGS-B").x


def pool_rows(paths) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """(plan features by name, trials held (n,), scene (n,)) of one pool JSON or several (their
    scenes numbered apart); ValueError naming a pool that lacks the plan features."""
    paths = [paths] if isinstance(paths, (str, Path)) else list(paths)
    parts, offset = [], 0
    for p in paths:
        rows = read_pool(p)
        missing = [f"plan_{k}" for k in PLAN_FEATURES if f"plan_{k}" not in rows]
        if missing:
            raise ValueError(f"{p}: its candidate rows lack {missing} (written by an older planning.bench pool)")
        f = {k: np.asarray(rows[f"plan_{k}"], dtype=np.float64) for k in PLAN_FEATURES}
        sc = np.asarray(rows["scene"])
        parts.append((f, np.asarray(rows["held"], dtype=np.float64), sc + offset))
        offset += int(sc.max()) + 1 if len(sc) else 0
    feats = {k: np.concatenate([f[k] for f, _, _ in parts]) for k in PLAN_FEATURES}
    return feats, np.concatenate([h for _, h, _ in parts]), np.concatenate([sc for _, _, sc in parts])


def fit(paths, features: tuple[str, ...] = FEATURES) -> LinearModel:
    """The conditional logit on ``features`` fitted to a pool (or pools) of judged candidates:
    its value is the candidates' utility (higher ranks first; only differences within one scene
    mean anything)."""
    feats, held, scene = pool_rows(paths)
    m = LinearModel.standardising(design(feats, features), features)
    return dataclasses.replace(m, weights=fit_conditional_logit(m.standardised(feats), held, scene))


def precision_at_1(rank: np.ndarray, positive: np.ndarray, scene: np.ndarray) -> float:
    """Mean over scenes of ``positive`` at the scene's highest ``rank``."""
    return float(np.mean([positive[scene == s][np.argmax(rank[scene == s])] for s in np.unique(scene)]))


def judge(ranker: LinearModel, paths) -> dict:
    """Precision@1 among a pool's judged candidates (held in more than half of the trials) of the
    ranker, of the score alone and of a random pick."""
    feats, held, scene = pool_rows(paths)
    pos = held > 0.5
    return {
        "pools": [Path(p).name for p in ([paths] if isinstance(paths, (str, Path)) else paths)],
        "candidates": int(len(held)),
        "scenes": int(len(np.unique(scene))),
        "p_at_1_ranker": precision_at_1(ranker.value(feats), pos, scene),
        "p_at_1_score": precision_at_1(feats["score"], pos, scene),
        "p_at_1_random": float(np.mean([pos[scene == s].mean() for s in np.unique(scene)])),
    }


def load(model_dir: str | Path) -> LinearModel | None:
    """The ranker in ``model_dir``, or None when it has none; ValueError naming a malformed file."""
    return model_files.read(model_dir, FILE, "ranker", LinearModel.from_dict, "a planner ranker")


def main(argv=None) -> int:
    return fit_command(
        argv,
        prog="python -m planning.ranker",
        description=__doc__.splitlines()[0],
        file=FILE,
        key="ranker",
        fit=fit,
        judge=judge,
        what="the ranker",
        features_help="",
        headline=lambda m: (
            "utility weights (standardised): " + ", ".join(f"{k} {x:+.3f}" for k, x in zip(m.features, m.weights))
        ),
        line=lambda r: (
            f"{r['candidates']} candidates of {r['scenes']} scenes; precision@1 among judged: ranker "
            f"{100 * r['p_at_1_ranker']:.1f}%, score {100 * r['p_at_1_score']:.1f}%, random {100 * r['p_at_1_random']:.1f}%"
        ),
    )


if __name__ == "__main__":
    sys.exit(main())
