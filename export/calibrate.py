"""Fitting the calibration of ``vgq.calibration`` at export, measuring it, drawing it.

* :func:`fit_platt` / :func:`fit_temperature`: maximum likelihood on the logits of the
  network's raw probabilities over a labelled split (the validation split), by Newton's
  method; a weak Gaussian prior (one pseudo-observation) keeps the fit finite when the split
  is separable.
* :func:`fit_logistic`: the same Newton fit of a logistic regression on any columns (the
  planner's ``p_hold`` on its plan features uses it, ``planning.calibration``).
* :func:`native_positivity`: the positivity the deployed model meets, from the crop
  manifest's ``native_counts`` (or the sampled grasp dataset's statistics it was cut from).
* :func:`calibration_report`: fit on validation, ECE on test (re-weighted to the target
  positivity), for the model card; :func:`plot_reliability` draws the diagram.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vgq import atomic
from vgq.calibration import Calibration, expected_calibration_error, logit, prior_weights, reliability_bins, sigmoid
from vgq.schema import GRASP_FORMAT, read_manifest

N_BINS = 10
DIAGRAM = "reliability_diagram.png"


class CalibrationError(ValueError):
    """The labelled data cannot support a calibration fit (empty, one class, bad values)."""


def _labelled(p: np.ndarray, labels: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(p, dtype=np.float64).reshape(-1)
    y = np.asarray(labels).reshape(-1)
    if len(p) != len(y) or len(p) == 0:
        raise CalibrationError(f"{what}: need as many probabilities as labels (>= 1), got {len(p)} and {len(y)}")
    if not np.all((p >= 0) & (p <= 1)):
        raise CalibrationError(f"{what}: probabilities must lie in [0, 1]")
    if not np.all((y == 0) | (y == 1)):
        raise CalibrationError(f"{what}: labels must be 0 or 1")
    y = y.astype(np.float64)
    if y.min() == y.max():
        raise CalibrationError(f"{what}: all {len(y)} labels are {int(y[0])}; calibration needs both classes")
    return p, y


def fit_logistic(
    x: np.ndarray, y: np.ndarray, offset: np.ndarray, prior_mean: np.ndarray, iters: int = 100
) -> np.ndarray:
    """argmax_w of sum log-likelihood of y ~ Bernoulli(sigmoid(x @ w + offset)) - |w - prior_mean|^2 / 2."""
    w = prior_mean.astype(np.float64).copy()

    def objective(w):
        z = x @ w + offset
        return float(np.sum(y * z - np.logaddexp(0.0, z)) - 0.5 * np.sum((w - prior_mean) ** 2))

    f = objective(w)
    for _ in range(iters):
        s = sigmoid(x @ w + offset)
        grad = x.T @ (y - s) - (w - prior_mean)
        hess = (x * (s * (1 - s))[:, None]).T @ x + np.eye(len(w))
        step = np.linalg.solve(hess, grad)
        t = 1.0
        while True:  # backtracking: the objective is concave, a short enough step always climbs
            f_new = objective(w + t * step)
            if f_new >= f - 1e-12 or t < 1e-8:
                break
            t *= 0.5
        w, f_prev, f = w + t * step, f, f_new
        if abs(f - f_prev) < 1e-10 * max(1.0, abs(f)):
            break
    return w


def fit_platt(p_raw: np.ndarray, labels: np.ndarray, target_positivity: float | None = None) -> Calibration:
    """Platt scaling ``sigmoid(a logit(p) + b)`` fitted on (p_raw, labels); calibrated for
    ``target_positivity`` (default: the labels' own positivity)."""
    p, y = _labelled(p_raw, labels, "Platt fit")
    x = np.stack([logit(p), np.ones_like(p)], axis=1)
    a, b = fit_logistic(x, y, np.zeros_like(p), np.array([1.0, 0.0]))
    if not a > 0:
        raise CalibrationError(
            f"Platt fit: slope {a:.3g} <= 0 (the network's scores do not rank successes above failures)"
        )
    pos = float(y.mean())
    return Calibration("platt", float(a), float(b), pos, pos if target_positivity is None else float(target_positivity))


def fit_temperature(
    p_raw: np.ndarray, labels: np.ndarray, model_positivity: float, target_positivity: float | None = None
) -> Calibration:
    """Temperature scaling ``sigmoid(logit(p) / T + b0)`` fitted on (p_raw, labels), with
    ``b0 = logit(labels' positivity) - logit(model_positivity)`` fixed by the prior the
    network was trained at (0.5 with class-balanced loss weights, else the training split's)."""
    p, y = _labelled(p_raw, labels, "temperature fit")
    pos = float(y.mean())
    b0 = float(logit(pos) - logit(model_positivity))
    z = logit(p)
    (a,) = fit_logistic(z[:, None], y, np.full_like(z, b0), np.array([1.0]))
    if not a > 0:
        raise CalibrationError(
            f"temperature fit: 1/T = {a:.3g} <= 0 (the network's scores do not rank successes above failures)"
        )
    return Calibration("temperature", float(a), b0, pos, pos if target_positivity is None else float(target_positivity))


def native_positivity(manifest: dict, override: float | None = None) -> tuple[float, str]:
    """(positivity, where it comes from) for a crop manifest: ``override`` if given, else its
    ``native_counts``, else the native step of the sampled grasp dataset it was cut from, else
    the crops' own positivity over all splits (a dataset that was not resampled)."""
    if override is not None:
        return float(override), "given (--native-positivity)"
    nc = manifest.get("native_counts")
    if isinstance(nc, dict) and nc.get("n"):
        return nc["positive"] / nc[
            "n"
        ], f"crop manifest native_counts ({nc['positive']} of {nc['n']} grasps before sampling)"
    src = (manifest.get("source") or {}).get("dataset")
    if src and Path(src, "manifest.json").is_file():
        try:
            native = read_manifest(src, GRASP_FORMAT)["sampling"]["stats"]["steps"]["native"]
            return native["positive"] / native["grasps"], (
                f"grasp dataset {src}: {native['positive']} of {native['grasps']} grasps before sampling"
            )
        except (ValueError, KeyError, TypeError, ZeroDivisionError, json.JSONDecodeError):
            pass
    counts = [c for c in (manifest.get("counts") or {}).values() if isinstance(c, dict)]
    n = sum(int(c.get("n", c.get("grasps", 0))) for c in counts)
    pos = sum(int(c.get("positive", 0)) for c in counts)
    if n == 0:
        raise CalibrationError("the crop manifest records no counts; pass the native positivity explicitly")
    return pos / n, f"crop dataset counts ({pos} of {n}; no resampling recorded)"


@dataclass
class CalibrationReport:
    """A fitted calibration and its measurement, as recorded in the model card."""

    calibration: Calibration
    target_source: str
    fit: dict  # split, n, positive, nll_raw / nll_calibrated (at the fit split's positivity)
    test: dict  # split, n, positive, ECEs
    diagram: dict  # reliability bins (raw and calibrated) on the test split, re-weighted

    def to_dict(self) -> dict:
        return {
            **self.calibration.to_dict(),
            "temperature": self.calibration.temperature,
            "target_positivity_source": self.target_source,
            "fit": self.fit,
            "test": self.test,
            "reliability_diagram": DIAGRAM,
        }


def _nll(p: np.ndarray, y: np.ndarray) -> float:
    z = logit(p)
    return float(np.mean(np.logaddexp(0.0, z) - y * z))


def calibration_report(
    p_val: np.ndarray,
    y_val: np.ndarray,
    p_test: np.ndarray,
    y_test: np.ndarray,
    target_positivity: float,
    target_source: str,
    method: str = "platt",
    model_positivity: float = 0.5,
    splits: tuple[str, str] = ("val", "test"),
    n_bins: int = N_BINS,
) -> CalibrationReport:
    """Fit on (p_val, y_val) and measure on (p_test, y_test): the expected calibration error
    of the raw and the calibrated probabilities with the test rows re-weighted to
    ``target_positivity`` (what a deployed model meets), and, as a check of the fit alone,
    the calibration shifted to the test split's own positivity on the unweighted rows."""
    if method == "platt":
        cal = fit_platt(p_val, y_val, target_positivity)
    elif method == "temperature":
        cal = fit_temperature(p_val, y_val, model_positivity, target_positivity)
    else:
        raise CalibrationError(f"calibration method must be platt or temperature, got {method!r}")
    pv, yv = _labelled(p_val, y_val, f"{splits[0]} split")
    pt, yt = _labelled(p_test, y_test, f"{splits[1]} split")
    at_fit = cal.at_positivity(cal.fit_positivity)
    w = prior_weights(yt, target_positivity)
    p_cal = cal.apply(pt)
    test_pos = float(yt.mean())
    test = {
        "split": splits[1],
        "n": int(len(yt)),
        "positive": int(yt.sum()),
        "bins": n_bins,
        "weighting": f"rows re-weighted from the split's positivity {test_pos:.4f} to the target {target_positivity:.4f}",
        "ece_raw": expected_calibration_error(pt, yt, n_bins, w),
        "ece_calibrated": expected_calibration_error(p_cal, yt, n_bins, w),
        "ece_raw_at_split_positivity": expected_calibration_error(pt, yt, n_bins),
        "ece_calibrated_at_split_positivity": expected_calibration_error(
            cal.at_positivity(test_pos).apply(pt), yt, n_bins
        ),
    }
    fit = {
        "split": splits[0],
        "n": int(len(yv)),
        "positive": int(yv.sum()),
        "nll_raw": _nll(pv, yv),
        "nll_calibrated": _nll(at_fit.apply(pv), yv),
    }
    diagram = {
        "raw": reliability_bins(pt, yt, n_bins, w),
        "calibrated": reliability_bins(p_cal, yt, n_bins, w),
        "target_positivity": target_positivity,
        "split": splits[1],
    }
    return CalibrationReport(cal, target_source, fit, test, diagram)


def plot_reliability(report: CalibrationReport, path: str | Path) -> Path:
    """Reliability diagram (observed success rate against mean predicted probability, per
    bin) of the raw and the calibrated probabilities on the test split, with the share of
    predictions per bin below; written atomically as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d, t = report.diagram, report.test
    fig, (ax, hx) = plt.subplots(
        2, 1, figsize=(5.5, 6.5), sharex=True, gridspec_kw={"height_ratios": [3, 1]}, constrained_layout=True
    )
    ax.plot([0, 1], [0, 1], color="0.6", lw=1, ls="--", label="perfectly calibrated")
    centres = 0.5 * (d["raw"]["edges"][:-1] + d["raw"]["edges"][1:])
    for key, colour, ece in (("raw", "tab:red", t["ece_raw"]), ("calibrated", "tab:blue", t["ece_calibrated"])):
        r = d[key]
        full = r["weight"] > 0
        ax.plot(r["confidence"][full], r["accuracy"][full], "o-", color=colour, label=f"{key} (ECE {ece:.3f})")
        hx.bar(centres + (0.02 if key == "calibrated" else -0.02), r["weight"], width=0.04, color=colour, alpha=0.8)
    ax.set(
        xlim=(0, 1),
        ylim=(0, 1),
        ylabel="observed success rate",
        title=f"{d['split']} split ({t['n']} grasps), weighted to positivity {100 * d['target_positivity']:.1f}%",
    )
    ax.legend(loc="upper left", fontsize=8)
    hx.set(xlabel="predicted P(success)", ylabel="share", yscale="log")
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120)
    plt.close(fig)
    atomic.write_bytes(path, buf.getvalue())
    return Path(path)


def calibrate_on_dataset(
    net, ds, meta: dict, method: str = "platt", native: float | None = None, max_n: int = 10_000, seed: int = 0
) -> CalibrationReport:
    """Fit on the validation split and measure on the test split of the crop dataset ``ds``
    (``training.data.CropDataset``; at most ``max_n`` random rows of each) the calibration of
    ``net`` (torch, whose outputs the exported graphs reproduce) for the dataset's native
    positivity; ``meta`` is ``training.checkpoint.load_trained``'s (the class balance the
    net was trained with sets the temperature fit's prior)."""
    from training.data import DatasetError
    from training.metrics import sample_rows
    from training.predict import predict_split

    probs = {}
    for name in ("val", "test"):
        try:
            split = ds.split(name)
        except DatasetError as e:
            raise CalibrationError(f"calibration needs a val and a test split: {e}") from None
        idx = sample_rows(len(split), max_n, seed)
        p, _ = predict_split(net, split, idx)
        probs[name] = (p, np.asarray(split.labels[idx]))
    target, source = native_positivity(ds.manifest, native)
    train_counts = (meta.get("dataset", {}).get("counts") or {}).get("train") or {}
    balanced = meta.get("training", {}).get("config", {}).get("class_balance") == "loss_weights"
    model_pos = 0.5 if balanced or not train_counts.get("n") else train_counts["positive"] / train_counts["n"]
    return calibration_report(*probs["val"], *probs["test"], target, source, method, model_pos)
