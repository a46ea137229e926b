"""How likely a planned grasp is to hold: the network's score mapped to the share of the planner's
own candidates that survived the physics oracle's lift and shake.

The network's score is calibrated (``vgq.calibration``) for datagen's grasps on the true mesh; the
planner's candidates come from one depth image and hold far less often at the same score (its top
picks score ~0.9 and hold in ~30% of scenes, docs/planning.md). A Platt map fitted on a judged
pool of planner candidates (``python -m planning.bench pool --split train --json``: candidates of
training objects, each with its trials) turns the score into ``p_hold``: the probability that the
grasp holds in more than half of the oracle's noisy trials. It is monotone, so it changes no
ranking. The map lives beside the model (:data:`FILE` in the model folder); a model without one
plans with ``p_hold`` None.

Fit: ``python -m planning.calibration FIT.json --model DIR [--judge TEST.json]``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from vgq.calibration import Calibration, expected_calibration_error

from . import model_files
from .features import read_pool

#: the planner calibration's file name in a model folder
FILE = "planner_calibration.json"


def load(model_dir: str | Path) -> Calibration | None:
    """The planner calibration in ``model_dir``, or None when it has none; ValueError naming a
    malformed file."""
    return model_files.read(model_dir, FILE, "calibration", Calibration.from_dict, "a planner calibration")


def pool_scores(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(score (n,), held in more than half of its trials (n,) bool) of a pool JSON."""
    rows = read_pool(path)
    try:
        return np.asarray(rows["plan_score"], np.float64), np.asarray(rows["held"], np.float64) > 0.5
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{path}: not a pool JSON of planning.bench pool --json ({e})") from None


def fit(path: str | Path) -> Calibration:
    """Platt map of the pool's scores to "held in more than half", at the pool's own positivity
    (the planner's candidates as they come: no resampling to undo)."""
    from export.calibrate import fit_platt

    score, held = pool_scores(path)
    try:
        return fit_platt(score, held)  # refuses an empty pool, or one where all held or all failed
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None


def report(cal: Calibration, path: str | Path) -> dict:
    """Expected calibration error (10 bins) of the raw score and of ``p_hold`` on a pool."""
    score, y = pool_scores(path)
    return {
        "pool": Path(path).name,
        "candidates": int(len(y)),
        "held_more_than_half": float(y.mean()),
        "ece_score": expected_calibration_error(score, y),
        "ece_p_hold": expected_calibration_error(cal.apply(score), y),
        "mean_score": float(score.mean()),
        "mean_p_hold": float(cal.apply(score).mean()),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m planning.calibration", description=__doc__.splitlines()[0])
    ap.add_argument("fit", help="pool JSON of training objects (planning.bench pool --split train --json ...)")
    ap.add_argument("--model", required=True, help="model folder to write planner_calibration.json into")
    ap.add_argument("--judge", help="pool JSON of test objects to measure the calibration on")
    args = ap.parse_args(argv)
    try:
        model_files.check_model_folder(args.model)
        cal = fit(args.fit)
        rec = {"calibration": cal.to_dict(), "fitted_on": report(cal, args.fit)}
        if args.judge:
            rec["judged_on"] = report(cal, args.judge)
    except ValueError as e:
        print(f"planning.calibration: {e}", file=sys.stderr)
        return 2
    path = model_files.write(args.model, FILE, rec)
    print(f"p_hold = sigmoid({cal.slope:.4g} logit(score) + {cal.intercept:.4g}) -> {path}")
    for k in ("fitted_on", "judged_on"):
        if k in rec:
            r = rec[k]
            print(
                f"{k}: {r['candidates']} candidates, {100 * r['held_more_than_half']:.1f}% held; mean score "
                f"{r['mean_score']:.3f} vs p_hold {r['mean_p_hold']:.3f}; ECE {r['ece_score']:.3f} -> {r['ece_p_hold']:.3f}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
