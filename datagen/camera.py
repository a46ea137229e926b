"""Camera poses on a sphere around the world origin (SPEC section 1).

World frame: table surface z = 0, z up. Camera frame: OpenCV (x right, y down, z along the
principal ray). Distances in metres, angles in radians. A pose is given by the distance ``d``
from the world origin, the elevation ``phi`` from the table normal (0 = straight overhead) and
the azimuth ``theta`` about the world z-axis.
"""

from __future__ import annotations

from dataclasses import dataclass
from math import pi, radians

import numpy as np


@dataclass(frozen=True)
class CameraParams:
    """Sampling ranges (inclusive low, exclusive high) for camera poses; metres, radians."""

    d_range: tuple[float, float] = (0.4, 1.1)
    phi_range: tuple[float, float] = (0.0, radians(70.0))
    theta_range: tuple[float, float] = (0.0, 2.0 * pi)

    def __post_init__(self) -> None:
        for name in ("d_range", "phi_range", "theta_range"):
            r = getattr(self, name)
            if len(r) != 2 or not all(np.isfinite(x) for x in r):
                raise ValueError(f"CameraParams.{name} must be two finite numbers, got {r!r}")
            if r[0] > r[1]:
                raise ValueError(f"CameraParams.{name} must be (low, high) with low <= high, got {r!r}")
        if self.d_range[0] <= 0:
            raise ValueError(f"CameraParams.d_range must be > 0 m, got {self.d_range!r}")
        if self.phi_range[0] < 0 or self.phi_range[1] >= pi / 2:
            raise ValueError(
                f"CameraParams.phi_range must lie in [0, pi/2) rad (above the table), got {self.phi_range!r}"
            )


@dataclass
class CameraPoses:
    """n camera poses: ``T_world_camera`` (n, 4, 4) OpenCV camera frames and their spherical
    coordinates ``d`` (n,) metres, ``phi`` (n,) and ``theta`` (n,) radians."""

    T_world_camera: np.ndarray
    d: np.ndarray
    phi: np.ndarray
    theta: np.ndarray

    def __len__(self) -> int:
        return int(self.d.shape[0])


def look_at_table_origin(d, phi, theta) -> np.ndarray:
    """Camera poses (n, 4, 4) ``T_world_camera`` at spherical coordinates (d, phi, theta).

    The camera sits at ``d * (sin phi cos theta, sin phi sin theta, cos phi)``; its z-axis
    (principal ray) points at the world origin; its x-axis is the horizontal azimuth tangent
    ``(-sin theta, cos theta, 0)``, parallel to the table, so image rows are level and world
    "up" points towards -v (the object appears upright). The x-axis depends on theta only, so
    phi = 0 (straight overhead) is not degenerate. Inputs broadcast to a common (n,) shape.
    """
    d, phi, theta = (np.asarray(a, dtype=np.float64) for a in (d, phi, theta))
    d, phi, theta = (a.reshape(-1) for a in np.broadcast_arrays(d, phi, theta))
    if not (np.all(np.isfinite(d)) and np.all(np.isfinite(phi)) and np.all(np.isfinite(theta))):
        raise ValueError("camera d, phi, theta must be finite")
    if np.any(d <= 0):
        raise ValueError(f"camera distance d must be > 0 m, got min {d.min()}")
    if np.any(phi < 0) or np.any(phi >= pi / 2):
        raise ValueError("camera elevation phi must lie in [0, pi/2) rad (camera above the table)")
    sp, cp, st, ct = np.sin(phi), np.cos(phi), np.sin(theta), np.cos(theta)
    n = d.shape[0]
    radial = np.stack([sp * ct, sp * st, cp], axis=1)  # unit vector origin -> camera
    z = -radial
    x = np.stack([-st, ct, np.zeros(n)], axis=1)
    y = np.cross(z, x)  # (cos phi cos theta, cos phi sin theta, -sin phi): world-down component
    T = np.zeros((n, 4, 4))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2] = x, y, z
    T[:, :3, 3] = d[:, None] * radial
    T[:, 3, 3] = 1.0
    return T


def sample_cameras(n: int, params: CameraParams, rng: np.random.Generator) -> CameraPoses:
    """Draw ``n`` camera poses with d, phi, theta each uniform over ``params``' ranges."""
    if int(n) != n or n < 0:
        raise ValueError(f"number of cameras must be a non-negative integer, got {n!r}")
    n = int(n)
    d = rng.uniform(*params.d_range, size=n)
    phi = rng.uniform(*params.phi_range, size=n)
    theta = rng.uniform(*params.theta_range, size=n)
    return CameraPoses(T_world_camera=look_at_table_origin(d, phi, theta), d=d, phi=phi, theta=theta)
