"""Antipodal parallel-jaw grasp sampling (Dex-Net 2.0 style), vectorised.

All arrays are in the object frame, metres. Surface normals are outward. A grasp is the
line of action of the jaws: ``axes`` points from contact 0 to contact 1, ``centers`` is
the midpoint of the two contacts. Contacts are where the jaws, opened to ``max_width``
and centred on the grasp, first touch the surface when they close along the axis
(:func:`find_contacts`, shared with the quality metric).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh


@dataclass(frozen=True)
class AntipodalParams:
    """Sampler settings (metres, friction coefficient mu).

    num_samples: target number of grasps; at most ``num_samples * max_attempts_factor``
    surface points are tried. dedupe_distance / dedupe_axis_weight: two grasps are the same
    when ``|c1 - c2| + dedupe_axis_weight * (2 / pi) * angle(a1, a2) < dedupe_distance``
    (Dex-Net's grasp distance; the axis angle ignores the axis sign).
    """

    max_width: float = 0.05
    min_contact_distance: float = 0.0025
    friction_coef: float = 0.5
    num_cone_faces: int = 8
    num_samples: int = 100
    max_attempts_factor: int = 20
    dedupe_distance: float = 0.0025
    dedupe_axis_weight: float = 0.05

    def __post_init__(self) -> None:
        if not (np.isfinite(self.max_width) and self.max_width > 0):
            raise ValueError(f"max_width must be > 0 metres, got {self.max_width}")
        if not (0 <= self.min_contact_distance < self.max_width):
            raise ValueError(
                f"min_contact_distance must be in [0, max_width={self.max_width}), got {self.min_contact_distance}"
            )
        if not (np.isfinite(self.friction_coef) and self.friction_coef >= 0):
            raise ValueError(f"friction_coef must be >= 0, got {self.friction_coef}")
        if self.num_cone_faces < 3:
            raise ValueError(f"num_cone_faces must be >= 3, got {self.num_cone_faces}")
        if self.num_samples < 1 or self.max_attempts_factor < 1:
            raise ValueError("num_samples and max_attempts_factor must be >= 1")
        if self.dedupe_distance < 0 or self.dedupe_axis_weight < 0:
            raise ValueError("dedupe_distance and dedupe_axis_weight must be >= 0")


@dataclass
class AntipodalGrasps:
    """n grasps in the object frame (metres)."""

    centers: np.ndarray  # (n, 3) TCP = midpoint of the two contacts
    axes: np.ndarray  # (n, 3) unit jaw axis, contact 0 -> contact 1 (grasp frame x-axis)
    contacts: np.ndarray  # (n, 2, 3)
    normals: np.ndarray  # (n, 2, 3) outward surface normals at the contacts
    widths: np.ndarray  # (n,) contact distance

    def __len__(self) -> int:
        return len(self.centers)

    def __getitem__(self, idx) -> AntipodalGrasps:
        """Subset by index array, mask or slice."""
        return AntipodalGrasps(
            self.centers[idx], self.axes[idx], self.contacts[idx], self.normals[idx], self.widths[idx]
        )

    @classmethod
    def empty(cls) -> AntipodalGrasps:
        return cls(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 2, 3)), np.zeros((0, 2, 3)), np.zeros(0))


# --------------------------------------------------------------------------- ray casting


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


def cast_first(mesh: trimesh.Trimesh, origins: np.ndarray, directions: np.ndarray):
    """First surface hit of each ray (embree when available).

    Returns ``(face (n,) int, -1 for a miss; t (n,) distance along the unit direction,
    inf for a miss)``. ``t`` is recomputed in float64 from the hit face's plane, so
    ``origins + t * directions`` lies on the surface to float64 precision.
    """
    origins = np.ascontiguousarray(origins, dtype=np.float64).reshape(-1, 3)
    directions = np.ascontiguousarray(directions, dtype=np.float64).reshape(-1, 3)
    t = np.full(len(origins), np.inf)
    if len(origins) == 0:
        return np.zeros(0, dtype=np.int64), t
    face = np.asarray(mesh.ray.intersects_first(ray_origins=origins, ray_directions=directions), dtype=np.int64)
    hit = face >= 0
    if hit.any():
        n = mesh.face_normals[face[hit]]
        v0 = mesh.vertices[mesh.faces[face[hit], 0]]
        denom = np.einsum("ij,ij->i", n, directions[hit])
        with np.errstate(divide="ignore", invalid="ignore"):
            th = np.einsum("ij,ij->i", n, v0 - origins[hit]) / denom
        ok = np.isfinite(th)
        th = np.where(ok, np.maximum(th, 0.0), np.inf)
        t[hit] = th
        face[np.flatnonzero(hit)[~ok]] = -1
    return face, t


def find_contacts(mesh: trimesh.Trimesh, centers: np.ndarray, axes: np.ndarray, max_width: float):
    """Close parallel jaws on the mesh along each grasp line.

    Jaw 0 starts at ``center - max_width / 2 * axis`` and moves along +axis, jaw 1 starts
    at ``center + max_width / 2 * axis`` and moves along -axis; each stops at its first
    surface hit. ``axes`` must be unit vectors (n, 3).

    Returns ``(ok (n,) bool, contacts (n, 2, 3), normals (n, 2, 3) outward)``. A grasp is
    not ok when a jaw misses, when a jaw starts inside the object (its first hit is a face
    it leaves), or when the contacts do not fit within the opening.
    """
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    axes = np.asarray(axes, dtype=np.float64).reshape(-1, 3)
    n = len(centers)
    h = 0.5 * max_width
    origins = np.concatenate([centers - h * axes, centers + h * axes])
    dirs = np.concatenate([axes, -axes])
    face, t = cast_first(mesh, origins, dirs)
    f0, f1 = face[:n], face[n:]
    t0, t1 = t[:n], t[n:]
    ok = (f0 >= 0) & (f1 >= 0) & (t0 + t1 <= max_width)
    normals = np.zeros((n, 2, 3))
    normals[ok, 0] = mesh.face_normals[f0[ok]]
    normals[ok, 1] = mesh.face_normals[f1[ok]]
    # each jaw must meet a face that looks at it (outward normal against its motion)
    ok &= np.einsum("ij,ij->i", normals[:, 0], axes) < 0
    ok &= np.einsum("ij,ij->i", normals[:, 1], axes) > 0
    contacts = np.zeros((n, 2, 3))
    contacts[:, 0] = origins[:n] + np.where(ok, t0, 0.0)[:, None] * axes
    contacts[:, 1] = origins[n:] - np.where(ok, t1, 0.0)[:, None] * axes
    return ok, contacts, normals


def in_friction_cones(axes: np.ndarray, normals: np.ndarray, friction_coef) -> np.ndarray:
    """(n,) bool: the line of action lies inside both (circular) friction cones.

    Jaw 0 pushes along +axis into contact 0, jaw 1 along -axis into contact 1; the
    push must be within ``atan(mu)`` of each inward normal (force closure for two contacts).
    """
    axes = np.asarray(axes, dtype=np.float64).reshape(-1, 3)
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 2, 3)
    cos_lim = np.cos(np.arctan(np.asarray(friction_coef, dtype=np.float64)))
    c0 = -np.einsum("ij,ij->i", axes, normals[:, 0])  # cos(push, inward normal 0)
    c1 = np.einsum("ij,ij->i", axes, normals[:, 1])
    return (c0 >= cos_lim - 1e-12) & (c1 >= cos_lim - 1e-12) & (c0 > 0) & (c1 > 0)


# --------------------------------------------------------------------------- sampling


def sample_surface(mesh: trimesh.Trimesh, n: int, rng: np.random.Generator):
    """n area-uniform surface points. Returns ``(points (n, 3), face index (n,))``."""
    area = np.asarray(mesh.area_faces, dtype=np.float64)
    cdf = np.cumsum(area)
    face = np.searchsorted(cdf, rng.random(n) * cdf[-1], side="right")
    face = np.minimum(face, len(area) - 1)
    r = rng.random((n, 2))
    flip = r.sum(axis=1) > 1
    r[flip] = 1 - r[flip]
    tri = mesh.triangles[face]
    pts = tri[:, 0] + r[:, :1] * (tri[:, 1] - tri[:, 0]) + r[:, 1:] * (tri[:, 2] - tri[:, 0])
    return pts, face


def tangent_basis(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (n, 3) each, orthogonal to the unit ``normals`` (n, 3)."""
    ref = np.where(np.abs(normals[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    t1 = _unit(np.cross(normals, ref))
    t2 = np.cross(normals, t1)
    return t1, t2


def sample_in_cone(inward: np.ndarray, mu: float, num_faces: int, rng: np.random.Generator) -> np.ndarray:
    """Unit directions (n, 3), uniform over the (randomly rotated) ``num_faces``-sided
    linearised friction cone of half-angle ``atan(mu)`` around each unit ``inward`` normal."""
    n = len(inward)
    t1, t2 = tangent_basis(inward)
    # uniform point in a regular polygon inscribed in the circle of radius mu
    k = rng.integers(0, num_faces, n)
    r = rng.random((n, 2))
    flip = r.sum(axis=1) > 1
    r[flip] = 1 - r[flip]
    rot = rng.random(n) * 2 * np.pi
    a0 = rot + 2 * np.pi * k / num_faces
    a1 = a0 + 2 * np.pi / num_faces
    x = mu * (r[:, 0] * np.cos(a0) + r[:, 1] * np.cos(a1))
    y = mu * (r[:, 0] * np.sin(a0) + r[:, 1] * np.sin(a1))
    return _unit(inward + x[:, None] * t1 + y[:, None] * t2)


def _candidates(mesh: trimesh.Trimesh, m: int, params: AntipodalParams, rng: np.random.Generator) -> AntipodalGrasps:
    """Sample m surface points and return the valid antipodal grasps they lead to."""
    p0, f0 = sample_surface(mesh, m, rng)
    inward = -mesh.face_normals[f0]
    axes = sample_in_cone(inward, params.friction_coef, params.num_cone_faces, rng)
    # opposite contact: where the line through p0 leaves the solid
    eps = 1e-6 * max(float(mesh.scale), 1e-3)
    face, t = cast_first(mesh, p0 + eps * axes, axes)
    t = t + eps
    ok = (face >= 0) & (t <= params.max_width) & (t >= params.min_contact_distance)
    ok[ok] &= np.einsum("ij,ij->i", mesh.face_normals[face[ok]], axes[ok]) > 0  # an exit face
    if not ok.any():
        return AntipodalGrasps.empty()
    axes = axes[ok]
    centers = p0[ok] + 0.5 * t[ok, None] * axes
    # the contacts real jaws find when they close on this line
    ok2, contacts, normals = find_contacts(mesh, centers, axes, params.max_width)
    widths = np.linalg.norm(contacts[:, 1] - contacts[:, 0], axis=1)
    ok2 &= widths >= params.min_contact_distance
    ok2 &= in_friction_cones(axes, normals, params.friction_coef)
    contacts, normals, axes, widths = contacts[ok2], normals[ok2], axes[ok2], widths[ok2]
    centers = 0.5 * (contacts[:, 0] + contacts[:, 1])
    return AntipodalGrasps(centers, axes, contacts, normals, widths)


def dedupe(grasps: AntipodalGrasps, distance: float, axis_weight: float, limit: int | None = None) -> np.ndarray:
    """Indices of grasps kept by a greedy pass (in order) that drops any grasp closer than
    ``distance`` to a kept one (Dex-Net grasp distance, see :class:`AntipodalParams`);
    stops after ``limit`` kept grasps."""
    n = len(grasps)
    if n == 0 or distance <= 0:
        return np.arange(n if limit is None else min(n, limit))
    kept: list[int] = []
    c, a = grasps.centers, grasps.axes
    for i in range(n):
        if kept:
            k = np.asarray(kept)
            dc = np.linalg.norm(c[k] - c[i], axis=1)
            cosang = np.clip(np.abs(a[k] @ a[i]), 0.0, 1.0)
            d = dc + axis_weight * (2 / np.pi) * np.arccos(cosang)
            if d.min() < distance:
                continue
        kept.append(i)
        if limit is not None and len(kept) >= limit:
            break
    return np.asarray(kept, dtype=np.int64)


def _concat(parts: list[AntipodalGrasps]) -> AntipodalGrasps:
    if not parts:
        return AntipodalGrasps.empty()
    return AntipodalGrasps(
        np.concatenate([g.centers for g in parts]),
        np.concatenate([g.axes for g in parts]),
        np.concatenate([g.contacts for g in parts]),
        np.concatenate([g.normals for g in parts]),
        np.concatenate([g.widths for g in parts]),
    )


def sample_antipodal_grasps(
    mesh: trimesh.Trimesh, params: AntipodalParams, rng: np.random.Generator
) -> AntipodalGrasps:
    """Up to ``params.num_samples`` distinct antipodal grasps on a watertight mesh.

    Surface points are sampled area-uniformly in batches; for each, a jaw axis is drawn
    inside the friction cone of the inward normal, the opposite contact is found by ray
    casting, the jaws are closed along that line (:func:`find_contacts`) and the grasp is
    kept when the contacts are at least ``min_contact_distance`` apart, fit within
    ``max_width`` and the line lies in both friction cones. Near-duplicates are removed.
    Returns fewer grasps (possibly none) when the attempt budget runs out.
    """
    if len(mesh.faces) == 0 or not float(mesh.area) > 0:
        raise ValueError("mesh has no faces with area")
    target = params.num_samples
    budget = params.num_samples * params.max_attempts_factor
    found: list[AntipodalGrasps] = []
    n_valid = 0
    batch = min(budget, max(4 * target, 64))
    used = 0
    while used < budget:
        m = min(batch, budget - used)
        g = _candidates(mesh, m, params, rng)
        used += m
        found.append(g)
        n_valid += len(g)
        if n_valid >= 2 * target:  # enough raw candidates: try dedupe
            allg = _concat(found)
            keep = dedupe(allg, params.dedupe_distance, params.dedupe_axis_weight, limit=target)
            if len(keep) >= target:
                return allg[keep]
        # grow the next batch by the observed yield
        rate = max(n_valid / used, 1.0 / params.max_attempts_factor)
        batch = int(np.clip(2 * (target - n_valid / 2) / rate, 64, budget))
    allg = _concat(found)
    keep = dedupe(allg, params.dedupe_distance, params.dedupe_axis_weight, limit=target)
    return allg[keep]
