"""A linear model over the plan features (:mod:`planning.features`): the planner's ranker and its
``p_hold`` are both one, fitted on judged pools of planner candidates and kept beside the model.

value = intercept + sum_j weights[j] (x_j - mean[j]) / std[j] over ``features``, the score taken
as its logit and a missing value (NaN: no table estimate, no object region) as the mean."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from . import model_files
from .features import PLAN_FEATURES

#: the features the planner's models combine by default ("seen" is almost always 1: left out)
FEATURES: tuple[str, ...] = tuple(k for k in PLAN_FEATURES if k != "seen")


def design(feats: dict[str, np.ndarray], names: tuple[str, ...], fill: np.ndarray | None = None) -> np.ndarray:
    """(n, len(names)) columns; the score as a logit; NaN -> ``fill`` (default: the column means)."""
    cols = []
    for k in names:
        x = np.asarray(feats[k], dtype=np.float64)
        if k == "score":
            s = np.clip(x, 1e-6, 1 - 1e-6)
            x = np.log(s / (1 - s))
        cols.append(x)
    X = np.stack(cols, axis=1)
    if fill is None:  # column means of the finite values (0 for a column with none)
        ok = np.isfinite(X)
        fill = np.where(ok, X, 0.0).sum(axis=0) / np.maximum(ok.sum(axis=0), 1)
    return np.where(np.isfinite(X), X, fill)


def sigmoid(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * np.asarray(x, dtype=np.float64)))


@dataclass(frozen=True)
class LinearModel:
    features: tuple[str, ...]
    mean: np.ndarray  # (d,) of the design columns it was fitted on
    std: np.ndarray  # (d,) > 0
    weights: np.ndarray  # (d,) per standardised column
    intercept: float = 0.0

    @classmethod
    def standardising(cls, X: np.ndarray, features: tuple[str, ...]) -> LinearModel:
        """A model with no weights yet whose standardisation is that of ``X`` (n, d)."""
        return cls(tuple(features), X.mean(axis=0), X.std(axis=0) + 1e-12, np.zeros(X.shape[1]))

    def standardised(self, feats: dict[str, np.ndarray]) -> np.ndarray:
        """(n, d) standardised design columns of candidates whose plan features are ``feats``."""
        return (design(feats, self.features, fill=self.mean) - self.mean) / self.std

    def value(self, feats: dict[str, np.ndarray]) -> np.ndarray:
        """(n,) the model's value (a utility, or a logit) of the candidates with plan features ``feats``."""
        return self.standardised(feats) @ self.weights + self.intercept

    def to_dict(self) -> dict:
        return {
            "features": list(self.features),
            "mean": self.mean.tolist(),
            "std": self.std.tolist(),
            "weights": self.weights.tolist(),
            "intercept": float(self.intercept),
        }

    @classmethod
    def from_dict(cls, d: dict) -> LinearModel:
        feats = tuple(d["features"])
        unknown = [k for k in feats if k not in PLAN_FEATURES]
        if unknown or not feats:
            raise ValueError(f"features must be some of {list(PLAN_FEATURES)}, got {list(feats)}")
        arrs = [np.asarray(d[k], dtype=np.float64) for k in ("mean", "std", "weights")]
        if any(a.shape != (len(feats),) or not np.isfinite(a).all() for a in arrs) or (arrs[1] <= 0).any():
            raise ValueError("mean, std (> 0) and weights must be finite, one per feature")
        intercept = float(d.get("intercept", 0.0))
        if not np.isfinite(intercept):
            raise ValueError(f"intercept must be finite, got {intercept}")
        return cls(feats, *arrs, intercept)


def parse_features(text: str) -> tuple[str, ...]:
    """Comma-separated plan feature names; ValueError naming unknown ones."""
    features = tuple(k.strip() for k in text.split(",") if k.strip())
    unknown = [k for k in features if k not in PLAN_FEATURES]
    if unknown or not features:
        raise ValueError(f"--features: {unknown or 'none given'}; choose from {', '.join(PLAN_FEATURES)}")
    return features


def fit_command(
    argv,
    *,
    prog: str,
    description: str,
    file: str,
    key: str,
    fit: Callable[[list[str], tuple[str, ...]], LinearModel],
    judge: Callable[[LinearModel, list[str]], dict],
    what: str,
    features_help: str,
    headline: Callable[[LinearModel], str],
    line: Callable[[dict], str],
) -> int:
    """The command line of a linear model fitted on judged pools and written beside a model
    (``python -m planning.calibration`` / ``planning.ranker``): pool JSON(s) to fit on, ``--model``
    DIR, ``--judge`` pools, ``--features``. Writes ``{key: model, "fitted_on": judge(fit pools),
    "judged_on": judge(judge pools)}`` as ``file`` in DIR and prints ``headline(model)`` and a
    ``line(record)`` per judging. Exit 2 with one line for a bad pool, folder or feature."""
    ap = argparse.ArgumentParser(prog=prog, description=description)
    ap.add_argument(
        "fit", nargs="+", help="pool JSON(s) of training objects (planning.bench pool --split train --json)"
    )
    ap.add_argument("--model", required=True, help=f"model folder to write {file} into")
    ap.add_argument("--judge", nargs="+", help=f"pool JSON(s) of test objects to measure {what} on, together")
    ap.add_argument(
        "--features",
        default=",".join(FEATURES),
        help=f"comma-separated plan features (planning.features; default {','.join(FEATURES)}{features_help})",
    )
    args = ap.parse_args(argv)
    try:
        model_files.check_model_folder(args.model)
        model = fit(args.fit, parse_features(args.features))
        rec = {key: model.to_dict(), "fitted_on": judge(model, args.fit)}
        if args.judge:
            rec["judged_on"] = judge(model, args.judge)
    except ValueError as e:
        print(f"{prog.removeprefix('python -m ')}: {e}", file=sys.stderr)
        return 2
    path = model_files.write(args.model, file, rec)
    print(f"{headline(model)} -> {path}")
    for k in ("fitted_on", "judged_on"):
        if k in rec:
            print(f"{k}: {line(rec[k])}")
    return 0
