"""Grasp poses as the network sees them (SPEC sections 1 and 2.6).

Input grasp frames are in the world frame (table z = 0, z up; grasp x = jaw axis, z =
approach); the camera is OpenCV (x right, y down, z along the principal ray). Output: the
projected TCP pixel (u = column, v = row), its camera-frame depth z (metres), the grasp
orientation in the camera frame as a canonical unit quaternion (w, x, y, z), w >= 0
(``vgq.pose``), and the angles beta, psi, jaw_angle (radians).
"""

from __future__ import annotations

import numpy as np

from vgq.camera import DEFAULT_INTRINSICS, Intrinsics, project
from vgq.pose import quaternion_from_matrix
from vgq.turns import jaw_angles  # noqa: F401  (the one definition; datagen's name for it)

from .gripper import as_frames, beta_angles


def psi_angles(R_camera_grasp: np.ndarray) -> np.ndarray:
    """Angles (n,) radians between each grasp's approach axis (column 2 of the camera-frame
    rotation (n, 3, 3)) and the camera principal ray (0, 0, 1): >= pi/2 approaches from
    behind the object as the camera sees it."""
    return np.arccos(np.clip(np.asarray(R_camera_grasp)[:, 2, 2], -1.0, 1.0))


def project_grasps(
    T_world_grasp: np.ndarray, T_world_camera: np.ndarray, intr: Intrinsics = DEFAULT_INTRINSICS
) -> dict[str, np.ndarray]:
    """Project grasp frames (n, 4, 4) into the camera ``T_world_camera`` (4, 4).

    Returns a dict of float64 arrays: ``u``, ``v`` (n,) pixels of the TCP; ``z`` (n,) TCP
    depth, metres; ``q`` (n, 4) canonical (w, x, y, z) rotation camera <- grasp; ``beta``,
    ``psi``, ``jaw_angle`` (n,) radians; and ``in_image`` (n,) bool: z > 0 and (u, v)
    within the image (pixel centres at integers, so u in [-0.5, W - 0.5)).
    """
    T = as_frames(T_world_grasp, "T_world_grasp")
    C = np.asarray(T_world_camera, dtype=np.float64)
    if C.shape != (4, 4) or not np.all(np.isfinite(C)):
        raise ValueError(f"T_world_camera must be a finite (4, 4) matrix, got shape {C.shape}")
    Rc, tc = C[:3, :3], C[:3, 3]
    R = np.einsum("ji,njk->nik", Rc, T[:, :3, :3])  # Rc^T @ R_world_grasp
    p = np.einsum("ji,nj->ni", Rc, T[:, :3, 3] - tc)
    uvz = project(p, intr)
    u, v, z = uvz[:, 0], uvz[:, 1], uvz[:, 2]
    in_image = (z > 0) & (u >= -0.5) & (u < intr.width - 0.5) & (v >= -0.5) & (v < intr.height - 0.5)
    return {
        "u": u,
        "v": v,
        "z": z,
        "q": quaternion_from_matrix(R) if len(R) else np.zeros((0, 4)),
        "beta": beta_angles(T),
        "psi": psi_angles(R),
        "jaw_angle": jaw_angles(p, R[:, :, 0], intr),
        "in_image": in_image,
    }
