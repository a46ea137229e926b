"""Parallel-jaw gripper model and grasp frames (SPEC sections 1 and 2.5).

Grasp frame ``T^g``: origin at the tool centre point (TCP, midway between the contacts),
x-axis along the jaw axis (contact 0 -> contact 1), z-axis the approach direction (the gripper
moves along +z to reach the grasp), y = z x x. Metres and radians throughout.

The gripper is three boxes in the grasp frame, opened to ``max_width``: two fingers whose
inner faces sit at x = +-max_width / 2 and whose tips reach ``tip_offset`` past the TCP
along +z, and a palm box behind the fingers. Its straight approach starts
``approach_distance`` back along -z; the volume swept on the way is the same boxes extended
back along -z by that distance (:func:`gripper_boxes` with ``swept=True``).
"""

from __future__ import annotations

from math import pi

import numpy as np

# The dimensions and boxes live in vgq (shared with planning, which must not import trimesh).
from vgq.gripper import GripperGeometry, box_corners, gripper_boxes  # noqa: F401  (re-exported)


def gripper_mesh(geom: GripperGeometry, swept: bool = False, T: np.ndarray | None = None):
    """The gripper boxes as one ``trimesh.Trimesh`` (grasp frame, or moved by ``T`` (4, 4)),
    for visualisation and collision models."""
    import trimesh

    centres, half = gripper_boxes(geom, swept=swept)
    parts = [trimesh.creation.box(extents=2 * h, transform=_translation(c)) for c, h in zip(centres, half)]
    mesh = trimesh.util.concatenate(parts)
    if T is not None:
        mesh.apply_transform(np.asarray(T, dtype=np.float64))
    return mesh


def _translation(t) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = t
    return T


def as_frames(T: np.ndarray, name: str) -> np.ndarray:
    """``T`` as float64 frames (n, 4, 4) (a single (4, 4) becomes n = 1); ValueError naming
    ``name`` for a wrong shape or non-finite entries."""
    T = np.asarray(T, dtype=np.float64)
    if T.ndim == 2:
        T = T[None]
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"{name} must have shape (n, 4, 4), got {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError(f"{name} has non-finite entries")
    return T


def _angles(omega, n: int) -> np.ndarray:
    """``omega`` as (n,) float64 angles: a scalar is repeated; must be finite."""
    om = np.asarray(omega, dtype=np.float64)
    om = np.full(n, float(om)) if om.ndim == 0 else om.reshape(-1).copy()
    if om.shape[0] != n:
        raise ValueError(f"omega must be a scalar or {n} angles, got shape {np.shape(omega)}")
    if not np.all(np.isfinite(om)):
        raise ValueError("omega must be finite")
    return om


def rotation_about_x(angle) -> np.ndarray:
    """Rotation matrices (n, 3, 3) about the x-axis by ``angle`` (n,) radians."""
    a = np.asarray(angle, dtype=np.float64).reshape(-1)
    c, s = np.cos(a), np.sin(a)
    R = np.zeros((a.shape[0], 3, 3))
    R[:, 0, 0] = 1.0
    R[:, 1, 1], R[:, 1, 2] = c, -s
    R[:, 2, 1], R[:, 2, 2] = s, c
    return R


def grasp_frames(centers, axes, omega) -> np.ndarray:
    """Grasp frames ``T_object_grasp`` (n, 4, 4) from TCPs (n, 3), jaw axes (n, 3) and
    rotations ``omega`` (n,) radians about the jaw axis.

    At omega = 0 the approach axis z is the deterministic unit vector orthogonal to x built
    from the basis vector e_k with the smallest |x_k| (z0 = normalise(e_k - (e_k . x) x));
    omega rotates the frame about its own x-axis: R = [x, y0, z0] @ Rx(omega).
    """
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    x = np.asarray(axes, dtype=np.float64).reshape(-1, 3)
    if c.shape[0] != x.shape[0]:
        raise ValueError(f"centers ({c.shape[0]}) and axes ({x.shape[0]}) must have the same length")
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(x))):
        raise ValueError("grasp centers and axes must be finite")
    om = _angles(omega, x.shape[0])
    norm = np.linalg.norm(x, axis=1)
    if np.any(norm < 1e-9):
        raise ValueError("grasp axes must be non-zero vectors")
    x = x / norm[:, None]
    k = np.argmin(np.abs(x), axis=1)
    ref = np.eye(3)[k]
    z0 = ref - np.sum(ref * x, axis=1, keepdims=True) * x
    z0 /= np.linalg.norm(z0, axis=1, keepdims=True)
    y0 = np.cross(z0, x)
    R0 = np.stack([x, y0, z0], axis=2)
    T = np.zeros((x.shape[0], 4, 4))
    T[:, :3, :3] = R0 @ rotation_about_x(om)
    T[:, :3, 3] = c
    T[:, 3, 3] = 1.0
    return T


def beta_angles(T_world_grasp) -> np.ndarray:
    """Angles (n,) radians between each grasp's approach axis (z) and the downward table
    normal (0, 0, -1): 0 = top grasp, > pi/2 approaches from under the table."""
    T = as_frames(T_world_grasp, "T_world_grasp")
    return np.arccos(np.clip(-T[:, 2, 2], -1.0, 1.0))


def align_to_table(T_world_grasp, rng: np.random.Generator | None = None, omega=None):
    """Random rotation about each grasp's x-axis, then the SPEC 2.5 flip.

    Rotates each frame (n, 4, 4) about its own x-axis by ``omega`` (n,) radians (drawn
    uniformly from [0, 2 pi) with ``rng`` when not given); where the approach then has
    beta > pi/2 (from under the table) rotates once more by pi about x, which maps beta to
    pi - beta. Returns ``(T_world_grasp' (n, 4, 4), omega' (n,) in [0, 2 pi), beta' (n,))``
    where omega' is the total rotation applied relative to the input frames (omega, plus pi
    where flipped). Pass frames built with omega = 0 (:func:`grasp_frames`) to get omega'
    relative to the deterministic base frame.
    """
    T = as_frames(T_world_grasp, "T_world_grasp")
    n = T.shape[0]
    if omega is None:
        if rng is None:
            raise ValueError("align_to_table needs either rng or omega")
        om = rng.uniform(0.0, 2.0 * pi, size=n)
    else:
        om = _angles(omega, n)
    R = T[:, :3, :3] @ rotation_about_x(om)
    flip = R[:, 2, 2] > 0.0  # approach z has an upward component: beta > pi/2
    R[flip, :, 1:] *= -1.0  # rotation by pi about x: y -> -y, z -> -z
    om = np.mod(om + np.where(flip, pi, 0.0), 2.0 * pi)
    out = T.copy()
    out[:, :3, :3] = R
    return out, om, beta_angles(out)
