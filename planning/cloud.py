"""The depth image as an organised point cloud with surface normals (camera frame, metres).

Pixel (u, v) back-projects through the pinhole model of :mod:`vgq.camera`; a pixel with
depth 0 or non-finite has no reading (``valid`` False, point and normal zero).
"""

from __future__ import annotations

import cv2
import numpy as np

from vgq.camera import Intrinsics, valid_depth


def valid_mask(depth: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels with a reading (:func:`vgq.camera.valid_depth`: finite, > 0, <= 10 m)."""
    return valid_depth(depth)


def backproject(depth: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Points (H, W, 3) float32 in the camera frame and the (H, W) valid mask.

    float32 (resolution ~0.1 um at 1 m): the organised cloud and its normals are the planner's
    largest arrays (per pixel: points, normals and the differences between them)."""
    d = np.asarray(depth, dtype=np.float32)
    valid = valid_mask(d)
    d = np.where(valid, d, np.float32(0.0))
    h, w = d.shape
    x = ((np.arange(w, dtype=np.float64) - intr.cx) / intr.fx).astype(np.float32)
    y = ((np.arange(h, dtype=np.float64) - intr.cy) / intr.fy).astype(np.float32)
    pts = np.empty((h, w, 3), np.float32)
    pts[..., 0] = x[None, :] * d
    pts[..., 1] = y[:, None] * d
    pts[..., 2] = d
    return pts, valid


def estimate_normals(points: np.ndarray, valid: np.ndarray, window: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Unit surface normals (H, W, 3), of the dtype of ``points``, of an organised cloud,
    pointing towards the camera, and where they are defined (H, W) bool.

    The normal at a pixel is the cross product of the central differences to its left /
    right and upper / lower neighbours, averaged over a ``window`` x ``window`` box. Where
    the neighbours straddle a depth edge the differences follow the edge, so a silhouette
    pixel gets the normal of the side the camera grazes (perpendicular to its ray): the
    direction a jaw closing on that side pushes against."""
    p = points
    dx = np.zeros_like(p)
    dy = np.zeros_like(p)
    dx[:, 1:-1] = p[:, 2:] - p[:, :-2]
    dy[1:-1] = p[2:] - p[:-2]
    ok = np.zeros_like(valid)
    ok[1:-1, 1:-1] = valid[1:-1, 1:-1] & valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1] & valid[:-2, 1:-1]
    # n = -(dx x dy), written out (np.cross is slow on image-sized arrays)
    n = np.empty_like(p)
    n[..., 0] = dx[..., 2] * dy[..., 1] - dx[..., 1] * dy[..., 2]
    n[..., 1] = dx[..., 0] * dy[..., 2] - dx[..., 2] * dy[..., 0]
    n[..., 2] = dx[..., 1] * dy[..., 0] - dx[..., 0] * dy[..., 1]
    del dx, dy
    n /= np.maximum(_norm(n), 1e-12)[..., None]
    n[~ok] = 0.0
    if window > 1:  # the box mean of each component, edges replicated
        n = cv2.boxFilter(n, -1, (window, window), normalize=True, borderType=cv2.BORDER_REPLICATE)
    norm = _norm(n)
    ok &= norm > 1e-6
    n /= np.maximum(norm, 1e-12)[..., None]
    # towards the camera: n . p < 0
    np.negative(n, out=n, where=(np.einsum("ijk,ijk->ij", n, p) > 0)[..., None])
    n[~ok] = 0.0
    return n, ok


def _norm(v: np.ndarray) -> np.ndarray:
    """Euclidean norms (H, W) of an image of 3-vectors (H, W, 3)."""
    return np.sqrt(np.einsum("ijk,ijk->ij", v, v))
