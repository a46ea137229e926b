"""Client grasps -> network pose rows, checked: the contract between a caller (the service,
the benchmark) and a Fast-VGQ-CNN's head.

A grasp is ``(u, v, z, qw, qx, qy, qz)``: (u, v) the TCP pixel in the full depth image
(u = column, v = row), z the TCP depth in metres (camera frame), q the orientation
quaternion in the camera frame (w, x, y, z); q is normalised and made canonical
(``vgq.pose.canonical_quaternion``). A pose row is ``(du, dv, z, qw, qx, qy, qz)`` with
(du, dv) in crop pixels from the crop window's centre (``vgq.crop.pose_uv``).

Bad batches raise ``GraspError`` (a ``vgq.pose.PoseError``, so a ValueError) whose
``indices`` name the offending rows.
"""

from __future__ import annotations

import numpy as np

from .crop import CropGeometry, in_training_range, pose_uv
from .pose import PoseError, canonical_rows, largest_component

GRASP_WIDTH = 7
MAX_Z_M = 10.0  # TCP depth bound (metres): beyond it the float32 network input is meaningless or inf
ZERO_QUATERNION = 1e-6  # a quaternion whose largest |component| is below this is "zero"


class GraspError(PoseError):
    """A batch of grasps that cannot be scored; ``indices``: the offending rows (up to 20)."""


def pose_rows(
    grasps: np.ndarray, window_center: np.ndarray, geom: CropGeometry, max_grasps: int, check_window: bool = True
) -> np.ndarray:
    """Check (k, 7) grasps against a crop window centred at ``window_center`` (image px, (u, v),
    one centre or one per grasp) and return (k, 7) float32 network pose rows. Raises GraspError.
    ``check_window=False``: the caller placed each grasp's window itself within kappa (the
    service's training grid, or its fixed window checked before), so that check is skipped."""
    grasps = np.asarray(grasps, dtype=np.float64)
    if grasps.ndim != 2 or grasps.shape[1] != GRASP_WIDTH:
        raise GraspError(f"grasps must be (k, {GRASP_WIDTH}) rows u, v, z, qw, qx, qy, qz; got shape {grasps.shape}")
    k = len(grasps)
    if k == 0:
        raise GraspError("no grasps given (k = 0)")
    if k > max_grasps:
        raise GraspError(f"{k} grasps given; at most {max_grasps} per request")
    # whole-array checks first; the offending rows are only looked for when one fails
    if not np.isfinite(grasps).all():
        bad = ~np.isfinite(grasps).all(axis=1)
        raise GraspError(f"{int(bad.sum())} grasps have non-finite values", np.flatnonzero(bad))
    z = grasps[:, 2]
    if not (z.min() > 0 and z.max() <= MAX_Z_M):
        bad = ~((z > 0) & (z <= MAX_Z_M))
        raise GraspError(
            f"{int(bad.sum())} grasps have depth z outside (0, {MAX_Z_M:g}] (metres, camera frame)", np.flatnonzero(bad)
        )
    q = grasps[:, 3:7]
    largest = largest_component(q)
    if largest.min() < ZERO_QUATERNION:
        bad = largest < ZERO_QUATERNION
        raise GraspError(f"{int(bad.sum())} grasps have a zero quaternion", np.flatnonzero(bad))
    if check_window:
        bad = ~in_training_range(grasps[:, :2], window_center, geom)  # the crop contract's one definition
        if bad.any():
            c, r = window_center, geom.kappa_px
            raise GraspError(
                f"{int(bad.sum())} grasps lie outside the window the model was trained for: u in "
                f"[{c[0] - r:g}, {c[0] + r:g}], v in [{c[1] - r:g}, {c[1] + r:g}] "
                "(upload the image again with center_u / center_v near these grasps)",
                np.flatnonzero(bad),
            )
    out = np.empty((k, GRASP_WIDTH), np.float32)
    out[:, :2] = pose_uv(grasps[:, :2], window_center, geom)
    out[:, 2] = z
    out[:, 3:] = canonical_rows(q, largest)  # vgq.pose.canonical_quaternion, its checks done above
    return out
