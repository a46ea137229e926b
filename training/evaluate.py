"""Evaluation of a trained run on a crop-dataset split: overall TPR / TNR / balanced accuracy
/ accuracy / AUC, the same per object family (when the dataset records families) and per camera-grid cell (d in 0.05 m, phi in 5 deg steps) as heat maps,
and the run's training curves."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from vgq import atomic
from vgq.crop import CropGeometry
from vgq.pose import FULL_POSE_COLUMNS, approach_angle

from . import metrics as M
from .checkpoint import RunPaths, load_trained, resolve_run
from .data import CropDataset, DatasetError, open_crop_dataset
from .plots import plot_grid_heatmaps, plot_training_curves
from .predict import predict_split


def check_trained_geometry(data: CropDataset, meta: dict) -> None:
    """Raise DatasetError unless ``data``'s crops have the window, size and turning of the crops the
    net of ``meta`` (``load_trained``) was trained on."""
    g = meta["geometry"]
    if (data.geometry.window, data.geometry.out) != (int(g["window"]), int(g["out"])):
        raise DatasetError(
            f"crop dataset {data.path} has window/out {data.geometry.window}/{data.geometry.out}, "
            f"the net was trained on {g['window']}/{g['out']}"
        )
    trained = CropGeometry.from_dict(g)
    if (data.geometry.align_jaw, data.geometry.jaw_turns) != (trained.align_jaw, trained.jaw_turns):
        raise DatasetError(
            f"crop dataset {data.path} has crops {data.geometry.turning()}; the net was trained on crops {trained.turning()}"
        )


def open_trained_on(run: str | Path, data_dir: str | Path, split: str):
    """``(net, meta, data, split rows, run folder or None)``: the trained net of ``run`` (a run folder's
    best checkpoint, or a checkpoint file) and ``split`` of the crop dataset ``data_dir``, checked to be
    crops of the kind it was trained on."""
    ckpt_path, run_dir = resolve_run(Path(run))
    net, meta = load_trained(ckpt_path)
    data = open_crop_dataset(data_dir)
    data.check_arch(meta["arch"])
    check_trained_geometry(data, meta)
    return net, meta, data, data.split(split), run_dir


def evaluate(
    run: str | Path,
    data_dir: str | Path,
    split: str = "test",
    out_dir: str | Path | None = None,
    threshold: float = 0.5,
    batch_size: int = 64,
    d_step: float = 0.05,
    phi_step_deg: float = 5.0,
    progress: bool = True,
    name: str | None = None,
    max_n: int = 0,
    seed: int = 0,
) -> dict:
    """Evaluate the run folder (best checkpoint) or checkpoint ``run`` on ``split`` of the
    crop dataset ``data_dir``.

    Writes ``metrics_<name>.json``, ``heatmap_<name>.png`` (``name`` defaults to the split;
    e.g. ``test_clean`` for the test split of a clean-sensor copy) and (for a run folder)
    ``curves.png`` into ``out_dir`` (default: the run's ``eval/`` folder, or ``eval/`` beside
    a bare checkpoint). ``max_n`` > 0: only that many rows, drawn at random (``seed``) from the
    split; a copy of the split with the same grasps (a clean ``crops_clean_test``) gets the same
    rows. Returns the metrics record (``overall``, ``by_family``, ``grid``, the dataset's sensor
    model, provenance).
    """
    name = name or split
    if not name.replace("_", "").replace("-", "").isalnum():
        raise ValueError(f"evaluation name must be letters, digits, '_' or '-', got {name!r}")
    net, meta, data, sp, run_dir = open_trained_on(run, data_dir, split)
    ckpt_path = Path(meta["checkpoint"])
    if max_n < 0:
        raise ValueError(f"max_n must be >= 0, got {max_n}")
    rows = M.sample_rows(len(sp), max_n, seed)
    t0 = time.time()
    net = net.to(memory_format=torch.channels_last)  # ~1.1x faster convolutions, the same fp32 results
    p, loss = predict_split(net, sp, rows, batch_size=batch_size, progress=progress, desc=f"evaluate {split}")
    dt = time.time() - t0
    labels = np.asarray(sp.labels[rows])
    object_id = np.asarray(sp.arrays["object_id"][rows])
    overall = M.nan_to_none({**M.binary_metrics(labels, p, threshold), "loss": loss})
    overall["balanced_accuracy_ci95"] = M.object_bootstrap_ci(labels, p, object_id, threshold)
    by_family, held_out = _family_metrics(data, object_id, labels, p, threshold)
    cam_d, cam_phi = np.asarray(sp.arrays["camera_d"][rows]), np.asarray(sp.arrays["camera_phi"][rows])
    # the camera grid's margins: does accuracy fall with distance (fewer pixels per object) or elevation?
    by_distance = {k: M.nan_to_none(m) for k, m in M.metrics_by_bin(labels, p, cam_d, 0.1, threshold).items()}
    by_elevation = {
        k: M.nan_to_none(m) for k, m in M.metrics_by_bin(labels, p, np.degrees(cam_phi), 10.0, threshold).items()
    }
    # the grasp's margins: its offset from the window centre (max |u|, |v|, crop px; Fast-VGQ-CNN:
    # how well the head finds the grasp in the shared window) and its approach angle psi to the view axis
    pose = np.asarray(sp.arrays["poses"][rows], dtype=np.float64)
    cols = list(FULL_POSE_COLUMNS)
    by_psi = {
        k: M.nan_to_none(m)
        for k, m in M.metrics_by_bin(
            labels, p, np.degrees(approach_angle(pose[:, cols.index("qw") : cols.index("qz") + 1])), 15.0, threshold
        ).items()
    }
    # and its approach to the downward table normal beta (0 = straight down: what gravity pulls along)
    by_beta = (
        {
            k: M.nan_to_none(m)
            for k, m in M.metrics_by_bin(labels, p, np.degrees(sp.arrays["beta"][rows]), 15.0, threshold).items()
        }
        if "beta" in sp.arrays
        else {}
    )
    offset = np.abs(pose[:, [cols.index("u"), cols.index("v")]]).max(axis=1)
    by_offset = {k: M.nan_to_none(m) for k, m in M.metrics_by_bin(labels, p, offset, 2.0, threshold).items()}
    grid = M.grid_metrics(
        labels,
        p,
        cam_d,
        cam_phi,
        d_step=d_step,
        phi_step_deg=phi_step_deg,
        threshold=threshold,
    )
    if out_dir is None:
        out_dir = RunPaths(run_dir).eval_dir if run_dir is not None else ckpt_path.parent / "eval"
    out_dir = Path(out_dir)
    rec = {
        "split": split,
        "name": name,
        "sensor": data.manifest.get("sensor", {"name": "clean"}).get("name"),
        "checkpoint": str(ckpt_path.resolve()),
        "arch": meta["arch"],
        "data": str(data.path.resolve()),
        "data_geometry": data.geometry.to_dict(),
        "trained_geometry": meta["geometry"],
        "samples_seen": meta["training"]["samples_seen"],
        "overall": overall,
        "by_family": by_family,
        # leave-family-out datasets: the rows of the families never seen in training, together
        "held_out_families": held_out,
        "by_camera_distance_m": by_distance,
        "by_camera_elevation_deg": by_elevation,
        "by_approach_psi_deg": by_psi,
        "by_approach_beta_deg": by_beta,
        "by_window_offset_px": by_offset,
        "rows": {"evaluated": int(len(rows)), "of": int(len(sp)), "seed": int(seed) if len(rows) < len(sp) else None},
        "grid": {"d_step_m": d_step, "phi_step_deg": phi_step_deg, **M.grid_to_json(grid)},
        "inference_s": dt,
    }
    atomic.write_json(out_dir / f"metrics_{name}.json", rec)
    title = f"{meta['arch']} on {split} split ({rec['sensor']} sensor): balanced accuracy {M.pct(overall['balanced_accuracy'])}"
    plot_grid_heatmaps(grid, out_dir / f"heatmap_{name}.png", title=title)
    if run_dir is not None and RunPaths(run_dir).metrics.is_file():
        plot_training_curves(RunPaths(run_dir).metrics, out_dir / "curves.png", title=f"{meta['arch']} training")
    return rec


def _family_metrics(data, object_id: np.ndarray, labels: np.ndarray, p: np.ndarray, threshold: float):
    """(metrics per object family, with how many test objects each rests on and how many of them
    have a positive grasp; the rows of the dataset's held-out families together, or None).
    ({}, None) for a dataset that records no families."""
    families = data.object_families()
    if not families:
        return {}, None
    row_family = np.array([families.get(int(i), "") for i in object_id])
    by_family = {f: M.nan_to_none(m) for f, m in M.metrics_by_group(labels, p, row_family, threshold).items()}
    for f, m in by_family.items():
        rows = row_family == f
        m["objects"] = int(np.unique(object_id[rows]).size)
        m["objects_with_positive"] = int(np.unique(object_id[rows & (labels == 1)]).size)
        m["balanced_accuracy_ci95"] = M.object_bootstrap_ci(labels[rows], p[rows], object_id[rows], threshold)
    holdout = sorted(((data.manifest.get("source") or {}).get("sampling") or {}).get("holdout_families") or [])
    if not holdout:
        return by_family, None
    rows = np.isin(row_family, holdout)
    return by_family, M.nan_to_none({"families": holdout, **M.binary_metrics(labels[rows], p[rows], threshold)})
