"""Classification metrics (pure numpy): TPR, TNR, balanced accuracy, accuracy, ROC AUC, overall,
per family and per cell of the camera grid (distance d in metres, elevation phi in radians)."""

from __future__ import annotations

import math

import numpy as np


def confusion(labels: np.ndarray, predicted: np.ndarray) -> dict[str, int]:
    """Counts tp, fn, tn, fp of boolean/0-1 ``predicted`` against 0-1 ``labels``."""
    y = np.asarray(labels).astype(bool).ravel()
    p = np.asarray(predicted).astype(bool).ravel()
    if y.shape != p.shape:
        raise ValueError(f"labels ({y.shape}) and predictions ({p.shape}) differ in length")
    return {
        "tp": int(np.sum(y & p)),
        "fn": int(np.sum(y & ~p)),
        "tn": int(np.sum(~y & ~p)),
        "fp": int(np.sum(~y & p)),
    }


def from_confusion(c: dict[str, int]) -> dict[str, float]:
    """TPR, TNR, balanced accuracy, accuracy (NaN where undefined) plus the counts."""
    pos, neg = c["tp"] + c["fn"], c["tn"] + c["fp"]
    n = pos + neg
    tpr = c["tp"] / pos if pos else math.nan
    tnr = c["tn"] / neg if neg else math.nan
    bacc = (tpr + tnr) / 2 if pos and neg else math.nan
    acc = (c["tp"] + c["tn"]) / n if n else math.nan
    return {
        "tpr": tpr,
        "tnr": tnr,
        "balanced_accuracy": bacc,
        "accuracy": acc,
        "n": n,
        "n_positive": pos,
        "n_negative": neg,
        **{k: int(v) for k, v in c.items()},
    }


def sample_rows(n: int, max_n: int, seed: int = 0) -> np.ndarray:
    """Sorted indices of the rows to evaluate out of ``n``: all of them, or ``max_n`` (> 0) drawn at
    random with ``seed`` (the same rows for every model and for a copy of the split with the same grasps)."""
    if max_n and n > max_n:
        return np.sort(np.random.default_rng(seed).choice(n, max_n, replace=False))
    return np.arange(n)


def binary_metrics(labels: np.ndarray, p_success: np.ndarray, threshold: float = 0.5) -> dict[str, float]:
    """Metrics of predicting success where ``p_success > threshold``, and the ROC AUC of ``p_success``."""
    out = from_confusion(confusion(labels, np.asarray(p_success) > threshold))
    out["threshold"] = threshold
    out["auc"] = auc(p_success, labels)
    return out


def metrics_by_group(
    labels: np.ndarray, p_success: np.ndarray, groups: np.ndarray, threshold: float = 0.5
) -> dict[str, dict[str, float]]:
    """:func:`binary_metrics` of the rows of each value of ``groups`` (e.g. each object family),
    keyed by that value, in sorted order."""
    y, p, g = np.asarray(labels), np.asarray(p_success), np.asarray(groups)
    return {str(k): binary_metrics(y[g == k], p[g == k], threshold) for k in np.unique(g)}


def object_bootstrap_ci(
    labels: np.ndarray,
    p_success: np.ndarray,
    objects: np.ndarray,
    threshold: float = 0.5,
    n_boot: int = 2000,
    level: float = 0.95,
    seed: int = 0,
) -> list[float | None]:
    """Percentile interval ``[lo, hi]`` of balanced accuracy when the objects are resampled with
    replacement (the rows of one object move together: a split draws objects, not grasps, so a
    family's 4 test objects are 4 draws however many rows they have). ``[None, None]`` with fewer
    than 2 objects or when most resamples lack a class."""
    y = np.asarray(labels).astype(bool).ravel()
    pred = np.asarray(p_success).ravel() > threshold
    ids, inv = np.unique(np.asarray(objects).ravel(), return_inverse=True)
    if len(ids) < 2:
        return [None, None]
    k = len(ids)
    counts = np.stack(  # (objects, 4): tp, fn, tn, fp
        [np.bincount(inv, weights=w, minlength=k) for w in (y & pred, y & ~pred, ~y & ~pred, ~y & pred)], axis=1
    )
    draws = np.random.default_rng(seed).multinomial(k, np.full(k, 1.0 / k), size=n_boot)  # (n_boot, objects)
    tp, fn, tn, fp = (draws @ counts).T
    with np.errstate(invalid="ignore", divide="ignore"):
        bacc = (tp / (tp + fn) + tn / (tn + fp)) / 2
    bacc = bacc[np.isfinite(bacc)]
    if len(bacc) < n_boot / 2:
        return [None, None]
    lo, hi = np.percentile(bacc, [50 * (1 - level), 50 * (1 + level)])
    return [float(lo), float(hi)]


def metrics_by_bin(
    labels: np.ndarray, p_success: np.ndarray, values: np.ndarray, step: float, threshold: float = 0.5
) -> dict[str, dict[str, float]]:
    """:func:`binary_metrics` of the rows in each ``step``-wide bin of ``values`` (e.g. camera
    distance in metres), keyed "lo-hi" in ascending order; empty bins are left out."""
    v = np.asarray(values, dtype=np.float64).ravel()
    edges = bin_edges(v, step)
    idx = bin_index(v, edges)
    y, p = np.asarray(labels).ravel(), np.asarray(p_success).ravel()
    return {
        f"{edges[i]:g}-{edges[i + 1]:g}": binary_metrics(y[idx == i], p[idx == i], threshold) for i in np.unique(idx)
    }


def auc(score: np.ndarray, y: np.ndarray, weight: np.ndarray | None = None) -> float:
    """Area under the ROC curve of ``score`` for binary ``y`` (ties count half); ``weight``
    per sample. NaN when only one class is present."""
    s = np.asarray(score, np.float64)
    y = np.asarray(y, bool)
    w = np.ones_like(s) if weight is None else np.asarray(weight, np.float64)
    wp, wn = w * y, w * ~y
    if wp.sum() == 0 or wn.sum() == 0:
        return float("nan")
    order = np.argsort(s, kind="mergesort")
    s, wp, wn = s[order], wp[order], wn[order]
    _, start = np.unique(s, return_index=True)
    pos = np.add.reduceat(wp, start)
    neg = np.add.reduceat(wn, start)
    neg_below = np.cumsum(neg) - neg
    return float(np.sum(pos * (neg_below + 0.5 * neg)) / (wp.sum() * wn.sum()))


def bin_index(values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Bin of each value among ``edges`` (as :func:`bin_edges` makes them; a value on an edge
    falls in the bin above it, the last edge in the last bin)."""
    return np.clip(np.searchsorted(edges, values + 1e-9, side="right") - 1, 0, len(edges) - 2)


def bin_edges(values: np.ndarray, step: float) -> np.ndarray:
    """Edges at multiples of ``step`` covering ``values`` (at least one bin)."""
    v = np.asarray(values, dtype=np.float64)
    if v.size == 0:
        return np.array([0.0, step])
    lo = math.floor(float(v.min()) / step + 1e-9)
    hi = max(math.floor(float(v.max()) / step + 1e-9) + 1, lo + 1)
    return np.arange(lo, hi + 1) * step


def grid_metrics(
    labels: np.ndarray,
    p_success: np.ndarray,
    camera_d: np.ndarray,
    camera_phi: np.ndarray,
    d_step: float = 0.05,
    phi_step_deg: float = 5.0,
    threshold: float = 0.5,
) -> dict:
    """TPR / TNR / balanced accuracy / counts per (d, phi) cell.

    Rows index d bins (metres, ``d_edges``), columns phi bins (degrees, ``phi_edges_deg``).
    Cells without positives (negatives) have TPR (TNR) NaN; JSON-ready lists via
    :func:`grid_to_json`.
    """
    y = np.asarray(labels).astype(bool).ravel()
    pred = np.asarray(p_success).ravel() > threshold
    d = np.asarray(camera_d, dtype=np.float64).ravel()
    phi = np.degrees(np.asarray(camera_phi, dtype=np.float64).ravel())
    d_edges, phi_edges = bin_edges(d, d_step), bin_edges(phi, phi_step_deg)
    di, pj = bin_index(d, d_edges), bin_index(phi, phi_edges)
    shape = (len(d_edges) - 1, len(phi_edges) - 1)
    cell = di * shape[1] + pj
    size = shape[0] * shape[1]
    tp = np.bincount(cell[y & pred], minlength=size).reshape(shape)
    pos = np.bincount(cell[y], minlength=size).reshape(shape)
    tn = np.bincount(cell[~y & ~pred], minlength=size).reshape(shape)
    neg = np.bincount(cell[~y], minlength=size).reshape(shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        tpr = np.where(pos > 0, tp / np.maximum(pos, 1), np.nan)
        tnr = np.where(neg > 0, tn / np.maximum(neg, 1), np.nan)
    return {
        "d_edges": d_edges,
        "phi_edges_deg": phi_edges,
        "tpr": tpr,
        "tnr": tnr,
        "balanced_accuracy": (tpr + tnr) / 2,
        "n_positive": pos,
        "n_negative": neg,
    }


def grid_to_json(grid: dict) -> dict:
    """Arrays to lists, NaN to None."""

    def conv(a):
        a = np.asarray(a, dtype=np.float64)
        return (
            [[None if not np.isfinite(x) else float(x) for x in row] for row in a]
            if a.ndim == 2
            else [float(x) for x in a]
        )

    return {k: conv(v) for k, v in grid.items()}


def pct(x: float | None) -> str:
    """A fraction as a percentage with one decimal ("81.2%"), "n/a" for None."""
    return "n/a" if x is None else f"{100 * x:.1f}%"


def nan_to_none(d: dict) -> dict:
    """Replace NaN floats by None (strict JSON)."""
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}
