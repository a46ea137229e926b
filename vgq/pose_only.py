"""The pose-only baseline's model file: one format, written by ``training baseline`` and read
torch-free (numpy) by whoever ranks grasps with it (``planning.bench``).

``baseline_<model>.npz`` holds ``columns`` (names from ``vgq.pose.FULL_POSE_COLUMNS``),
``mean`` and ``std`` (the feature standardisation), and ``w0, b0, w1, b1, ...``: dense layers
``x @ w.T + b`` with ReLU between them; the last one gives the two class logits. A grasp's
features are its pose row (u, v in crop pixels from the window centre, z metres, quaternion
w, x, y, z) in ``FULL_POSE_COLUMNS`` order, the rows the head takes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import atomic
from .pose import FULL_POSE_COLUMNS


class PoseOnlyError(ValueError):
    """A baseline model file that cannot be read."""


def file_name(model: str) -> str:
    return f"baseline_{model}.npz"


@dataclass(frozen=True)
class PoseOnlyModel:
    columns: tuple[str, ...]
    mean: np.ndarray
    std: np.ndarray
    layers: tuple[tuple[np.ndarray, np.ndarray], ...]  # (weight (out, in), bias (out,))

    def save(self, path: str | Path) -> None:
        arrays = {"columns": np.array(self.columns), "mean": self.mean, "std": self.std}
        for i, (w, b) in enumerate(self.layers):
            arrays[f"w{i}"], arrays[f"b{i}"] = w, b
        atomic.save_npz(path, **{k: np.asarray(v) for k, v in arrays.items()})

    @classmethod
    def load(cls, path: str | Path) -> PoseOnlyModel:
        try:
            with np.load(path, allow_pickle=False) as z:
                columns = tuple(str(c) for c in z["columns"])
                layers, i = [], 0
                while f"w{i}" in z:
                    layers.append((z[f"w{i}"].astype(np.float32), z[f"b{i}"].astype(np.float32)))
                    i += 1
                mean, std = z["mean"].astype(np.float32), z["std"].astype(np.float32)
        except (OSError, KeyError, ValueError) as e:
            raise PoseOnlyError(f"{path}: not a pose-only baseline file ({e})") from None
        unknown = [c for c in columns if c not in FULL_POSE_COLUMNS]
        if unknown or not layers or mean.shape != (len(columns),) or std.shape != mean.shape:
            raise PoseOnlyError(f"{path}: bad columns {unknown or columns} or standardisation / layer shapes")
        width = len(columns)
        for w, b in layers:
            if w.ndim != 2 or w.shape[1] != width or b.shape != (w.shape[0],):
                raise PoseOnlyError(f"{path}: layer shapes do not chain ({w.shape} after width {width})")
            width = w.shape[0]
        if width != 2:
            raise PoseOnlyError(f"{path}: the last layer gives {width} outputs, not 2 logits")
        return cls(columns, mean, std, tuple(layers))

    def predict(self, poses: np.ndarray) -> np.ndarray:
        """P(success) (n,) of pose rows (n, 7) in ``FULL_POSE_COLUMNS`` order."""
        idx = [FULL_POSE_COLUMNS.index(c) for c in self.columns]
        x = (np.asarray(poses, np.float32)[:, idx] - self.mean) / self.std
        for i, (w, b) in enumerate(self.layers):
            x = x @ w.T + b
            if i < len(self.layers) - 1:
                x = np.maximum(x, 0.0)
        z = x[:, 1] - x[:, 0]
        return 1.0 / (1.0 + np.exp(-np.clip(z, -60, 60)))
