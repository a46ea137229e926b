"""Figures (matplotlib, Agg backend): camera-grid heat maps, training curves, kappa ablation."""

from __future__ import annotations

import io
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from vgq import atomic  # noqa: E402


def _save(fig, path: str | Path) -> Path:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120, bbox_inches="tight")
    plt.close(fig)
    atomic.write_bytes(path, buf.getvalue())
    return Path(path)


def plot_grid_heatmaps(grid: dict, path: str | Path, title: str = "") -> Path:
    """TPR (left) and TNR (right) over the camera grid: rows d (m), columns phi (deg),
    cell values annotated in percent; cells without samples of the class are grey."""
    d_edges = np.asarray(grid["d_edges"], dtype=float)
    p_edges = np.asarray(grid["phi_edges_deg"], dtype=float)
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.2), constrained_layout=True)
    cmap = matplotlib.colormaps["viridis"].with_extremes(bad="0.85")
    for ax, key, name in zip(axes, ("tpr", "tnr"), ("TPR", "TNR")):
        a = np.asarray(grid[key], dtype=float)
        im = ax.imshow(
            np.ma.masked_invalid(a),
            origin="lower",
            cmap=cmap,
            vmin=0.0,
            vmax=1.0,
            aspect="auto",
            extent=(p_edges[0], p_edges[-1], d_edges[0], d_edges[-1]),
        )
        if a.size <= 400:
            for i in range(a.shape[0]):
                for j in range(a.shape[1]):
                    if np.isfinite(a[i, j]):
                        x = (p_edges[j] + p_edges[j + 1]) / 2
                        y = (d_edges[i] + d_edges[i + 1]) / 2
                        ax.text(
                            x,
                            y,
                            f"{100 * a[i, j]:.0f}",
                            ha="center",
                            va="center",
                            fontsize=7,
                            color="white" if a[i, j] < 0.6 else "black",
                        )
        ax.set_xlabel("camera elevation phi (deg)")
        ax.set_ylabel("camera distance d (m)")
        ax.set_title(name)
        fig.colorbar(im, ax=ax, fraction=0.046)
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def read_metrics_log(path: str | Path) -> list[dict]:
    """Records of a metrics.jsonl (lines that do not parse are skipped)."""
    out = []
    for line in Path(path).read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return out


def plot_training_curves(metrics_log: str | Path, path: str | Path, title: str = "") -> Path:
    """Training loss and validation loss (left), validation TPR / TNR / balanced accuracy
    (right), against samples seen."""
    recs = read_metrics_log(metrics_log)
    tr = [r for r in recs if r.get("kind") == "train"]
    va = [r for r in recs if r.get("kind") == "val"]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.5), constrained_layout=True)

    def series(rs, key):
        pts = [(r["samples"], r[key]) for r in rs if r.get(key) is not None]
        return ([p[0] for p in pts], [p[1] for p in pts]) if pts else ([], [])

    a1.plot(*series(tr, "loss"), label="train loss")
    a1.plot(*series(va, "loss"), "o-", label="val loss")
    a1.set_xlabel("samples")
    a1.set_ylabel("cross-entropy")
    a1.legend()
    for key, lab in (("balanced_accuracy", "val balanced accuracy"), ("tpr", "val TPR"), ("tnr", "val TNR")):
        a2.plot(*series(va, key), "o-", label=lab)
    a2.set_xlabel("samples")
    a2.set_ylim(0, 1)
    a2.legend()
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def plot_ablation(results: list[dict], path: str | Path, title: str = "") -> Path:
    """Test balanced accuracy (and TPR / TNR) against kappa in crop pixels (32 x 32 input)
    with the source-pixel value on a secondary axis label."""
    rs = sorted(results, key=lambda r: r["kappa_px"])
    k = [r["kappa_px"] / r.get("scale", 3) for r in rs]
    fig, ax = plt.subplots(figsize=(6, 4.2), constrained_layout=True)
    for key, lab, st in (
        ("balanced_accuracy", "balanced accuracy", "o-"),
        ("tpr", "TPR", "s--"),
        ("tnr", "TNR", "^--"),
    ):
        ax.plot(k, [r.get(key) if r.get(key) is not None else np.nan for r in rs], st, label=lab)
    ax.set_xlabel("kappa = max(|u|, |v|) (px in the 32 x 32 crop)")
    ax.set_ylabel("test metric")
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend()
    ax.set_title(title or "Fast-VGQ-CNN: kappa ablation")
    return _save(fig, path)
