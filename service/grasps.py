"""Parse and check a batch of grasps, and turn them into network pose rows.

A grasp from a client is ``(u, v, z, qw, qx, qy, qz)``: (u, v) the TCP pixel in the
uploaded image (u = column, v = row), z the TCP depth in metres (camera frame), q the
orientation quaternion in the camera frame (w, x, y, z). Non-unit quaternions are
normalised; q and -q are the same rotation (made canonical, w >= 0).
"""

from __future__ import annotations

import numpy as np
import orjson

from vgq.crop import CropGeometry, pose_uv
from vgq.pose import canonical_quaternion

from .errors import ApiError

GRASP_WIDTH = 7
MAX_Z_M = 10.0  # TCP depth bound (metres): beyond it the float32 network input is meaningless or inf
_MAX_LISTED = 20


def _indices(mask: np.ndarray) -> list[int]:
    return [int(i) for i in np.flatnonzero(mask)[:_MAX_LISTED]]


def parse_json(body: bytes | list) -> np.ndarray:
    """``{"grasps": [[u, v, z, qw, qx, qy, qz], ...]}`` (or objects with u, v, z, q) -> (k, 7) float64."""
    try:
        doc = orjson.loads(body) if isinstance(body, (bytes, bytearray, str)) else body
    except orjson.JSONDecodeError as e:
        raise ApiError(400, f"body is not valid JSON: {e}") from None
    rows = doc.get("grasps") if isinstance(doc, dict) else None
    if not isinstance(rows, list):
        raise ApiError(422, 'body must be a JSON object with a "grasps" list of [u, v, z, qw, qx, qy, qz] rows')
    if rows and isinstance(rows[0], dict):
        try:
            rows = [[g["u"], g["v"], g["z"], *g["q"]] for g in rows]
        except (KeyError, TypeError):
            raise ApiError(422, 'grasp objects need keys "u", "v", "z" and "q" (a list of 4: w, x, y, z)') from None
    try:
        a = np.array(rows, dtype=np.float64)
    except (ValueError, TypeError):
        raise ApiError(422, "every grasp must be a list of 7 numbers [u, v, z, qw, qx, qy, qz]") from None
    if a.size == 0:
        a = a.reshape(0, GRASP_WIDTH)
    if a.ndim != 2 or a.shape[1] != GRASP_WIDTH:
        raise ApiError(422, "every grasp must be a list of 7 numbers [u, v, z, qw, qx, qy, qz]")
    return a


def parse_binary(body: bytes) -> np.ndarray:
    """Little-endian float32, k x 7 row-major -> (k, 7) float64."""
    if len(body) % (GRASP_WIDTH * 4):
        raise ApiError(422, f"binary grasps must be k x 7 float32 (a multiple of 28 bytes), got {len(body)} bytes")
    return np.frombuffer(body, dtype="<f4").reshape(-1, GRASP_WIDTH).astype(np.float64)


def _unit_canonical(q: np.ndarray) -> np.ndarray:
    """``vgq.pose.canonical_quaternion`` of finite, non-zero (k, 4) rows, ~5x faster: rows
    with |w| > 1e-12 (after normalising) take the sign of w; the rare others go through
    canonical_quaternion (first non-zero component positive)."""
    u = q / np.sqrt(np.einsum("ij,ij->i", q, q))[:, None]
    w = u[:, 0]
    u *= np.where(w < 0, -1.0, 1.0)[:, None]
    tiny = np.abs(w) <= 1e-12
    if tiny.any():
        u[tiny] = canonical_quaternion(q[tiny])
    return u


def to_network_poses(grasps: np.ndarray, window_center: np.ndarray, geom: CropGeometry, max_grasps: int) -> np.ndarray:
    """Check (k, 7) client grasps and return (k, 7) float32 network pose rows
    ``(du, dv, z, qw, qx, qy, qz)`` with (du, dv) in crop pixels. Raises ApiError 422."""
    k = len(grasps)
    if k == 0:
        raise ApiError(422, "no grasps given (k = 0)")
    if k > max_grasps:
        raise ApiError(422, f"{k} grasps given; at most {max_grasps} per request")
    bad = ~np.isfinite(grasps).all(axis=1)
    if bad.any():
        raise ApiError(422, f"{int(bad.sum())} grasps have non-finite values", {"grasps": _indices(bad)})
    bad = ~((grasps[:, 2] > 0) & (grasps[:, 2] <= MAX_Z_M))
    if bad.any():
        raise ApiError(422, f"{int(bad.sum())} grasps have depth z outside (0, {MAX_Z_M:g}] (metres, camera frame)",
                       {"grasps": _indices(bad)})
    q = grasps[:, 3:7]
    qmax = np.abs(q).max(axis=1, keepdims=True)  # largest |component|: scale without overflow (|q| up to 1e308)
    bad = qmax[:, 0] < 1e-6
    if bad.any():
        raise ApiError(422, f"{int(bad.sum())} grasps have a zero quaternion", {"grasps": _indices(bad)})
    q = _unit_canonical(q / qmax)  # unit, w >= 0
    off = grasps[:, :2] - window_center
    bad = (np.abs(off) > geom.kappa_px + 1e-6).any(axis=1)
    if bad.any():
        c = window_center
        raise ApiError(
            422,
            f"{int(bad.sum())} grasps lie outside the window the model was trained for: u in "
            f"[{c[0] - geom.kappa_px:g}, {c[0] + geom.kappa_px:g}], v in [{c[1] - geom.kappa_px:g}, {c[1] + geom.kappa_px:g}] "
            "(upload the image again with center_u / center_v near these grasps)",
            {"grasps": _indices(bad)},
        )
    out = np.empty((k, GRASP_WIDTH), np.float32)
    out[:, :2] = pose_uv(grasps[:, :2], window_center, geom)
    out[:, 2] = grasps[:, 2]
    out[:, 3:] = q
    return out
