"""Free-form families: composites (unions of 2-5 primitives) and smooth organic shapes
(the level set of a random metaball field).

Same contract as :mod:`.solids`. Connectivity is built into the samplers: each new
primitive (or ball) is centred inside an earlier one, so the union is one body."""

from __future__ import annotations

import math

import manifold3d as m3d
import numpy as np
import trimesh

from .geometry import (
    FamilyError,
    choice,
    length,
    lengths,
    points,
    random_rotation,
    rounded,
    segments,
    to_trimesh,
    transform,
    uniform,
)

PRIMITIVES = ("box", "cylinder", "sphere")

# ----------------------------------------------------------------------------- composite


def _primitive(rng: np.random.Generator) -> dict:
    """One primitive, each graspable by itself (a dimension below 4.4 cm)."""
    kind = PRIMITIVES[int(rng.integers(len(PRIMITIVES)))]
    if kind == "box":
        size = [uniform(rng, 0.012, 0.07), uniform(rng, 0.012, 0.07), uniform(rng, 0.012, 0.04)]
    elif kind == "cylinder":
        size = [uniform(rng, 0.006, 0.022), uniform(rng, 0.02, 0.1)]  # radius, height
    else:
        size = [uniform(rng, 0.01, 0.022)]  # radius
    return {"kind": kind, "size": size}


def _inside(prim: dict, rng: np.random.Generator) -> np.ndarray:
    """A random point well inside ``prim`` (its own frame, metres)."""
    u = rng.uniform(-0.7, 0.7, size=3)
    s = prim["size"]
    if prim["kind"] == "box":
        return u * np.asarray(s) / 2
    if prim["kind"] == "cylinder":
        ang = rng.uniform(0, 2 * math.pi)
        return np.array([abs(u[0]) * s[0] * math.cos(ang), abs(u[0]) * s[0] * math.sin(ang), u[2] * s[1] / 2])
    return u / max(np.linalg.norm(u), 1e-9) * abs(u[0]) * s[0]


def sample_composite(rng: np.random.Generator) -> dict:
    """2-5 boxes, cylinders and spheres at random orientations; primitive i > 0 is centred
    inside a random earlier one."""
    n = int(rng.integers(2, 6))
    prims: list[dict] = []
    for i in range(n):
        prim = _primitive(rng)
        prim["rotation"] = random_rotation(rng)
        if i == 0:
            prim["center"] = [0.0, 0.0, 0.0]
        else:
            parent = prims[int(rng.integers(i))]
            R = _rotation(parent["rotation"])
            prim["center"] = rounded(np.asarray(parent["center"]) + R @ _inside(parent, rng))
        prims.append(prim)
    return {"primitives": prims}


def _rotation(q) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    return trimesh.transformations.quaternion_matrix(q / np.linalg.norm(q))[:3, :3]


def _solid(prim: dict, i: int) -> m3d.Manifold:
    what = f"composite primitive {i}"
    kind = choice(prim, "kind", PRIMITIVES, what)
    if kind == "box":
        s = lengths(prim, "size", what, 3)
        solid = m3d.Manifold.cube(tuple(s), center=True)
    elif kind == "cylinder":
        r, h = lengths(prim, "size", what, 2)
        solid = m3d.Manifold.cylinder(h, r, r, segments(r), center=True)
    else:
        (r,) = lengths(prim, "size", what, 1)
        solid = m3d.Manifold.sphere(r, segments(r))
    q = points({"rotation": [prim.get("rotation")]}, "rotation", what, 4, 1, bound=1.0 + 1e-6)[0]
    if np.linalg.norm(q) < 0.5:
        raise FamilyError(f"{what}: rotation must be a unit quaternion (w, x, y, z)")
    c = points({"center": [prim.get("center")]}, "center", what, 3, 1)[0]
    return transform(solid, q, c)


def build_composite(p: dict) -> trimesh.Trimesh:
    prims = p.get("primitives")
    if not isinstance(prims, list) or not 1 <= len(prims) <= 8 or not all(isinstance(q, dict) for q in prims):
        raise FamilyError("composite: primitives must be a list of 1-8 primitive objects")
    solid = m3d.Manifold.batch_boolean([_solid(q, i) for i, q in enumerate(prims)], m3d.OpType.Add)
    return to_trimesh(solid, "composite")


# ----------------------------------------------------------------------------- metaball

EDGE_LENGTH = 0.004  # level-set grid: ~4 mm triangles
SIMPLIFY_TOLERANCE = 0.0002  # then merge triangles where the surface moves < 0.2 mm


def metaball_field(x: np.ndarray, centers: np.ndarray, r2: np.ndarray) -> np.ndarray:
    """sum_i r_i^2 / |x - c_i|^2 at points ``x`` (..., 3) (metres) for balls at ``centers``
    (n, 3) with squared radii ``r2`` (n,): each ball alone is >= 1 inside its sphere."""
    d2 = ((np.asarray(x)[..., None, :] - centers) ** 2).sum(axis=-1)
    return (r2 / np.maximum(d2, 1e-12)).sum(axis=-1)


def _blob_extents(centers: np.ndarray, radii: list[float], squash: list[float], step: float = 0.002) -> np.ndarray:
    """The squashed metaball's extents (3,) (metres, ascending) along its principal axes, from the
    field sampled on a ``step`` grid (blending makes a cluster of balls swell well beyond each
    ball)."""
    r2 = np.asarray(radii) ** 2
    margin = 1.05 * math.sqrt(float(r2.sum()))
    axes = [np.arange(lo - margin, hi + margin, step) for lo, hi in zip(centers.min(axis=0), centers.max(axis=0))]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    field = metaball_field(g, centers, r2)
    inside = g[field >= 1.0] * np.asarray(squash)
    if len(inside) < 4:
        return np.zeros(3)
    principal = np.linalg.svd(inside - inside.mean(axis=0), full_matrices=False)[2]
    return np.sort(np.ptp(inside @ principal.T, axis=0))


def sample_metaball(rng: np.random.Generator) -> dict:
    """2-6 balls of radius 12-18 mm, mostly in a chain; ball i > 0 sits 0.45-0.85 of the
    blending reach (ri^(2/3) + rj^(2/3))^(3/2) from a random earlier ball j, the distance up
    to which the field stays >= 1 along the segment between them, so the blob is one smooth
    body (potatoes, peanuts, pebbles, bent sausages). It is then squashed along y and z
    (factors 0.8-1 and 0.7-0.9) so it rests in a few distinct poses, not on any facet of
    a near-sphere. A blob must be at least 3 cm thick and at most 4.4 cm wide (its two
    smallest principal extents, :func:`_blob_extents`), else it is drawn again: it rests on its
    broad side, so the jaws close across its width from above (a blob 4.3 cm thick but 7 cm
    wide had no collision-free grasp), and a round body is gripped across its middle with the
    fingertips 1 cm past the contacts (a 2.6 cm blob had collision-free grasps for under 1% of
    its antipodal pairs)."""
    for _ in range(60):
        n = int(rng.integers(2, 7))
        radii = [uniform(rng, 0.012, 0.018)]
        centers = [np.zeros(3)]
        for _ in range(1, n):
            j = len(radii) - 1 if rng.random() < 0.7 else int(rng.integers(len(radii)))  # mostly chains
            d = rng.normal(size=3)
            d /= np.linalg.norm(d)
            r = uniform(rng, 0.012, 0.018)
            reach = (radii[j] ** (2 / 3) + r ** (2 / 3)) ** 1.5  # farthest centre distance that still blends
            centers.append(centers[j] + d * rng.uniform(0.45, 0.85) * reach)
            radii.append(r)
        c = rounded(np.array(centers))
        squash = [1.0, uniform(rng, 0.8, 1.0), uniform(rng, 0.7, 0.9)]
        e = _blob_extents(np.asarray(c), radii, squash)
        if e[0] >= 0.03 and e[1] <= 0.044:
            break
    return {"centers": c, "radii": radii, "squash": squash}


def build_metaball(p: dict) -> trimesh.Trimesh:
    """Surface where sum_i r_i^2 / |x - c_i|^2 = 1 (each ball alone is the sphere of radius
    r_i; close balls blend), from manifold3d's marching-tetrahedra level set, then scaled
    per axis by ``squash``."""
    c = points(p, "centers", "metaball", 3, 1, bound=0.2)
    r = np.asarray(p.get("radii", []), dtype=np.float64) if isinstance(p.get("radii"), list) else np.zeros(0)
    if r.shape != (len(c),) or len(c) > 12:
        raise FamilyError("metaball: radii must be a list with one radius per centre (at most 12)")
    for i, v in enumerate(r):
        length({"radius": float(v)}, "radius", f"metaball ball {i}", lo=0.003, hi=0.1)
    r2 = r * r
    margin = 1.05 * math.sqrt(float(r2.sum())) + 2 * EDGE_LENGTH  # the field is < 1 beyond this
    bounds = list(c.min(axis=0) - margin) + list(c.max(axis=0) + margin)

    def field(x: float, y: float, z: float) -> float:
        return float(metaball_field((x, y, z), c, r2)) - 1.0

    squash = lengths(p, "squash", "metaball", 3, lo=0.1, hi=1.0)
    solid = m3d.Manifold.level_set(field, bounds, EDGE_LENGTH).simplify(SIMPLIFY_TOLERANCE).scale(tuple(squash))
    return to_trimesh(solid, "metaball")
