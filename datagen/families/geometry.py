"""Shared geometry for the object families: manifold3d solids to trimesh, parameter
checks, and seeded draws. Units: metres and radians; object frame z up."""

from __future__ import annotations

import math

import manifold3d as m3d
import numpy as np
import trimesh

MAX_SIZE = 0.5  # no family object is larger than this along any axis (metres)
MIN_SIZE = 0.001  # nor is any size parameter smaller (metres)


class FamilyError(ValueError):
    """A family name or parameter set is invalid; the message names it."""


def to_trimesh(solid: m3d.Manifold, what: str) -> trimesh.Trimesh:
    """The manifold ``solid`` as a watertight trimesh (float64 vertices, metres)."""
    if solid.is_empty() or solid.status() != m3d.Error.NoError:
        raise FamilyError(f"{what}: the parameters give an empty or invalid solid ({solid.status()})")
    mesh = solid.to_mesh64()
    v = np.asarray(mesh.vert_properties, dtype=np.float64)[:, :3]
    f = np.asarray(mesh.tri_verts, dtype=np.int64)
    out = trimesh.Trimesh(vertices=v, faces=f, process=True)
    if not (out.is_watertight and out.is_volume and out.volume > 0):
        raise FamilyError(f"{what}: the parameters give a mesh that is not a closed volume")
    return out


def length(params: dict, key: str, what: str, lo: float = MIN_SIZE, hi: float = MAX_SIZE) -> float:
    """``params[key]`` as a finite length in [lo, hi] metres, or FamilyError naming it."""
    if key not in params:
        raise FamilyError(f"{what}: missing parameter {key!r}")
    v = params[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not lo <= v <= hi:
        raise FamilyError(f"{what}: {key} must be a length in [{lo:g}, {hi:g}] m, got {v!r}")
    return float(v)


def lengths(params: dict, key: str, what: str, n: int, lo: float = MIN_SIZE, hi: float = MAX_SIZE) -> np.ndarray:
    """``params[key]`` as ``n`` finite lengths in [lo, hi] metres, or FamilyError naming it."""
    v = params.get(key)
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        a = np.zeros(0)
    if v is None or a.shape != (n,) or not np.all(np.isfinite(a)) or a.min() < lo or a.max() > hi:
        raise FamilyError(f"{what}: {key} must be {n} lengths in [{lo:g}, {hi:g}] m, got {v!r}")
    return a


def choice(params: dict, key: str, options: tuple[str, ...], what: str) -> str:
    v = params.get(key)
    if v not in options:
        raise FamilyError(f"{what}: {key} must be one of {', '.join(options)}, got {v!r}")
    return v


def points(params: dict, key: str, what: str, dim: int, min_count: int, bound: float = MAX_SIZE) -> np.ndarray:
    """``params[key]`` as a finite (n, dim) array with n >= min_count and |x| <= bound."""
    try:
        a = np.asarray(params[key], dtype=np.float64)
    except KeyError:
        raise FamilyError(f"{what}: missing parameter {key!r}") from None
    except (TypeError, ValueError):
        raise FamilyError(f"{what}: {key} must be a list of {dim}-vectors") from None
    if a.ndim != 2 or a.shape[1] != dim or len(a) < min_count:
        raise FamilyError(f"{what}: {key} must be a list of at least {min_count} {dim}-vectors, got shape {a.shape}")
    if not np.all(np.isfinite(a)) or np.abs(a).max() > bound:
        raise FamilyError(f"{what}: {key} must hold finite coordinates within +-{bound:g} m")
    return a


def segments(radius: float) -> int:
    """Circular segments for a radius (metres): ~6 mm chords, 16..32 segments (the
    sagitta stays below 0.2 mm, under a depth pixel; each side facet of a lying body is a
    stable pose, so finer circles only multiply near-identical poses)."""
    return int(np.clip(math.ceil(2 * math.pi * radius / 0.006), 16, 32))


def uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return mm(rng.uniform(lo, hi))


def log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return mm(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def mm(x: float) -> float:
    """Round a length to 0.01 mm (parameters stay readable in manifests)."""
    return round(float(x), 5)


def rounded(a) -> list:
    return np.round(np.asarray(a, dtype=np.float64), 5).tolist()


def random_rotation(rng: np.random.Generator) -> list[float]:
    """A uniformly random rotation as a unit quaternion (w, x, y, z)."""
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    return np.round(q if q[0] >= 0 else -q, 6).tolist()


def transform(solid: m3d.Manifold, quat_wxyz, translation) -> m3d.Manifold:
    """``solid`` rotated by the quaternion (w, x, y, z), then translated (metres)."""
    q = np.asarray(quat_wxyz, dtype=np.float64)
    q = q / np.linalg.norm(q)
    R = trimesh.transformations.quaternion_matrix(q)[:3, :3]
    M = np.concatenate([R, np.asarray(translation, dtype=np.float64).reshape(3, 1)], axis=1)
    return solid.transform(M)


def revolve(profile_rz: np.ndarray, what: str) -> m3d.Manifold:
    """Solid of revolution about z of the closed polygon ``profile_rz`` ((n, 2) rows of
    (radius, z), radius >= 0)."""
    prof = np.asarray(profile_rz, dtype=np.float64)
    r_max = float(prof[:, 0].max())
    cs = m3d.CrossSection([prof])
    if cs.is_empty():
        raise FamilyError(f"{what}: the revolved profile is empty")
    return m3d.Manifold.revolve(cs, segments(r_max))
