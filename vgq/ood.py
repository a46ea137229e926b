"""Out-of-distribution flags: the reasons a grasp's score is not to be trusted.

A grasp row is (u, v, z, qw, qx, qy, qz): pixel (image px), depth z (metres, camera frame),
orientation (camera frame, w, x, y, z; gripper z = approach). Each flag is one bit, so a
grasp's flags travel as one small integer and as a list of names.
"""

from __future__ import annotations

import numpy as np

from .camera import valid_depth

#: bit -> name, in bit order
OOD_FLAGS: dict[int, str] = {
    1: "approach_away_from_camera",  # psi >= 90 deg: the training data filtered these out
    2: "z_outside_training_range",  # TCP depth outside the z range the model was trained on
    4: "center_on_missing_depth",  # the grasp's pixel has no depth reading in the upload
    8: "window_mostly_missing",  # its crop window is mostly missing depth (inpainted)
    16: "camera_tilt_outside_training",  # the camera (its up direction given) looks more sideways than any training camera
}
APPROACH_AWAY, Z_OUT_OF_RANGE, CENTER_MISSING, WINDOW_MISSING, CAMERA_TILT = OOD_FLAGS


def approach_away(q: np.ndarray) -> np.ndarray:
    """(k,) bool: the approach axis (gripper z in the camera frame) points back towards the
    camera or sideways (psi >= 90 deg). ``q`` (k, 4) unit quaternions (w, x, y, z)."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    # R[2, 2] = cos(psi) = 1 - 2 (x^2 + y^2) for a unit quaternion. In floating point too,
    # 1 - 2 s <= 0 exactly when s >= 0.5: 2 s is exact, and a positive 1 - 2 s never rounds to 0
    x, y = q[:, 1], q[:, 2]
    return x * x + y * y >= 0.5


def center_missing(uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """(k,) bool: the nearest pixel to each (u, v) (k, 2) has no reading (:func:`vgq.camera.valid_depth`)."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    h, w = depth.shape
    px = np.floor(uv + 0.5).astype(np.int64)  # (k, 2) nearest (column, row)
    np.maximum(px, 0, out=px)
    np.minimum(px, (w - 1, h - 1), out=px)  # clipped to the image (np.clip, without its overhead)
    return ~valid_depth(depth[px[:, 1], px[:, 0]])


def ood_flags(
    grasps: np.ndarray,
    depth: np.ndarray,
    z_range: tuple[float, float],
    window_missing: np.ndarray | bool = False,
    camera_tilted: bool = False,
) -> np.ndarray:
    """(k,) uint8 bitmask of :data:`OOD_FLAGS` for grasp rows (k, 7) on ``depth`` (H, W,
    metres, the image as uploaded: missing pixels still 0). ``z_range`` (metres) is the
    training range; ``window_missing`` per grasp (or one bool): its window is mostly missing;
    ``camera_tilted``: the camera's tilt is outside the training cameras'
    (:func:`vgq.camera.tilt_outside_training`)."""
    g = np.asarray(grasps, dtype=np.float64).reshape(-1, 7)
    z = g[:, 2]
    flags = np.zeros(len(g), dtype=np.uint8)
    for bit, hit in (
        (APPROACH_AWAY, approach_away(g[:, 3:7])),
        (Z_OUT_OF_RANGE, (z < z_range[0]) | (z > z_range[1])),
        (CENTER_MISSING, center_missing(g[:, :2], depth)),
        (WINDOW_MISSING, np.asarray(window_missing, dtype=bool)),  # (k,) or one bool, broadcast by `where`
        (CAMERA_TILT, bool(camera_tilted)),
    ):
        np.bitwise_or(flags, bit, out=flags, where=hit)
    return flags


def flag_names(mask: int) -> list[str]:
    """Names of the bits set in one grasp's ``mask``, in bit order."""
    return [name for bit, name in OOD_FLAGS.items() if int(mask) & bit]
