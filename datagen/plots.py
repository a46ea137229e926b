"""Sampling-stage plots (matplotlib, Agg backend, PNG files)."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def _save(fig, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def positivity_by_beta(path: str | Path, edges_deg, tables: dict[str, dict], target: float) -> Path:
    """Line plot of positivity (percent) per beta bin for each named step, with the target."""
    fig, ax = plt.subplots(figsize=(7, 4))
    centres = 0.5 * (np.asarray(edges_deg[:-1]) + np.asarray(edges_deg[1:]))
    for name, tab in tables.items():
        y = np.array([np.nan if r is None else r for r in tab["positivity"]], dtype=float)
        ax.plot(centres[: len(y)], y, marker="o", label=name)
    ax.axhline(target, color="k", ls="--", lw=1, label=f"target {target:g}%")
    ax.set_xlabel("beta (deg)")
    ax.set_ylabel("positivity rate (%)")
    ax.legend()
    ax.grid(alpha=0.3)
    return _save(fig, Path(path))


def counts_histograms(
    path: str | Path, phi_deg: dict[str, np.ndarray], beta_deg: dict[str, np.ndarray], bin_deg=(5.0, 5.0)
) -> Path:
    """Grasp counts over phi and over beta (5 deg bins) for each named subset."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, data, label, w in (
        (axes[0], phi_deg, "camera phi (deg)", bin_deg[0]),
        (axes[1], beta_deg, "beta (deg)", bin_deg[1]),
    ):
        hi = max([float(np.max(v)) for v in data.values() if len(v)] + [w])
        bins = np.arange(0, hi + w, w)
        for name, v in data.items():
            ax.hist(v, bins=bins, histtype="step", lw=1.5, label=name)
        ax.set_xlabel(label)
        ax.set_ylabel("grasps")
        ax.set_yscale("log")
        ax.legend()
    return _save(fig, Path(path))


def sampling_plots(out_dir: str | Path, stats: dict, table, steps: dict[str, np.ndarray], params) -> list[Path]:
    """The sampling stage's plots: positivity over beta per step and count histograms."""
    out_dir = Path(out_dir)
    tabs = {k: stats["steps"][k]["by_beta"] for k in ("psi", "positivity", "uniform")}
    files = [
        positivity_by_beta(out_dir / "positivity_by_beta.png", stats["beta_bins_deg"], tabs, params.target_positivity)
    ]
    phi = {k: np.degrees(table.phi[m]) for k, m in steps.items() if k in ("psi", "uniform")}
    beta = {k: np.degrees(table.beta[m]) for k, m in steps.items() if k in ("psi", "uniform")}
    files.append(
        counts_histograms(
            out_dir / "counts_phi_beta.png", phi, beta, (math.degrees(params.phi_bin), math.degrees(params.beta_bin))
        )
    )
    return files
