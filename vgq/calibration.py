"""Calibrated success probabilities: the one map from a network's raw P(success) to the
probability of success at the positivity a deployed model meets (numpy only, so the export
that fits it and the service that applies it run the same function).

The network is trained on a resampled dataset (positivity equalised to ~19 %, often with
class-balanced loss weights: an effective 50 %), so its raw 0.5 means neither 50 % nor the
native rate of success. With ``z = logit(p_raw)``::

    z_fit = slope * z + intercept          Platt scaling (temperature: slope = 1 / T), fitted
                                           on a split of positivity ``fit_positivity``
    z_cal = z_fit + logit(target_positivity) - logit(fit_positivity)     prior shift
    p_cal = sigmoid(z_cal)

The prior shift is Bayes' rule for a change of class frequencies alone (label shift: the
inputs of each class look the same before and after resampling); the dataset's resampling
(per beta bin, then uniform over (phi, beta) bins) also reshapes the inputs, so the shift is
an approximation, which the export measures (ECE on the test split re-weighted to the
target positivity). Positivities are fractions in (0, 1).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from functools import cached_property

import numpy as np

METHODS = ("platt", "temperature")
#: probabilities are clipped to [EPS, 1 - EPS] before the logit (float32 sigmoid outputs saturate)
EPS = 1e-7


def logit(p: np.ndarray) -> np.ndarray:
    """log(p / (1 - p)) of probabilities clipped to [EPS, 1 - EPS] (float64)."""
    p = np.minimum(np.maximum(np.asarray(p, dtype=np.float64), EPS), 1.0 - EPS)  # np.clip, without its overhead
    return np.log(p) - np.log1p(-p)


def sigmoid(z: np.ndarray) -> np.ndarray:
    """1 / (1 + exp(-z)) without overflow (float64)."""
    z = np.asarray(z, dtype=np.float64)
    e = np.exp(-np.abs(z))
    d = 1.0 + e
    return np.where(z >= 0, 1.0 / d, e / d)


def _fraction(name: str, x: float) -> float:
    x = float(x)
    if not 0.0 < x < 1.0:
        raise ValueError(f"{name} must be a fraction in (0, 1), got {x}")
    return x


@dataclass(frozen=True)
class Calibration:
    """Parameters of the map above; ``apply`` is the map."""

    method: str  # "platt" | "temperature"
    slope: float  # a = 1 / T, > 0
    intercept: float  # b, logit units, at fit_positivity
    fit_positivity: float  # positives / rows of the split the parameters were fitted on
    target_positivity: float  # the positivity the calibrated probabilities are for

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"calibration method must be one of {METHODS}, got {self.method!r}")
        if not (np.isfinite(self.slope) and self.slope > 0 and np.isfinite(self.intercept)):
            raise ValueError(
                f"calibration needs a finite slope > 0 and a finite intercept, got {self.slope}, {self.intercept}"
            )
        _fraction("fit_positivity", self.fit_positivity)
        _fraction("target_positivity", self.target_positivity)

    @property
    def temperature(self) -> float:
        return 1.0 / self.slope

    @cached_property
    def prior_shift(self) -> float:
        """logit(target_positivity) - logit(fit_positivity), added to the fitted logit (computed
        once: ``apply`` runs on every score request)."""
        return float(logit(self.target_positivity) - logit(self.fit_positivity))

    def apply(self, p_raw: np.ndarray) -> np.ndarray:
        """Calibrated P(success) (float64, same shape) of the network's raw probabilities."""
        return sigmoid(self.slope * logit(p_raw) + self.intercept + self.prior_shift)

    def at_positivity(self, target_positivity: float) -> Calibration:
        """The same fit, calibrated for another positivity (e.g. a test split's own)."""
        return Calibration(self.method, self.slope, self.intercept, self.fit_positivity, float(target_positivity))

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> Calibration:
        """From a ``to_dict`` (other keys, e.g. a model card's report, are ignored)."""
        try:
            return cls(
                str(d["method"]),
                float(d["slope"]),
                float(d["intercept"]),
                float(d["fit_positivity"]),
                float(d["target_positivity"]),
            )
        except (KeyError, TypeError) as e:
            raise ValueError(f"not a calibration record ({type(e).__name__}: {e}): {d}") from e


def prior_weights(labels: np.ndarray, target_positivity: float) -> np.ndarray:
    """Per-row weights that make labelled rows count as if their positivity were
    ``target_positivity`` (positives target / observed, negatives (1 - target) / (1 - observed)),
    normalised to mean 1. Needs both classes."""
    y = np.asarray(labels).astype(bool).reshape(-1)
    obs = float(y.mean()) if len(y) else 0.0
    if not 0.0 < obs < 1.0:
        raise ValueError(f"re-weighting to a positivity needs both classes (observed positivity {obs})")
    t = _fraction("target_positivity", target_positivity)
    w = np.where(y, t / obs, (1.0 - t) / (1.0 - obs))
    return w / w.mean()


def reliability_bins(p: np.ndarray, labels: np.ndarray, n_bins: int = 10, weights: np.ndarray | None = None) -> dict:
    """Equal-width bins of predicted probability over [0, 1]: per bin the (weighted) share of
    rows ``weight``, mean prediction ``confidence`` and observed success rate ``accuracy``
    (NaN where a bin is empty)."""
    p = np.asarray(p, dtype=np.float64).reshape(-1)
    y = np.asarray(labels, dtype=np.float64).reshape(-1)
    w = np.ones_like(p) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    if not (len(p) == len(y) == len(w)) or len(p) == 0:
        raise ValueError(f"need as many probabilities, labels and weights (>= 1), got {len(p)}, {len(y)}, {len(w)}")
    if n_bins < 1:
        raise ValueError(f"n_bins must be >= 1, got {n_bins}")
    b = np.minimum((np.clip(p, 0.0, 1.0) * n_bins).astype(np.int64), n_bins - 1)
    tot = np.bincount(b, weights=w, minlength=n_bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        conf = np.bincount(b, weights=w * p, minlength=n_bins) / tot
        acc = np.bincount(b, weights=w * y, minlength=n_bins) / tot
    return {
        "edges": np.linspace(0.0, 1.0, n_bins + 1),
        "weight": tot / tot.sum(),
        "confidence": conf,
        "accuracy": acc,
        "count": np.bincount(b, minlength=n_bins),
    }


def expected_calibration_error(
    p: np.ndarray, labels: np.ndarray, n_bins: int = 10, weights: np.ndarray | None = None
) -> float:
    """ECE: sum over equal-width bins of (bin share) * |mean prediction - observed rate|."""
    r = reliability_bins(p, labels, n_bins, weights)
    full = r["weight"] > 0
    return float(np.sum(r["weight"][full] * np.abs(r["confidence"][full] - r["accuracy"][full])))
