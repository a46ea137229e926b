"""Windows turned towards the jaw axis: which of K in-plane turns a grasp is scored in.

A Fast-VGQ-CNN trained with ``CropGeometry.jaw_turns`` = K sees each grasp in a window of the
image turned about the optical axis by the multiple of pi / K nearest to the grasp's in-image
jaw angle (modulo pi: a jaw axis and its reverse are the same line), so the jaw axis lies within
+/- pi / (2K) of horizontal in every window it was trained on. A turn is a roll of the camera
(:func:`vgq.camera.level_depth`, :func:`vgq.camera.map_pixels`, :func:`vgq.pose.roll_quaternions`
with the same angle), so the pose stays exact: the residual angle is in the rolled quaternion.
One definition for datagen's crops and the service, so that both pick the same turn for a row.

Angles in radians, in-image angles measured from +u towards +v (pixel rows grow downwards).
"""

from __future__ import annotations

import numpy as np

from .camera import DEFAULT_INTRINSICS, Intrinsics, level_depth, map_pixels
from .pose import canonical_quaternion, matrix_from_quaternion, roll_quaternions


def jaw_angles(p_cam: np.ndarray, x_cam: np.ndarray, intr: Intrinsics = DEFAULT_INTRINSICS) -> np.ndarray:
    """In-image angles (n,) radians, in (-pi, pi], of the jaw axis ``x_cam`` (n, 3) at the
    TCP ``p_cam`` (n, 3) (camera frame, metres): the direction in which the projection of
    p + s * x moves for small s > 0, measured from +u towards +v."""
    p, x = np.asarray(p_cam, dtype=np.float64), np.asarray(x_cam, dtype=np.float64)
    z = p[:, 2]
    du = intr.fx * (x[:, 0] * z - p[:, 0] * x[:, 2])
    dv = intr.fy * (x[:, 1] * z - p[:, 1] * x[:, 2])
    return np.arctan2(dv, du)


def pose_jaw_angles(uv: np.ndarray, z: np.ndarray, q: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """In-image jaw angles (n,) radians of grasps given as pose rows: TCP pixel ``uv`` (n, 2),
    depth ``z`` (n,) metres, unit quaternions ``q`` (n, 4) (w, x, y, z), camera ``intr``
    (:func:`jaw_angles` of the back-projected TCP and the rotation's x column)."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    z = np.asarray(z, dtype=np.float64).reshape(-1)
    p = np.stack([(uv[:, 0] - intr.cx) * z / intr.fx, (uv[:, 1] - intr.cy) * z / intr.fy, z], axis=1)
    x = matrix_from_quaternion(np.asarray(q, dtype=np.float64).reshape(-1, 4))[:, :, 0]
    return jaw_angles(p, x, intr)


def check_turns(turns: int) -> int:
    """``turns`` as an int: 0 (windows not turned) or >= 2. ValueError otherwise."""
    t = int(turns)
    if t != turns or t < 0 or t == 1:
        raise ValueError(f"jaw_turns must be 0 (not turned) or an integer >= 2, got {turns}")
    return t


def turn_index(jaw_angle: np.ndarray, turns: int) -> np.ndarray:
    """(n,) int64 in [0, turns): the turn k whose angle k * pi / turns is nearest to each jaw
    angle (radians) modulo pi. ``turns`` >= 2."""
    a = np.asarray(jaw_angle, dtype=np.float64)
    return np.mod(np.rint(a * (turns / np.pi)), turns).astype(np.int64)


def turn_roll(index: int, turns: int) -> float:
    """The roll (radians, [0, pi)) of turn ``index`` of ``turns``: the camera turned by it sees a
    jaw axis at that in-image angle horizontal."""
    return float(index) * np.pi / turns


def turned_view(depth: np.ndarray, intr: Intrinsics, turn: int, turns: int) -> tuple[np.ndarray, Intrinsics, float]:
    """The depth image (H, W) metres of camera ``intr`` turned by turn ``turn`` of ``turns``: (depth',
    the turned canvas's intrinsics, the roll in radians) (:func:`vgq.camera.level_depth`)."""
    roll = turn_roll(turn, turns)
    d, canvas = level_depth(depth, intr, roll)
    return d, canvas, roll


def turned_poses(uv: np.ndarray, q: np.ndarray, intr: Intrinsics, canvas: Intrinsics, roll: float):
    """Grasp pixels ``uv`` (n, 2) and orientations ``q`` (n, 4) (w, x, y, z) of camera ``intr`` as the
    camera turned by ``roll`` radians sees them on ``canvas``: ((n, 2), canonical (n, 4))."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if roll == 0.0:
        return uv, canonical_quaternion(q)
    return map_pixels(uv, intr, canvas, roll), canonical_quaternion(roll_quaternions(q, roll))
