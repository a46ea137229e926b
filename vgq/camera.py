"""Pinhole camera model (OpenCV convention: x right, y down, z along the principal ray).

Units: metres for points and depth, pixels for (u, v). Pixel centres sit on integer
coordinates, so the centre of a 300 px wide image is u = 149.5.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of a depth sensor (pixels)."""

    fx: float = 525.0
    fy: float = 525.0
    cx: float = 149.5
    cy: float = 149.5
    width: int = 300
    height: int = 300

    def __post_init__(self) -> None:
        vals = (self.fx, self.fy, self.cx, self.cy)
        if not all(np.isfinite(v) for v in vals):
            raise ValueError(f"intrinsics must be finite, got {vals}")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"focal lengths must be > 0, got fx={self.fx}, fy={self.fy}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be > 0, got {self.width}x{self.height}")

    @property
    def matrix(self) -> np.ndarray:
        """3x3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "Intrinsics":
        return cls(**{k: d[k] for k in ("fx", "fy", "cx", "cy", "width", "height")})


DEFAULT_INTRINSICS = Intrinsics()


def project(points_cam: np.ndarray, intr: Intrinsics = DEFAULT_INTRINSICS) -> np.ndarray:
    """Project camera-frame points (n, 3) in metres to (n, 3) rows of (u, v, z)."""
    p = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intr.fx * p[:, 0] / z + intr.cx
        v = intr.fy * p[:, 1] / z + intr.cy
    return np.stack([u, v, z], axis=1)


def deproject(uvz: np.ndarray, intr: Intrinsics = DEFAULT_INTRINSICS) -> np.ndarray:
    """Inverse of :func:`project`: (n, 3) rows of (u, v, z) to camera-frame points (n, 3)."""
    a = np.asarray(uvz, dtype=np.float64).reshape(-1, 3)
    x = (a[:, 0] - intr.cx) * a[:, 2] / intr.fx
    y = (a[:, 1] - intr.cy) * a[:, 2] / intr.fy
    return np.stack([x, y, a[:, 2]], axis=1)
