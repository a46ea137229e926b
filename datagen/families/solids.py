"""Solid families: boxes and slabs, cylinders / discs / rods, cones and frustums,
ellipsoids, tori and rings, prisms of (concave) polygons.

Each family is a pair: ``sample_<family>(rng) -> params`` draws realistic sizes (metres)
with at least one dimension a 5 cm parallel-jaw opening can span, and
``build_<family>(params) -> trimesh.Trimesh`` makes the watertight mesh (object frame,
z up, resting face at z = 0 where there is one)."""

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
    log_uniform,
    points,
    revolve,
    rounded,
    segments,
    to_trimesh,
    uniform,
)

# ----------------------------------------------------------------------------- box


def sample_box(rng: np.random.Generator) -> dict:
    """Blocks, slabs, dominoes, bars: thickness 6-45 mm, width up to 12 cm, length up to 25 cm."""
    t = log_uniform(rng, 0.006, 0.045)
    a = log_uniform(rng, max(t, 0.015), 0.12)
    b = log_uniform(rng, max(a, 0.02), 0.25)
    return {"size": [b, a, t]}


def build_box(p: dict) -> trimesh.Trimesh:
    size = lengths(p, "size", "box", 3)
    return to_trimesh(m3d.Manifold.cube(tuple(size), center=False), "box")


# ----------------------------------------------------------------------------- cylinder


def sample_cylinder(rng: np.random.Generator) -> dict:
    """Discs (pucks, jar lids, spools: 3-4.6 cm across, 2-3.5 cm high), rods (handles,
    dowels, thick markers: 2-4 cm thick) and cans. Everything lies at least 2 cm high: the
    fingertips reach 1 cm past the contacts, so a flatter disc or a pen lying on the table
    has no grasp this gripper can make."""
    kind = ("disc", "rod", "can")[int(rng.integers(3))]
    if kind == "disc":
        r, h = log_uniform(rng, 0.015, 0.023), uniform(rng, 0.02, 0.035)
    elif kind == "rod":
        r, h = log_uniform(rng, 0.01, 0.02), uniform(rng, 0.06, 0.25)
    else:
        r, h = uniform(rng, 0.012, 0.022), uniform(rng, 0.03, 0.16)
    return {"kind": kind, "radius": r, "height": h}


def build_cylinder(p: dict) -> trimesh.Trimesh:
    r, h = length(p, "radius", "cylinder"), length(p, "height", "cylinder")
    return to_trimesh(m3d.Manifold.cylinder(h, r, r, segments(r)), "cylinder")


# ----------------------------------------------------------------------------- cone


def sample_cone(rng: np.random.Generator) -> dict:
    """Cones and frustums (cups upside down, funnels, lamp feet): base radius 12-35 mm,
    top radius below 25 mm, height 3-15 cm and at least 4.7 x the radius difference: sides
    within 12 deg of vertical, well inside the friction cone (26.6 deg at mu 0.5), so a grasp
    across them holds when lifted (steeper tapers squeeze the object out of the jaws)."""
    rb = uniform(rng, 0.012, 0.035)
    rt = uniform(rng, max(0.0, rb - 0.03), min(0.85 * rb, 0.025))
    if rt < 0.002:
        rt = 0.0
    h = uniform(rng, max(0.03, 4.7 * (rb - rt)), 0.15)
    return {"kind": "cone" if rt == 0 else "frustum", "radius_bottom": rb, "radius_top": rt, "height": h}


def build_cone(p: dict) -> trimesh.Trimesh:
    rb, h = length(p, "radius_bottom", "cone"), length(p, "height", "cone")
    rt = length(p, "radius_top", "cone", lo=0.0)
    return to_trimesh(m3d.Manifold.cylinder(h, rb, rt, segments(rb)), "cone")


# ----------------------------------------------------------------------------- ellipsoid


def sample_ellipsoid(rng: np.random.Generator) -> dict:
    """Eggs, pebbles, bars of soap: semi-axes a < b < c with a 17-21 mm and b at most
    22.5 mm, so the object rests 3.4-4.2 cm high and is at most 4.5 cm across (graspable
    from above with the fingertips, 1 cm past the contacts, clear of the table; a flatter
    pebble has no such grasp)."""
    a = uniform(rng, 0.017, 0.021)
    b = uniform(rng, 1.05 * a, 0.0225)
    c = uniform(rng, 1.2 * b, 0.08)
    return {"semi_axes": [a, b, c]}


def build_ellipsoid(p: dict) -> trimesh.Trimesh:
    axes = lengths(p, "semi_axes", "ellipsoid", 3)
    unit = m3d.Manifold.sphere(1.0, segments(float(max(axes))))
    return to_trimesh(unit.scale(tuple(axes)), "ellipsoid")


# ----------------------------------------------------------------------------- torus


def sample_torus(rng: np.random.Generator) -> dict:
    """Tori (bagels, donuts, thick handles; tube 3-4.2 cm thick) and flat rings (tape rolls,
    pipe sections, bangles; 1.5-5 cm high, walls 3-20 mm, holes 4-10 cm across). A tube
    thinner than ~3 cm lying on the table leaves no room for the fingertips below a grasp
    across it."""
    if rng.random() < 0.5:
        R = uniform(rng, 0.03, 0.06)
        return {"kind": "torus", "major_radius": R, "minor_radius": uniform(rng, 0.015, 0.021)}
    ri = uniform(rng, 0.02, 0.05)  # the 5 cm-open jaws fit inside for a grasp across the wall
    return {"kind": "ring", "inner_radius": ri, "wall": uniform(rng, 0.003, 0.02), "height": uniform(rng, 0.015, 0.05)}


def build_torus(p: dict) -> trimesh.Trimesh:
    kind = choice(p, "kind", ("torus", "ring"), "torus")
    if kind == "torus":
        R, r = length(p, "major_radius", "torus"), length(p, "minor_radius", "torus")
        if r >= R:
            raise FamilyError(f"torus: minor_radius {r} must be < major_radius {R}")
        t = np.linspace(0, 2 * math.pi, segments(r), endpoint=False)
        profile = np.stack([R + r * np.cos(t), r * np.sin(t)], axis=1)
    else:
        ri, w, h = length(p, "inner_radius", "torus"), length(p, "wall", "torus"), length(p, "height", "torus")
        profile = np.array([[ri, 0.0], [ri + w, 0.0], [ri + w, h], [ri, h]])
    return to_trimesh(revolve(profile, "torus"), "torus")


# ----------------------------------------------------------------------------- prism

PRISM_SHAPES = ("ngon", "L", "T", "U", "cross", "star")


def _outline(shape: str, s: float, w: float, s2: float, n: int, ratio: float) -> np.ndarray:
    """Polygon (k, 2), counter-clockwise, metres: size s, bar width w, second length s2."""
    if shape == "ngon":
        t = 2 * math.pi * np.arange(n) / n
        return 0.5 * s * np.stack([np.cos(t), np.sin(t)], axis=1)
    if shape == "star":
        t = math.pi * np.arange(2 * n) / n
        r = np.where(np.arange(2 * n) % 2 == 0, 0.5 * s, 0.5 * s * ratio)
        return np.stack([r * np.cos(t), r * np.sin(t)], axis=1)
    if shape == "L":
        return np.array([[0, 0], [s, 0], [s, w], [w, w], [w, s2], [0, s2]])
    if shape == "T":
        return np.array(
            [
                [-w / 2, 0],
                [w / 2, 0],
                [w / 2, s2],
                [s / 2, s2],
                [s / 2, s2 + w],
                [-s / 2, s2 + w],
                [-s / 2, s2],
                [-w / 2, s2],
            ]
        )
    if shape == "U":
        return np.array([[0, 0], [s, 0], [s, s2], [s - w, s2], [s - w, w], [w, w], [w, s2], [0, s2]])
    h, a = w / 2, s / 2  # cross
    return np.array(
        [[-h, -a], [h, -a], [h, -h], [a, -h], [a, h], [h, h], [h, a], [-h, a], [-h, h], [-a, h], [-a, -h], [-h, -h]]
    )


def sample_prism(rng: np.random.Generator) -> dict:
    """Extruded polygons, convex (n-gons) and concave (L, T, U, cross, star): outline 4-14 cm,
    thickness 8-45 mm (the graspable dimension), bars 25-40 % of the outline."""
    shape = PRISM_SHAPES[int(rng.integers(len(PRISM_SHAPES)))]
    s = uniform(rng, 0.04, 0.14)
    w = uniform(rng, 0.25, 0.4) * s
    s2 = uniform(rng, 0.6, 1.2) * s
    n = int(rng.integers(3, 9)) if shape == "ngon" else int(rng.integers(5, 9))
    ratio = uniform(rng, 0.4, 0.65)
    poly = _outline(shape, s, w, s2, n, ratio)
    poly = poly - (poly.min(axis=0) + poly.max(axis=0)) / 2
    return {"shape": shape, "outline": rounded(poly), "thickness": uniform(rng, 0.008, 0.045)}


def build_prism(p: dict) -> trimesh.Trimesh:
    poly = points(p, "outline", "prism", 2, 3)
    t = length(p, "thickness", "prism")
    cs = m3d.CrossSection([poly], m3d.FillRule.NonZero)
    if cs.is_empty() or cs.area() < 1e-6:
        raise FamilyError("prism: the outline encloses no area")
    return to_trimesh(m3d.Manifold.extrude(cs, t), "prism")
