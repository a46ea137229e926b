"""Pose-only baseline: logistic regression or a small MLP on pose columns (no image),
trained on the train split, evaluated on the test split with the network's metrics.

It tells how much of the label the pose alone predicts (e.g. through the camera-grasp
geometry), the floor a grasp-quality CNN has to beat.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn
from tqdm import tqdm

from vgq import atomic
from vgq.pose import FULL_POSE_COLUMNS, POSE_COLUMNS, QUATERNION_COLUMNS
from vgq.pose_only import PoseOnlyModel, file_name

from . import metrics as M
from .data import DatasetError, open_crop_dataset
from .plots import plot_grid_heatmaps

MODELS = ("logreg", "mlp")


@dataclass
class BaselineConfig:
    model: str = field(default="logreg", metadata={"choices": MODELS, "help": "logreg | mlp (one hidden layer)"})
    columns: str = field(
        default="all",
        metadata={
            "choices": ("all", *POSE_COLUMNS),
            "help": "'all' (u, v, z, qw, qx, qy, qz) or an architecture's pose columns",
        },
    )
    hidden: int = 64
    epochs: int = 10
    batch_size: int = 4096
    lr: float = 0.01  # Adam
    class_balance: bool = True  # cross-entropy class weights n / (2 n_class): balanced accuracy is the target
    max_train_samples: int = 0  # 0: the whole train split
    seed: int = 0

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise ValueError(f"baseline model must be one of {MODELS}, got {self.model!r}")
        if self.columns != "all" and self.columns not in POSE_COLUMNS:
            raise ValueError(f"columns must be 'all' or one of {sorted(POSE_COLUMNS)}, got {self.columns!r}")
        if self.hidden <= 0 or self.epochs <= 0 or self.batch_size <= 0 or self.lr <= 0 or self.max_train_samples < 0:
            raise ValueError("hidden, epochs, batch_size, lr must be > 0 and max_train_samples >= 0")

    @property
    def column_names(self) -> tuple[str, ...]:
        return FULL_POSE_COLUMNS if self.columns == "all" else POSE_COLUMNS[self.columns]


def _features(poses: np.ndarray, cols: tuple[str, ...]) -> np.ndarray:
    idx = [FULL_POSE_COLUMNS.index(c) for c in cols]
    return np.ascontiguousarray(np.asarray(poses)[:, idx], dtype=np.float32)


def run_baseline(
    data_dir: str | Path, config: BaselineConfig | None = None, out: str | Path | None = None, progress: bool = True
) -> dict:
    """Train the baseline on ``train``, report metrics on ``val`` (if present) and ``test``.

    With ``out`` (a folder) writes ``baseline_<model>.json`` (metrics), ``baseline_<model>.npz``
    (the model, :mod:`vgq.pose_only`: planning ranks grasps with it torch-free) and
    ``heatmap_baseline_<model>.png``.
    """
    cfg = config or BaselineConfig()
    data = open_crop_dataset(data_dir)
    tr = data.split("train")
    data.split("test")  # must exist and be non-empty
    cols = cfg.column_names
    rng = np.random.default_rng(cfg.seed)
    n = len(tr)
    sel = np.sort(rng.choice(n, cfg.max_train_samples, replace=False)) if 0 < cfg.max_train_samples < n else slice(None)
    x = _features(tr.arrays["poses"][sel], cols)
    y = np.asarray(tr.labels[sel], dtype=np.int64)
    mean, std = x.mean(0), x.std(0)
    for i, c in enumerate(cols):
        if c in QUATERNION_COLUMNS:
            mean[i], std[i] = 0.0, 1.0
    std = np.where(std > 1e-12, std, 1.0).astype(np.float32)
    pos = int(y.sum())
    if pos == 0 or pos == len(y):
        raise DatasetError(f"crop dataset {data.path}: the train split has only one class")
    weight = torch.tensor([len(y) / (2.0 * (len(y) - pos)), len(y) / (2.0 * pos)]) if cfg.class_balance else None

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # a model this small only loses from thread synchronisation
    try:
        return _fit_and_score(cfg, data, cols, x, y, mean, std, weight, out, progress)
    finally:
        torch.set_num_threads(threads)


def _fit_and_score(cfg, data, cols, x, y, mean, std, weight, out, progress) -> dict:
    torch.manual_seed(cfg.seed)
    d = len(cols)
    model = (
        nn.Linear(d, 2)
        if cfg.model == "logreg"
        else nn.Sequential(
            nn.Linear(d, cfg.hidden), nn.ReLU(), nn.Linear(cfg.hidden, cfg.hidden), nn.ReLU(), nn.Linear(cfg.hidden, 2)
        )
    )
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    xt = torch.from_numpy((x - mean) / std)
    yt = torch.from_numpy(y)
    g = torch.Generator().manual_seed(cfg.seed)
    bar = tqdm(range(cfg.epochs), desc=f"baseline {cfg.model}", unit="epoch", disable=not progress)
    for _ in bar:
        perm = torch.randperm(len(yt), generator=g)
        tot = 0.0
        for i in range(0, len(perm), cfg.batch_size):
            b = perm[i : i + cfg.batch_size]
            loss = F.cross_entropy(model(xt[b]), yt[b], weight=weight)
            opt.zero_grad()
            loss.backward()
            opt.step()
            tot += loss.item() * len(b)
        bar.set_postfix(loss=f"{tot / len(yt):.4f}")

    @torch.no_grad()
    def predict(split) -> np.ndarray:
        f = torch.from_numpy((_features(split.arrays["poses"], cols) - mean) / std)
        return torch.softmax(model(f), 1)[:, 1].numpy()

    rec = {"config": asdict(cfg), "columns": list(cols), "data": str(data.path.resolve()), "train_samples": int(len(y))}
    for name in ("val", "test"):
        if name in data.splits and len(data.splits[name]):
            sp = data.splits[name]
            p = predict(sp)
            rec[name] = M.nan_to_none(M.binary_metrics(np.asarray(sp.labels), p))
            if name == "test":
                grid = M.grid_metrics(
                    np.asarray(sp.labels), p, np.asarray(sp.arrays["camera_d"]), np.asarray(sp.arrays["camera_phi"])
                )
                rec["grid"] = M.grid_to_json(grid)
    if out is not None:
        out = Path(out)
        linears = [m for m in model.modules() if isinstance(m, nn.Linear)]
        PoseOnlyModel(
            tuple(cols),
            mean.astype(np.float32),
            std.astype(np.float32),
            tuple((m.weight.detach().numpy().copy(), m.bias.detach().numpy().copy()) for m in linears),
        ).save(out / file_name(cfg.model))
        atomic.write_json(out / f"baseline_{cfg.model}.json", rec)
        plot_grid_heatmaps(
            grid, out / f"heatmap_baseline_{cfg.model}.png", title=f"pose-only {cfg.model} baseline (test)"
        )
    return rec
