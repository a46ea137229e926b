"""Input normalisation of the networks: one scalar mean / std for depth pixels, per-column
mean / std for pose inputs, except quaternion columns (mean 0, std 1). A zero std becomes 1.

Statistics come from the training split only; they are stored in the model card and baked
into the exported ONNX graphs, so clients always pass raw metres and crop pixels.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .pose import QUATERNION_COLUMNS


@dataclass
class Normalization:
    image_mean: float
    image_std: float
    pose_columns: tuple[str, ...]
    pose_mean: list[float] = field(default_factory=list)
    pose_std: list[float] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.pose_columns = tuple(self.pose_columns)
        if len(self.pose_mean) != len(self.pose_columns) or len(self.pose_std) != len(self.pose_columns):
            raise ValueError("pose_mean / pose_std must have one entry per pose column")
        vals = [self.image_mean, self.image_std, *self.pose_mean, *self.pose_std]
        if not all(np.isfinite(v) for v in vals):
            raise ValueError("normalisation constants must be finite")
        if self.image_std <= 0 or any(s <= 0 for s in self.pose_std):
            raise ValueError("normalisation std must be > 0")

    @classmethod
    def from_data(cls, images: np.ndarray, poses: np.ndarray, pose_columns) -> Normalization:
        """Statistics of training images (any shape, metres) and poses (n, len(pose_columns))."""
        pose_columns = tuple(pose_columns)
        images = np.asarray(images)
        # float64 accumulation over possibly memory-mapped data, chunked, shifted by the first
        # image's mean so that E[x^2] - E[x]^2 does not cancel to rounding noise
        flat = images.reshape(len(images), -1) if images.ndim > 1 else images.reshape(-1, 1)
        shift = float(np.asarray(flat[0], dtype=np.float64).mean()) if len(flat) else 0.0
        s = s2 = 0.0
        n = 0
        for i in range(0, len(flat), 4096):
            blk = np.asarray(flat[i : i + 4096], dtype=np.float64) - shift
            s += blk.sum()
            s2 += (blk**2).sum()
            n += blk.size
        d = s / max(n, 1)
        mean = shift + d
        std = float(np.sqrt(max(s2 / max(n, 1) - d**2, 0.0)))
        poses = np.asarray(poses, dtype=np.float64).reshape(len(poses), len(pose_columns))
        pm = poses.mean(axis=0) if len(poses) else np.zeros(len(pose_columns))
        ps = poses.std(axis=0) if len(poses) else np.ones(len(pose_columns))
        for i, c in enumerate(pose_columns):
            if c in QUATERNION_COLUMNS:
                pm[i], ps[i] = 0.0, 1.0
        ps = np.where(ps > 1e-12, ps, 1.0)
        return cls(
            image_mean=float(mean),
            image_std=std if std > 1e-12 else 1.0,
            pose_columns=pose_columns,
            pose_mean=[float(x) for x in pm],
            pose_std=[float(x) for x in ps],
        )

    def normalize_image(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x, dtype=np.float32) - self.image_mean) / self.image_std

    def normalize_pose(self, p: np.ndarray) -> np.ndarray:
        return (np.asarray(p, dtype=np.float32) - np.asarray(self.pose_mean, np.float32)) / np.asarray(
            self.pose_std, np.float32
        )

    def to_dict(self) -> dict:
        return {
            "image_mean": self.image_mean,
            "image_std": self.image_std,
            "pose_columns": list(self.pose_columns),
            "pose_mean": list(self.pose_mean),
            "pose_std": list(self.pose_std),
        }

    @classmethod
    def from_dict(cls, d: dict) -> Normalization:
        return cls(
            image_mean=float(d["image_mean"]),
            image_std=float(d["image_std"]),
            pose_columns=tuple(d["pose_columns"]),
            pose_mean=[float(x) for x in d["pose_mean"]],
            pose_std=[float(x) for x in d["pose_std"]],
        )
