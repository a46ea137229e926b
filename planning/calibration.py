"""How likely a planned grasp is to hold: ``p_hold``, a logistic regression on the plan features
fitted to the share of the planner's own candidates that survived the physics oracle's lift and
shake.

The network's score is calibrated (``vgq.calibration``) for datagen's grasps on the true mesh; the
planner's candidates come from one depth image and hold far less often at the same score (its top
picks score ~0.9 and hold in ~30% of scenes, docs/planning.md), and the score alone tells those that
hold from those that fail little better than chance (ROC AUC ~0.65). Fitted on a judged pool of
planner candidates (``python -m planning.bench pool --split train --json``: candidates of training
objects, each with its trials), a :class:`planning.linear.LinearModel` on the plan features (the
score's logit, the jaw width, the gripper's pose against the estimated table, the TCP's distance
from the object's estimated centre) gives ``p_hold = sigmoid(value)``: the probability that the
grasp holds in more than half of the oracle's noisy trials. It lives beside the model (:data:`FILE`
in the model folder); a model without one plans with ``p_hold`` None. A file of the earlier form (a
Platt map of the score, key ``calibration``) is read as the same model on the score alone.

Fit: ``python -m planning.calibration FIT.json --model DIR [--judge TEST.json ...] [--features ...]``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from vgq.calibration import Calibration, expected_calibration_error

from . import model_files
from .linear import FEATURES, LinearModel, design, fit_command, sigmoid
from .ranker import pool_rows

#: the planner calibration's file name in a model folder
FILE = "planner_calibration.json"


def _parse(d: dict) -> LinearModel:
    """The file's model; an earlier file's Platt map of the score (key ``calibration``) as a
    model on the score's logit alone."""
    if "p_hold" in d:
        return LinearModel.from_dict(d["p_hold"])
    cal = Calibration.from_dict(d["calibration"])
    return LinearModel(("score",), np.zeros(1), np.ones(1), np.array([cal.slope]), cal.intercept + cal.prior_shift)


def load(model_dir: str | Path) -> LinearModel | None:
    """The planner calibration in ``model_dir``, or None when it has none; ValueError naming a
    malformed file."""
    return model_files.read(model_dir, FILE, None, _parse, "a planner calibration")


def p_hold(model: LinearModel, feats: dict[str, np.ndarray]) -> np.ndarray:
    """(n,) the probability that each candidate (its plan features ``feats``) holds."""
    return sigmoid(model.value(feats))


def fit(paths, features: tuple[str, ...] = FEATURES) -> LinearModel:
    """Logistic regression of "held in more than half of its trials" on ``features``, over the
    pool(s)' candidates as they come (no resampling to undo); a weak Gaussian prior (one
    pseudo-observation per weight) keeps it finite. ValueError for a pool where all held or
    all failed."""
    from export.calibrate import fit_logistic

    feats, held, _ = pool_rows(paths)
    y = (held > 0.5).astype(np.float64)
    if len(y) == 0 or y.min() == y.max():
        raise ValueError(
            f"{paths}: need candidates that held and candidates that failed, got {int(y.sum())} of {len(y)} held"
        )
    m = LinearModel.standardising(design(feats, features), features)
    X = np.c_[m.standardised(feats), np.ones(len(y))]
    w = fit_logistic(X, y, np.zeros(len(y)), np.zeros(X.shape[1]))
    return LinearModel(m.features, m.mean, m.std, w[:-1], float(w[-1]))


def report(model: LinearModel, paths) -> dict:
    """Expected calibration error (10 bins) and ROC AUC of the raw score and of ``p_hold`` on a
    pool (or pools)."""
    from training.metrics import auc

    feats, held, _ = pool_rows(paths)
    y = held > 0.5
    p = p_hold(model, feats)
    return {
        "pools": [Path(x).name for x in ([paths] if isinstance(paths, (str, Path)) else paths)],
        "candidates": int(len(y)),
        "held_more_than_half": float(y.mean()),
        "ece_score": expected_calibration_error(feats["score"], y),
        "ece_p_hold": expected_calibration_error(p, y),
        "auc_score": auc(feats["score"], y),
        "auc_p_hold": auc(p, y),
        "mean_score": float(feats["score"].mean()),
        "mean_p_hold": float(p.mean()),
    }


def main(argv=None) -> int:
    return fit_command(
        argv,
        prog="python -m planning.calibration",
        description=__doc__.splitlines()[0],
        file=FILE,
        key="p_hold",
        fit=fit,
        judge=report,
        what="the calibration",
        features_help="; score alone: a Platt map",
        headline=lambda m: (
            "p_hold = sigmoid("
            + f"{m.intercept:+.3f} + "
            + ", ".join(f"{k} {x:+.3f}" for k, x in zip(m.features, m.weights))
            + " (standardised))"
        ),
        line=lambda r: (
            f"{r['candidates']} candidates, {100 * r['held_more_than_half']:.1f}% held; mean p_hold "
            f"{r['mean_p_hold']:.3f}; ECE score {r['ece_score']:.3f} -> p_hold {r['ece_p_hold']:.3f}; "
            f"ROC AUC score {r['auc_score']:.3f} -> p_hold {r['auc_p_hold']:.3f}"
        ),
    )


if __name__ == "__main__":
    sys.exit(main())
