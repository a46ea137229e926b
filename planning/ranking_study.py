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
from scipy.optimize import minimize

from .features import PLAN_FEATURES, read_pool

#: the feature sets tried, by name (score: its logit)
RANKERS: dict[str, tuple[str, ...]] = {
    "score": ("score",),
    "width": ("width",),
    "score + width": ("score", "width"),
    "all plan features": tuple(k for k in PLAN_FEATURES if k != "seen"),
}


def pools_rows(paths) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """:func:`pool_rows` of one pool JSON or several (their scenes numbered apart)."""
    paths = [paths] if isinstance(paths, (str, Path)) else list(paths)
    parts, offset = [], 0
    for p in paths:
        f, h, sc = pool_rows(p)
        parts.append((f, h, sc + offset))
        offset += int(sc.max()) + 1 if len(sc) else 0
    feats = {k: np.concatenate([f[k] for f, _, _ in parts]) for k in PLAN_FEATURES}
    return feats, np.concatenate([h for _, h, _ in parts]), np.concatenate([sc for _, _, sc in parts])


def pool_rows(path: str | Path) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
    """(plan features by name, trials held (n,), scene (n,)) of a pool JSON; ValueError naming
    what is missing."""
    rows = read_pool(path)
    missing = [f"plan_{k}" for k in PLAN_FEATURES if f"plan_{k}" not in rows]
    if missing:
        raise ValueError(f"{path}: its candidate rows lack {missing} (written by an older planning.bench pool)")
    feats = {k: np.asarray(rows[f"plan_{k}"], dtype=np.float64) for k in PLAN_FEATURES}
    return feats, np.asarray(rows["held"], dtype=np.float64), np.asarray(rows["scene"])


def design(feats: dict[str, np.ndarray], names: tuple[str, ...], fill: np.ndarray | None = None) -> np.ndarray:
    """(n, len(names)) columns; the score as a logit; NaN (no table estimate) -> ``fill`` (column means)."""
    cols = []
    for k in names:
        x = feats[k]
        if k == "score":
            s = np.clip(x, 1e-6, 1 - 1e-6)
            x = np.log(s / (1 - s))
        cols.append(x)
    X = np.stack(cols, axis=1)
    if fill is None:  # column means of the finite values (0 for a column with none)
        ok = np.isfinite(X)
        fill = np.where(ok, X, 0.0).sum(axis=0) / np.maximum(ok.sum(axis=0), 1)
    return np.where(np.isfinite(X), X, fill)


def fit_conditional_logit(X: np.ndarray, held: np.ndarray, scene: np.ndarray, l2: float = 0.05) -> np.ndarray:
    """Weights (d,) of a softmax over each scene's rows (X standardised by the caller) fitted by
    cross-entropy to the scene's distribution of trials held; scenes where nothing held are left out."""
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


def precision_at_1(rank: np.ndarray, positive: np.ndarray, scene: np.ndarray) -> float:
    """Mean over scenes of ``positive`` at the scene's highest ``rank``."""
    return float(np.mean([positive[scene == s][np.argmax(rank[scene == s])] for s in np.unique(scene)]))


def within_scene_auc(x: np.ndarray, positive: np.ndarray, scene: np.ndarray) -> tuple[float, int]:
    """(mean ROC AUC of ``x`` inside each scene with both outcomes, number of such scenes)."""
    from training.metrics import auc

    a = [auc(x[scene == s], positive[scene == s]) for s in np.unique(scene) if 0 < positive[scene == s].mean() < 1]
    return (float(np.mean(a)) if a else float("nan")), len(a)


def study(fit_path, judge_path) -> dict:
    """Each of :data:`RANKERS` fitted on ``fit_path``'s pool and judged on ``judge_path``'s (a
    path or a list of paths: their pools together)."""
    fa, ha, sa = pools_rows(fit_path)
    fb, hb, sb = pools_rows(judge_path)
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
        Xa = design(fa, names)
        mu, sd = Xa.mean(axis=0), Xa.std(axis=0) + 1e-12
        w = fit_conditional_logit((Xa - mu) / sd, ha, sa)
        r = ((design(fb, names, fill=mu) - mu) / sd) @ w
        out["rankers"][name] = {
            "features": list(names),
            "weights": w.tolist(),
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
