"""Input normalisation of the networks: one scalar mean / std for depth pixels, per-column
mean / std for pose inputs, except quaternion columns (mean 0, std 1). A zero std becomes 1.

``image_reference`` "centre": every crop is first made relative to its own reference depth,
the mean of its central ``REFERENCE_PIXELS`` x ``REFERENCE_PIXELS`` pixels (``window_reference``),
so the image statistics are those of the relief (metres) and the reference itself travels as
one more scalar (``reference_mean`` / ``reference_std``). "none": absolute depth (the paper's).

Statistics come from the training split only; they are stored in the model card and baked
into the exported ONNX graphs, so clients always pass raw metres and crop pixels.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .pose import QUATERNION_COLUMNS

IMAGE_REFERENCES = ("none", "centre")
#: side of the central block whose mean depth is a crop's reference (``image_reference`` "centre")
REFERENCE_PIXELS = 4


def window_reference(images: np.ndarray) -> np.ndarray:
    """(n,) reference depth (metres) of (n, ..., S, S) crops: the mean of their central
    REFERENCE_PIXELS x REFERENCE_PIXELS block (S even)."""
    images = np.asarray(images, dtype=np.float32)
    s = images.shape[-1]
    lo = (s - REFERENCE_PIXELS) // 2
    block = images[..., lo : lo + REFERENCE_PIXELS, lo : lo + REFERENCE_PIXELS]
    return block.reshape(len(images), -1).mean(axis=1)


@dataclass
class Normalization:
    image_mean: float
    image_std: float
    pose_columns: tuple[str, ...]
    pose_mean: list[float] = field(default_factory=list)
    pose_std: list[float] = field(default_factory=list)
    image_reference: str = "none"
    reference_mean: float = 0.0
    reference_std: float = 1.0

    def __post_init__(self) -> None:
        self.pose_columns = tuple(self.pose_columns)
        if self.image_reference not in IMAGE_REFERENCES:
            raise ValueError(f"image_reference must be one of {IMAGE_REFERENCES}, got {self.image_reference!r}")
        if not (np.isfinite(self.reference_mean) and np.isfinite(self.reference_std) and self.reference_std > 0):
            raise ValueError("reference_mean / reference_std must be finite, reference_std > 0")
        if len(self.pose_mean) != len(self.pose_columns) or len(self.pose_std) != len(self.pose_columns):
            raise ValueError("pose_mean / pose_std must have one entry per pose column")
        vals = [self.image_mean, self.image_std, *self.pose_mean, *self.pose_std]
        if not all(np.isfinite(v) for v in vals):
            raise ValueError("normalisation constants must be finite")
        if self.image_std <= 0 or any(s <= 0 for s in self.pose_std):
            raise ValueError("normalisation std must be > 0")

    @classmethod
    def from_data(
        cls, images: np.ndarray, poses: np.ndarray, pose_columns, image_reference: str = "none"
    ) -> Normalization:
        """Statistics of training images (any shape, metres; (n, ..., S, S) crops for
        ``image_reference`` "centre") and poses (n, len(pose_columns))."""
        pose_columns = tuple(pose_columns)
        images = np.asarray(images)
        relative = image_reference == "centre"
        # float64 accumulation over possibly memory-mapped data, in blocks, shifted by the first
        # image's mean so that E[x^2] - E[x]^2 does not cancel to rounding noise
        shift = None
        s = s2 = r = r2 = 0.0
        n = 0
        for i in range(0, len(images), 4096):
            blk = np.asarray(images[i : i + 4096], dtype=np.float32)
            if relative:
                ref = window_reference(blk)
                r, r2 = r + float(ref.sum(dtype=np.float64)), r2 + float((ref.astype(np.float64) ** 2).sum())
                blk = blk - ref.reshape((-1,) + (1,) * (blk.ndim - 1))
            blk = (
                blk.reshape(len(blk), -1).astype(np.float64) if blk.ndim > 1 else blk.reshape(-1, 1).astype(np.float64)
            )
            if shift is None:
                shift = float(blk[0].mean())
            blk -= shift
            s += blk.sum()
            s2 += (blk**2).sum()
            n += blk.size
        d = s / max(n, 1)
        mean = (shift or 0.0) + d
        std = float(np.sqrt(max(s2 / max(n, 1) - d**2, 0.0)))
        ref_mean, ref_std = 0.0, 1.0
        if relative and len(images):
            ref_mean = r / len(images)
            ref_std = float(np.sqrt(max(r2 / len(images) - ref_mean**2, 0.0)))
            ref_std = ref_std if ref_std > 1e-12 else 1.0
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
            image_reference=image_reference,
            reference_mean=ref_mean,
            reference_std=ref_std,
        )

    def normalize_image(self, x: np.ndarray) -> np.ndarray:
        """(n, ..., S, S) crops in metres -> the encoder's normalised input."""
        x = np.asarray(x, dtype=np.float32)
        if self.image_reference == "centre":
            x = x - window_reference(x).reshape((-1,) + (1,) * (x.ndim - 1))
        return (x - self.image_mean) / self.image_std

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
            "image_reference": self.image_reference,
            "reference_mean": self.reference_mean,
            "reference_std": self.reference_std,
        }

    @classmethod
    def from_dict(cls, d: dict) -> Normalization:
        return cls(
            image_mean=float(d["image_mean"]),
            image_std=float(d["image_std"]),
            pose_columns=tuple(d["pose_columns"]),
            pose_mean=[float(x) for x in d["pose_mean"]],
            pose_std=[float(x) for x in d["pose_std"]],
            image_reference=str(d.get("image_reference", "none")),
            reference_mean=float(d.get("reference_mean", 0.0)),
            reference_std=float(d.get("reference_std", 1.0)),
        )
