"""Kappa ablation (paper Fig. 6b): train Fast-VGQ-CNN on crop datasets that differ only in
kappa (the largest grasp offset from the crop centre), evaluate each on its test split and
plot balanced accuracy against kappa.

Each dataset gets a run folder ``OUT/kappa_<k>px``; runs resume, and a finished and
evaluated run is not trained again, so a killed ablation is restarted with the same command.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import torch.distributed as dist
from tqdm import tqdm

from vgq import atomic

from .checkpoint import RunPaths
from .config import TrainConfig
from .data import DatasetError, open_crop_dataset
from .evaluate import evaluate
from .plots import plot_ablation
from .train import train


def _finished(run_dir: Path, cfg: TrainConfig) -> dict | None:
    paths = RunPaths(run_dir)
    try:
        info = json.loads(paths.run_json.read_text())
        rec = json.loads(paths.eval_metrics("test").read_text())
    except (OSError, json.JSONDecodeError):
        return None
    t = info.get("training", {})
    if (
        t.get("finished")
        and t.get("samples_seen", 0) >= cfg.samples
        and rec.get("samples_seen", -1) == t.get("samples_seen")
    ):
        return rec
    return None


def run_ablation(data_dirs: list[str | Path], out_dir: str | Path, config: TrainConfig, progress: bool = True) -> dict:
    """Train ``config`` on each dataset of ``data_dirs`` (distinct kappa values) and evaluate.

    Writes ``ablation.json`` and ``ablation.png`` into ``out_dir``; returns the JSON record.
    """
    out_dir = Path(out_dir)
    sets = [open_crop_dataset(p) for p in data_dirs]
    if not sets:
        raise DatasetError("the ablation needs at least one crop dataset")
    kappas = [s.geometry.kappa_px for s in sets]
    if len(set(kappas)) != len(kappas):
        raise DatasetError(f"the ablation's datasets must have distinct kappa values, got {kappas}")
    for s in sets:
        s.check_arch(config.arch)
    main = int(os.environ.get("RANK", "0")) == 0
    results = []
    order = sorted(range(len(sets)), key=lambda i: kappas[i])
    for i in tqdm(order, desc="ablation", unit="run", disable=not (progress and main)):
        s = sets[i]
        run_dir = out_dir / f"kappa_{s.geometry.kappa_px:g}px"
        rec = _finished(run_dir, config)  # every rank decides alike (shared files)
        if rec is None:
            train(config, s.path, run_dir, resume=True, progress=progress)
            if main:
                rec = evaluate(run_dir, s.path, "test", progress=progress)
        if main:
            o = rec["overall"]
            results.append(
                {
                    "kappa_px": s.geometry.kappa_px,
                    "scale": s.geometry.scale,
                    "data": str(s.path.resolve()),
                    "run": str(run_dir.resolve()),
                    "samples_seen": rec["samples_seen"],
                    **{k: o.get(k) for k in ("balanced_accuracy", "tpr", "tnr", "accuracy", "n")},
                }
            )
        if dist.is_initialized():
            dist.barrier()
    record = {"arch": config.arch, "config": config.to_dict(), "results": results}
    if main:
        atomic.write_json(out_dir / "ablation.json", record)
        plot_ablation(results, out_dir / "ablation.png", title=f"{config.arch}: test balanced accuracy vs kappa")
    return record
