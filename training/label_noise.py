"""How well any model could do against the physics label: the ceiling its trial noise sets.

A physics label is ``k >= m`` successes in ``T`` noisy trials (``datagen.labels``: T = 8,
success rate > 0.5), a draw from Binomial(T, p) for the grasp's true success probability p.
Even a model that knew p exactly would mislabel grasps near the threshold, so balanced
accuracy and AUC have a ceiling below 100%. The distribution of p is fitted to the observed
counts k by its nonparametric maximum-likelihood estimate (EM over a grid of p), and the
ceiling is that of the best rule on p (a threshold), in expectation over the trials. The counts
pin down only the first ``T`` moments of p, so the balanced-accuracy ceiling is well determined
and the AUC ceiling less so (a p spread a little more or less within a cluster moves it by ~0.01).

The sampling stage keeps positives and negatives at different rates (VG-dset's positivity
equalisation), so the counts are first re-weighted to the dataset's native positivity (the
crop manifest's ``native_counts``); balanced accuracy and AUC do not depend on the class
prior, so the ceiling holds for the resampled splits too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import binom

from .data import DatasetError, open_crop_dataset


@dataclass(frozen=True)
class Ceiling:
    balanced_accuracy: float  # best balanced accuracy of a rule that knows p (fraction)
    auc: float  # ROC AUC of p itself as the score
    trials: int
    counts: list[int]  # rows per number of successes 0..trials, as observed
    native_positivity: float | None  # positivity the counts were re-weighted to (None: as observed)


def fit_success_distribution(counts: np.ndarray, trials: int, grid: np.ndarray, iters: int = 50_000) -> np.ndarray:
    """NPMLE weights (len(grid),) of p over ``grid`` for counts (trials + 1,) of k successes."""
    seen = np.flatnonzero(counts > 0)  # counts never observed add nothing (and their posteriors may vanish)
    lik = binom.pmf(seen[:, None], trials, grid[None, :])  # (K, G)
    c = np.asarray(counts, dtype=np.float64)[seen, None]
    w = np.full(len(grid), 1.0 / len(grid))
    total = c.sum()
    for _ in range(iters):
        post = lik * w[None, :]
        post /= post.sum(axis=1, keepdims=True)
        w = (c * post).sum(axis=0) / total
    return w


def label_ceiling(
    counts: np.ndarray, trials: int, min_successes: int, native_positivity: float | None = None
) -> Ceiling:
    """The ceiling for counts (trials + 1,) of rows with k successes, positive when k >= ``min_successes``."""
    counts = np.asarray(counts, dtype=np.float64).copy()
    observed = counts.copy()
    if native_positivity is not None:
        pos = counts[min_successes:].sum() / counts.sum()
        if not (0 < pos < 1 and 0 < native_positivity < 1):
            raise ValueError(f"cannot re-weight positivity {pos:.4f} to {native_positivity}")
        counts[min_successes:] *= (native_positivity / (1 - native_positivity)) / (pos / (1 - pos))
    grid = np.linspace(0.0, 1.0, 101)
    w = fit_success_distribution(counts, trials, grid)
    p_pos = binom.sf(min_successes - 1, trials, grid)  # P(label positive | p)
    wp, wn = w * p_pos, w * (1.0 - p_pos)
    P, N = wp.sum(), wn.sum()
    # threshold rules on p: predict positive for p >= grid[i]; p_pos rises with p, so these are the best rules
    tpr = np.cumsum(wp[::-1])[::-1] / P
    tnr = np.concatenate([[0.0], np.cumsum(wn)[:-1]]) / N
    bacc = float(np.max(0.5 * (tpr + tnr)))
    below = np.concatenate([[0.0], np.cumsum(wn)[:-1]])  # negative mass at lower p
    auc = float(np.sum(wp * (below + 0.5 * wn)) / (P * N))
    return Ceiling(bacc, auc, trials, [int(x) for x in observed], native_positivity)


def dataset_ceiling(path, split: str = "test") -> Ceiling:
    """The ceiling of a crop dataset's split labelled by physics trials (its manifest says how many)."""
    data = open_crop_dataset(path)
    label = data.label_info()
    if label.get("kind") != "physics":
        raise DatasetError(f"{path}: label {label.get('kind')!r}; the trial-noise ceiling needs the physics label")
    trials = int(label["trials"])
    k = np.rint(np.asarray(data.split(split).arrays["quality"], dtype=np.float64) * trials).astype(np.int64)
    if k.min() < 0 or k.max() > trials:
        raise DatasetError(f"{path}: quality outside [0, 1]; not a success rate of {trials} trials")
    min_successes = int(np.floor(float(label["threshold"]) * trials)) + 1  # success rate > threshold
    native = (data.manifest.get("native_counts") or {}).get("positivity")
    return label_ceiling(np.bincount(k, minlength=trials + 1), trials, min_successes, native)
