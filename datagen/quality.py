"""Ferrari-Canny (epsilon) grasp quality and its robust version (Dex-Net 2.0).

Object frame, metres; the origin is the object's centre of mass (as :func:`datagen.mesh.
load_object` prepares it): torques are taken about the origin. Normals are outward.

Contact model: jaw 0 pushes along +axis into contact 0, jaw 1 along -axis into contact 1
(axis = contact 0 -> contact 1). A contact slips, and the grasp scores 0, when its push lies
outside the friction cone (half-angle atan(mu)). Otherwise each contact contributes the
``num_cone_faces`` edges of its linearised friction cone, ``nmag * (n_in + mu * t_k)``
(``nmag`` = push . inward normal), as wrenches ``[f; s * (p x f)]`` with torque scaling
``s``, and with soft fingers also the torsional wrenches ``[0; +-s * pi r^2 mu nmag n_in]``.
The quality is the distance from the origin to the boundary of the convex hull of these
wrenches, 0 when the origin is not inside or the hull is degenerate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import ConvexHull, QhullError

from .grasps import AntipodalGrasps, _unit, find_contacts, tangent_basis


@dataclass(frozen=True)
class QualityParams:
    """Robust Ferrari-Canny settings (metres, radians).

    torque_scaling: None -> derived per object by ``torque_scaling_rule``, see
    :func:`resolve_torque_scaling` (the value used is recorded in the manifest). Perturbations per
    sample: grasp translation / rotation (rotation vector about the grasp centre), object
    translation / rotation (about the centre of mass; applied to the grasp as its inverse),
    friction mu ~ N(friction_coef, sigma_friction) truncated at 0. max_width is the jaw
    opening used to re-find the contacts of perturbed grasps (keep it equal to the
    sampler's). label_threshold: a grasp is positive when its robust quality exceeds it.

    finger_radius (soft-finger torsion radius) bounds the quality: two contacts resist
    torque about their line only through torsion, so the quality is at most
    ``torque_scaling * pi * finger_radius**2 * mu``. With 0.005 m and torque_scaling =
    1 / max radius no grasp of a random_urdfs object reaches label_threshold 0.002; with
    0.01 m (a 2 cm finger pad) about 8% of sampled grasps do (before collision checks).
    """

    friction_coef: float = 0.5
    num_cone_faces: int = 8
    soft_fingers: bool = True
    finger_radius: float = 0.01
    torque_scaling: float | None = None
    torque_scaling_rule: str = "dexnet"  # when torque_scaling is None: "dexnet" | "max_radius"
    num_samples: int = 25
    sigma_grasp_translation: float = 0.005
    sigma_grasp_rotation: float = 0.001
    sigma_object_translation: float = 0.005
    sigma_object_rotation: float = 0.001
    sigma_friction: float = 0.1
    label_threshold: float = 0.002
    max_width: float = 0.05

    def __post_init__(self) -> None:
        if not (np.isfinite(self.friction_coef) and self.friction_coef >= 0):
            raise ValueError(f"friction_coef must be >= 0, got {self.friction_coef}")
        if self.num_cone_faces < 3:
            raise ValueError(f"num_cone_faces must be >= 3, got {self.num_cone_faces}")
        if self.finger_radius < 0:
            raise ValueError(f"finger_radius must be >= 0, got {self.finger_radius}")
        if self.torque_scaling is not None and not (np.isfinite(self.torque_scaling) and self.torque_scaling > 0):
            raise ValueError(f"torque_scaling must be > 0 or None, got {self.torque_scaling}")
        if self.num_samples < 1:
            raise ValueError(f"num_samples must be >= 1, got {self.num_samples}")
        sig = (
            self.sigma_grasp_translation,
            self.sigma_grasp_rotation,
            self.sigma_object_translation,
            self.sigma_object_rotation,
            self.sigma_friction,
        )
        if not all(np.isfinite(s) and s >= 0 for s in sig):
            raise ValueError(f"perturbation sigmas must be >= 0, got {sig}")
        if not (np.isfinite(self.max_width) and self.max_width > 0):
            raise ValueError(f"max_width must be > 0 metres, got {self.max_width}")


def resolve_torque_scaling(mesh: trimesh.Trimesh, params: QualityParams) -> float:
    """The torque scaling used for ``mesh`` (1/metres): ``params.torque_scaling``, or when None
    by ``params.torque_scaling_rule``: "dexnet" = 1 / median of the bounding box's max corner
    (Dex-Net), "max_radius" = 1 / largest vertex distance from the object-frame origin."""
    if params.torque_scaling is not None:
        return float(params.torque_scaling)
    v = np.asarray(mesh.vertices)
    if params.torque_scaling_rule == "dexnet":
        # Dex-Net: 1 / median of the bounding box's max corner (object frame, centre of mass at 0)
        r = float(np.median(v.max(axis=0)))
    elif params.torque_scaling_rule == "max_radius":
        r = float(np.max(np.linalg.norm(v, axis=1)))
    else:
        raise ValueError(f"torque_scaling_rule must be 'dexnet' or 'max_radius', got {params.torque_scaling_rule!r}")
    if not (np.isfinite(r) and r > 0):
        raise ValueError("cannot derive torque scaling: mesh has no extent")
    return 1.0 / r


# --------------------------------------------------------------------------- wrenches


def contact_wrenches(contacts, normals, mu, params: QualityParams, torque_scaling: float, axes=None):
    """Wrench sets of m two-contact grasps.

    contacts, normals (outward): (m, 2, 3); mu: scalar or (m,); axes: (m, 3) jaw axes (jaw 0
    pushes along +axis, jaw 1 along -axis), None -> the contact line (contact 0 -> 1), as for
    point fingers; flat pads touching off the line pass their jaw axis
    (:mod:`datagen.pads`).
    Returns ``(W (m, P, 6), ok (m,) bool)`` with P = 2 * num_cone_faces (+4 with soft
    fingers); ``ok`` is False where the quality is 0 without a hull: contacts coincide, or a
    jaw's push is outside its contact's friction cone (the contact slips).

    The cone's tangent basis is built from the configuration itself (the push's tangential
    part, else the moment arm's, else a fixed axis), so rotating contacts, normals and the
    origin together rotates the wrenches with them and leaves the quality unchanged.
    """
    c = np.asarray(contacts, dtype=np.float64).reshape(-1, 2, 3)
    nrm = _unit(np.asarray(normals, dtype=np.float64).reshape(-1, 2, 3))
    m = len(c)
    mu = np.broadcast_to(np.asarray(mu, dtype=np.float64), (m,))
    d = c[:, 1] - c[:, 0]
    length = np.linalg.norm(d, axis=1)
    ok = length > 1e-12
    if axes is None:
        u = d / np.where(ok, length, 1.0)[:, None]
    else:
        u = _unit(np.asarray(axes, dtype=np.float64).reshape(m, 3))
    push = np.stack([u, -u], axis=1)  # (m, 2, 3)
    n_in = -nrm
    nmag = np.einsum("mij,mij->mi", push, n_in)  # (m, 2)
    tang = push - nmag[..., None] * n_in
    tang_norm = np.linalg.norm(tang, axis=2)
    ok &= np.all(nmag > 0, axis=1)
    ok &= np.all(tang_norm <= mu[:, None] * nmag + 1e-12, axis=1)

    # tangent basis t1, t2 per contact
    ref = tang
    arm = c - np.einsum("mij,mij->mi", c, n_in)[..., None] * n_in
    small = tang_norm < 1e-9
    ref = np.where(small[..., None], arm, ref)
    small = np.linalg.norm(ref, axis=2) < 1e-9
    fb1, _ = tangent_basis(n_in.reshape(-1, 3))
    ref = np.where(small[..., None], fb1.reshape(m, 2, 3), ref)
    t1 = _unit(ref - np.einsum("mij,mij->mi", ref, n_in)[..., None] * n_in)
    t2 = np.cross(n_in, t1)

    k = params.num_cone_faces
    th = 2 * np.pi * np.arange(k) / k
    # forces (m, 2, k, 3)
    dirs = np.cos(th)[None, None, :, None] * t1[:, :, None] + np.sin(th)[None, None, :, None] * t2[:, :, None]
    f = nmag[..., None, None] * (n_in[:, :, None] + mu[:, None, None, None] * dirs)
    tau = torque_scaling * np.cross(c[:, :, None], f)
    W = np.concatenate([f, tau], axis=3).reshape(m, 2 * k, 6)
    if params.soft_fingers:
        g = (torque_scaling * np.pi * params.finger_radius**2) * (mu[:, None] * nmag)[..., None] * n_in  # (m, 2, 3)
        tors = np.zeros((m, 4, 6))
        tors[:, :2, 3:] = g
        tors[:, 2:, 3:] = -g
        W = np.concatenate([W, tors], axis=1)
    return W, ok


def _full_rank(W: np.ndarray) -> np.ndarray:
    """(m,) bool: the wrench sets W (m, P, 6) span all 6 dimensions."""
    sv = np.linalg.svd(W, compute_uv=False)
    return sv[..., -1] > 1e-9 * np.maximum(sv[..., 0], 1e-300)


def _hull_distance(W: np.ndarray) -> float:
    """Distance from the origin to the boundary of conv(W) (P, 6), 0 if outside."""
    try:
        hull = ConvexHull(W, qhull_options="QJ")  # joggled input: always simplicial, fastest
    except (QhullError, ValueError):
        return 0.0
    q = -float(np.max(hull.equations[:, -1]))  # equations: unit normals, n.x + b <= 0 inside
    return q if q > 1e-12 else 0.0


def hull_quality(W: np.ndarray) -> float:
    """Distance from the origin to the boundary of conv(W) (W: (P, 6) wrenches); 0 if
    the origin is outside or the hull is degenerate (not full-dimensional)."""
    W = np.asarray(W, dtype=np.float64)
    return _hull_distance(W) if _full_rank(W[None])[0] else 0.0


def ferrari_canny_batch(contacts, normals, mu, params: QualityParams, torque_scaling: float, axes=None) -> np.ndarray:
    """Ferrari-Canny quality (m,) of m two-contact grasps (see :func:`contact_wrenches`);
    a convex hull is built only for grasps whose contacts do not slip."""
    W, ok = contact_wrenches(contacts, normals, mu, params, torque_scaling, axes)
    q = np.zeros(len(W))
    idx = np.flatnonzero(ok)
    if len(idx):
        idx = idx[_full_rank(W[idx])]
    for i in idx:
        q[i] = _hull_distance(W[i])
    return q


def ferrari_canny(contacts, normals, mu: float, params: QualityParams, torque_scaling: float) -> float:
    """Ferrari-Canny quality of one grasp: contacts (2, 3), outward normals (2, 3) in the
    object frame (origin = centre of mass), friction ``mu``. 0 if the origin is outside
    the wrench hull."""
    c = np.asarray(contacts, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    if c.shape != (2, 3) or n.shape != (2, 3):
        raise ValueError(f"contacts and normals must be (2, 3), got {c.shape} and {n.shape}")
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(n))):
        raise ValueError("contacts and normals must be finite")
    return float(ferrari_canny_batch(c[None], n[None], float(mu), params, torque_scaling)[0])


# --------------------------------------------------------------------------- robust


def rotation_matrices(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrices (n, 3, 3) of rotation vectors (n, 3) (axis * angle, radians)."""
    rv = np.asarray(rotvec, dtype=np.float64).reshape(-1, 3)
    th = np.linalg.norm(rv, axis=1)
    k = rv / np.where(th > 0, th, 1.0)[:, None]
    K = np.zeros((len(rv), 3, 3))
    K[:, 0, 1], K[:, 0, 2] = -k[:, 2], k[:, 1]
    K[:, 1, 0], K[:, 1, 2] = k[:, 2], -k[:, 0]
    K[:, 2, 0], K[:, 2, 1] = -k[:, 1], k[:, 0]
    s, c = np.sin(th)[:, None, None], np.cos(th)[:, None, None]
    return np.eye(3)[None] + s * K + (1 - c) * (K @ K)


def perturb_grasps(centers, axes, params: QualityParams, rng: np.random.Generator):
    """``params.num_samples`` perturbed copies of each grasp, in the object frame.

    Returns ``(centers (n, K, 3), axes (n, K, 3), mu (n, K))``: the grasp is translated
    and rotated about its centre, then expressed in the frame of a randomly displaced
    object (inverse of the object perturbation about the centre of mass); mu is drawn from
    N(friction_coef, sigma_friction) truncated at 0.
    """
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    a = np.asarray(axes, dtype=np.float64).reshape(-1, 3)
    n, K = len(c), params.num_samples
    m = n * K
    cg = np.repeat(c, K, axis=0) + params.sigma_grasp_translation * rng.standard_normal((m, 3))
    Rg = rotation_matrices(params.sigma_grasp_rotation * rng.standard_normal((m, 3)))
    ag = np.einsum("mij,mj->mi", Rg, np.repeat(a, K, axis=0))
    Ro = rotation_matrices(params.sigma_object_rotation * rng.standard_normal((m, 3)))
    to = params.sigma_object_translation * rng.standard_normal((m, 3))
    # grasp in the displaced object's frame: R_o^T (x - t_o)
    cp = np.einsum("mji,mj->mi", Ro, cg - to)
    ap = _unit(np.einsum("mji,mj->mi", Ro, ag))
    mu = np.maximum(params.friction_coef + params.sigma_friction * rng.standard_normal(m), 0.0)
    return cp.reshape(n, K, 3), ap.reshape(n, K, 3), mu.reshape(n, K)


def robust_ferrari_canny_samples(
    mesh: trimesh.Trimesh, grasps: AntipodalGrasps, params: QualityParams, rng: np.random.Generator
) -> np.ndarray:
    """Ferrari-Canny quality (n, K) of each grasp under K = ``params.num_samples``
    perturbations; contacts of perturbed grasps are re-found by closing the jaws on the
    mesh along the perturbed axis (one batched ray query), 0 where they find none."""
    n, K = len(grasps), params.num_samples
    if n == 0:
        return np.zeros((0, K))
    scaling = resolve_torque_scaling(mesh, params)
    cp, ap, mu = perturb_grasps(grasps.centers, grasps.axes, params, rng)
    ok, contacts, normals = find_contacts(mesh, cp.reshape(-1, 3), ap.reshape(-1, 3), params.max_width)
    q = np.zeros(n * K)
    if ok.any():
        q[ok] = ferrari_canny_batch(contacts[ok], normals[ok], mu.reshape(-1)[ok], params, scaling)
    return q.reshape(n, K)


def robust_ferrari_canny(
    mesh: trimesh.Trimesh, grasps: AntipodalGrasps, params: QualityParams, rng: np.random.Generator
) -> np.ndarray:
    """Robust Ferrari-Canny quality (n,): mean over ``params.num_samples`` perturbations of
    grasp pose, object pose and friction (see :func:`robust_ferrari_canny_samples`).
    ``mesh`` is in the object frame (centre of mass at the origin)."""
    return robust_ferrari_canny_samples(mesh, grasps, params, rng).mean(axis=1)
