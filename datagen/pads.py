"""Pad contacts: where the flat finger pads first touch the object when the jaws close.

Grasp frame as in :mod:`datagen.gripper` (x = jaw axis, z = approach, origin = TCP);
object frame with the centre of mass at the origin; metres.

A pad is the inner face of a finger: ``finger_width`` along y (centred) by
``finger_length`` along z, from the fingertip at z = ``tip_offset`` back to the palm. Closing
sweeps the pads along x from x = -+max_width / 2 towards the TCP, so each pad first touches
the surface where it is extreme in x *within the pad's footprint* (the prism
|y| <= finger_width / 2, tip_offset - finger_length <= z <= tip_offset), not where the grasp
line meets it (:func:`datagen.grasps.find_contacts`). The mesh is clipped to that prism
exactly (triangles sliced by its four side planes); jaw 0 touches at the smallest x, jaw 1
at the largest. The contact is the centre of the touching patch: the area-weighted
centroid of the clipped triangles lying within ``tol`` of the extreme x (a face flat against
the pad), else the centre of the bounding box of the clipped vertices within ``tol`` (the
midpoint of an edge, or the corner itself). The
contact normal is the pad's: -x at jaw 0 and +x at jaw 1 (outward from the object), and
the jaws push along +-x.
"""

from __future__ import annotations

import numpy as np
import trimesh
from trimesh.intersections import slice_faces_plane

from .gripper import GripperGeometry


def _clip_to_prism(v: np.ndarray, f: np.ndarray, half_y: float, z0: float, z1: float):
    """Triangles (vertices, faces) of the mesh (grasp frame) clipped to |y| <= half_y, z0 <= z <= z1."""
    planes = (
        ((0.0, -1.0, 0.0), (0.0, half_y, 0.0)),
        ((0.0, 1.0, 0.0), (0.0, -half_y, 0.0)),
        ((0.0, 0.0, 1.0), (0.0, 0.0, z0)),
        ((0.0, 0.0, -1.0), (0.0, 0.0, z1)),
    )
    for normal, origin in planes:
        if len(f) == 0:
            break
        v, f = slice_faces_plane(v, f, np.asarray(normal), np.asarray(origin))[:2]
    return np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64)


def _patch_centre(v: np.ndarray, f: np.ndarray, x: np.ndarray, extreme: float, tol: float) -> np.ndarray:
    near_v = np.abs(x - extreme) <= tol
    tri_near = near_v[f].all(axis=1)
    if tri_near.any():
        tri = v[f[tri_near]]
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        if area.sum() > 1e-12:
            return (tri.mean(axis=1) * area[:, None]).sum(axis=0) / area.sum()
    used = np.zeros(len(v), bool)
    used[f.reshape(-1)] = True
    pts = v[near_v & used]
    return 0.5 * (pts.min(axis=0) + pts.max(axis=0))  # an edge's midpoint, or the corner itself


def pad_contacts(mesh: trimesh.Trimesh, T_object_grasp: np.ndarray, gripper: GripperGeometry, tol: float = 1e-4):
    """Pad contacts of n grasps ``T_object_grasp`` (n, 4, 4) on ``mesh`` (object frame).

    Returns ``(ok (n,) bool, contacts (n, 2, 3), normals (n, 2, 3) outward, object frame)``.
    A grasp is not ok when the pads' footprint misses the object or when the object reaches
    beyond the open jaws within it (a finger would land on it, not close on it).
    """
    T = np.asarray(T_object_grasp, dtype=np.float64).reshape(-1, 4, 4)
    n = len(T)
    V = np.asarray(mesh.vertices, dtype=np.float64)
    F = np.asarray(mesh.faces, dtype=np.int64)
    hy = gripper.finger_width / 2
    z1 = gripper.tip_offset
    z0 = gripper.tip_offset - gripper.finger_length
    hw = gripper.max_width / 2
    ok = np.zeros(n, bool)
    contacts = np.zeros((n, 2, 3))
    normals = np.zeros((n, 2, 3))
    for i in range(n):
        R, c = T[i, :3, :3], T[i, :3, 3]
        vg = (V - c) @ R  # R^T (v - c): grasp frame
        tri = vg[F]
        lo, hi = tri.min(axis=1), tri.max(axis=1)
        cand = (hi[:, 1] >= -hy) & (lo[:, 1] <= hy) & (hi[:, 2] >= z0) & (lo[:, 2] <= z1)
        if not cand.any():
            continue
        fv, ff = _clip_to_prism(vg, F[cand], hy, z0, z1)
        if len(ff) == 0:
            continue
        used = np.unique(ff)
        x = fv[:, 0]
        xmin, xmax = float(x[used].min()), float(x[used].max())
        if xmin < -hw - 1e-9 or xmax > hw + 1e-9:
            continue
        p0 = _patch_centre(fv, ff, x, xmin, tol)
        p1 = _patch_centre(fv, ff, x, xmax, tol)
        contacts[i, 0] = R @ p0 + c
        contacts[i, 1] = R @ p1 + c
        normals[i, 0] = -R[:, 0]
        normals[i, 1] = R[:, 0]
        ok[i] = True
    return ok, contacts, normals


def pad_quality(
    mesh: trimesh.Trimesh,
    T_object_grasp: np.ndarray,
    gripper: GripperGeometry,
    params,
    torque_scaling: float,
    mu: float | None = None,
):
    """Ferrari-Canny quality (n,) at the pad contacts (pushes along the jaw axis), 0 where
    :func:`pad_contacts` finds none; also returns the contacts ``(q, ok, contacts)``."""
    from .quality import ferrari_canny_batch

    T = np.asarray(T_object_grasp, dtype=np.float64).reshape(-1, 4, 4)
    ok, contacts, normals = pad_contacts(mesh, T, gripper)
    q = np.zeros(len(T))
    if ok.any():
        m = np.broadcast_to(np.asarray(params.friction_coef if mu is None else mu, np.float64), (len(T),))
        q[ok] = ferrari_canny_batch(contacts[ok], normals[ok], m[ok], params, torque_scaling, axes=T[ok, :3, 0])
    return q, ok, contacts


def robust_pad_quality(
    mesh: trimesh.Trimesh,
    T_object_grasp: np.ndarray,
    gripper: GripperGeometry,
    params,
    torque_scaling: float,
    noise,
    rng: np.random.Generator,
):
    """Pad quality under execution noise: the mean over ``noise.num_samples`` perturbed poses
    (translation N(0, noise.sigma_translation) per axis, rotation vector N(0, noise.sigma_rotation)
    about the TCP; :func:`datagen.collision.perturb_frames`) and friction N(friction_coef,
    sigma_friction). Returns ``(mean quality (n,), fraction of poses whose pads close on the
    object (n,))``."""
    from .collision import perturb_frames

    T = np.asarray(T_object_grasp, dtype=np.float64).reshape(-1, 4, 4)
    n, K = len(T), noise.num_samples
    if n == 0:
        return np.zeros(0), np.zeros(0)
    Tp = perturb_frames(T, noise, rng).reshape(-1, 4, 4)
    mu = np.maximum(params.friction_coef + params.sigma_friction * rng.standard_normal(n * K), 0.0)
    q, ok, _ = pad_quality(mesh, Tp, gripper, params, torque_scaling, mu=mu)
    return q.reshape(n, K).mean(axis=1), ok.reshape(n, K).mean(axis=1)
