"""Families of revolved and hollow objects: open containers with wall thickness (cups,
bowls, hollow boxes), mugs (cup + handle), bottles and vases (revolved random profiles).

Same contract as :mod:`.solids`: ``sample_<family>(rng) -> params`` (metres),
``build_<family>(params) -> trimesh.Trimesh`` (watertight, object frame z up, base at z = 0).
A container's graspable dimension is its wall (a rim grasp)."""

from __future__ import annotations

import math

import manifold3d as m3d
import numpy as np
import trimesh
from scipy.interpolate import PchipInterpolator

from .geometry import (
    FamilyError,
    choice,
    length,
    lengths,
    points,
    revolve,
    rounded,
    segments,
    to_trimesh,
    transform,
    uniform,
)

# ----------------------------------------------------------------------------- container


def sample_container(rng: np.random.Generator) -> dict:
    """Cups (tapered, 5-10 cm across), bowls (8-18 cm across) and open hollow boxes;
    walls 2.5-8 mm."""
    kind = ("cup", "bowl", "box")[int(rng.integers(3))]
    if kind == "cup":
        R = uniform(rng, 0.025, 0.05)
        return {
            "kind": kind,
            "radius_top": R,
            "radius_bottom": uniform(rng, 0.75 * R, R),
            "height": uniform(rng, 0.04, 0.14),
            "wall": uniform(rng, 0.0025, 0.006),
            "bottom": uniform(rng, 0.003, 0.01),
        }
    if kind == "bowl":
        R = uniform(rng, 0.04, 0.09)
        return {
            "kind": kind,
            "radius_top": R,
            "radius_foot": uniform(rng, 0.35, 0.6) * R,
            "height": uniform(rng, 0.03, min(0.08, R)),
            "wall": uniform(rng, 0.003, 0.007),
        }
    return {
        "kind": kind,
        "size": [uniform(rng, 0.05, 0.15), uniform(rng, 0.05, 0.15), uniform(rng, 0.03, 0.12)],
        "wall": uniform(rng, 0.003, 0.008),
    }


def _cup_profile(rt: float, rb: float, h: float, wall: float, bottom: float) -> np.ndarray:
    """(radius, z) polygon of a tapered cup wall and bottom."""
    slope = (rt - rb) / h
    return np.array([[0, 0], [rb, 0], [rt, h], [rt - wall, h], [rb + slope * bottom - wall, bottom], [0, bottom]])


def _bowl_profile(R: float, rf: float, h: float, wall: float, n: int = 14) -> np.ndarray:
    """(radius, z) polygon of a bowl: quarter-ellipse walls from the foot ring to the rim."""
    t = np.linspace(0, math.pi / 2, n)
    outer = np.stack([rf + (R - rf) * np.sin(t), h * (1 - np.cos(t))], axis=1)
    inner = np.stack([rf - wall + (R - rf) * np.sin(t), wall + (h - wall) * (1 - np.cos(t))], axis=1)[::-1]
    return np.concatenate([[[0, 0]], outer, inner, [[0, wall]]])


def build_container(p: dict) -> trimesh.Trimesh:
    kind = choice(p, "kind", ("cup", "bowl", "box"), "container")
    wall = length(p, "wall", "container")
    if kind == "box":
        sx, sy, h = lengths(p, "size", "container", 3)
        if 2 * wall >= min(sx, sy) or wall >= h:
            raise FamilyError(f"container: wall {wall} m leaves no cavity in a box of size {[sx, sy, h]}")
        outer = m3d.Manifold.cube((sx, sy, h))
        cavity = m3d.Manifold.cube((sx - 2 * wall, sy - 2 * wall, h)).translate((wall, wall, wall))
        return to_trimesh(outer - cavity, "container")
    h = length(p, "height", "container")
    rt = length(p, "radius_top", "container")
    if kind == "cup":
        rb, bottom = length(p, "radius_bottom", "container"), length(p, "bottom", "container")
        if wall >= min(rt, rb) or bottom >= h:
            raise FamilyError("container: cup wall or bottom too thick for its radius or height")
        return to_trimesh(revolve(_cup_profile(rt, rb, h, wall, bottom), "container"), "container")
    rf = length(p, "radius_foot", "container")
    if not (wall < rf < rt) or wall >= h:
        raise FamilyError("container: a bowl needs wall < radius_foot < radius_top and wall < height")
    return to_trimesh(revolve(_bowl_profile(rt, rf, h, wall), "container"), "container")


# ----------------------------------------------------------------------------- mug


def sample_mug(rng: np.random.Generator) -> dict:
    """Mugs: a straight cup (6-9 cm across, 7-12 cm tall) with a torus-arc handle."""
    R, h = uniform(rng, 0.03, 0.045), uniform(rng, 0.07, 0.12)
    tube = uniform(rng, 0.004, 0.008)
    return {
        "radius": R,
        "height": h,
        "wall": uniform(rng, 0.003, 0.006),
        "bottom": uniform(rng, 0.004, 0.01),
        "handle_radius": uniform(rng, 0.018, min(0.035, 0.42 * h - tube)),
        "handle_tube": tube,
    }


def build_mug(p: dict) -> trimesh.Trimesh:
    R, h = length(p, "radius", "mug"), length(p, "height", "mug")
    wall, bottom = length(p, "wall", "mug"), length(p, "bottom", "mug")
    Rh, tube = length(p, "handle_radius", "mug"), length(p, "handle_tube", "mug")
    if wall >= R or bottom >= h or tube >= Rh or Rh + tube >= h / 2:
        raise FamilyError("mug: wall/bottom must fit the cup and the handle (handle_radius + handle_tube < height / 2)")
    body = m3d.Manifold.cylinder(h, R, R, segments(R))
    t = np.linspace(0, 2 * math.pi, segments(tube), endpoint=False)
    ring = revolve(np.stack([Rh + tube * np.cos(t), tube * np.sin(t)], axis=1), "mug")  # torus about z
    handle = transform(ring, [math.sqrt(0.5), math.sqrt(0.5), 0, 0], (R, 0, h / 2))  # into the xz-plane
    cavity = m3d.Manifold.cylinder(h, R - wall, R - wall, segments(R)).translate((0, 0, bottom))
    return to_trimesh((body + handle) - cavity, "mug")


# ----------------------------------------------------------------------------- bottle


def sample_bottle(rng: np.random.Generator) -> dict:
    """Bottles (body 4-9 cm across, neck 1.6-3.2 cm, 10-28 cm tall) and vases (random radii
    at 4-6 heights, one of them a graspable waist below 2.2 cm)."""
    if rng.random() < 0.5:
        h = uniform(rng, 0.1, 0.28)
        rb = uniform(rng, 0.02, 0.045)
        rn = uniform(rng, 0.008, min(0.016, 0.6 * rb))
        zs = uniform(rng, 0.45, 0.7) * h
        zn = min(zs + uniform(rng, 0.1, 0.2) * h, 0.92 * h)
        prof = [[0.95 * rb, 0.0], [rb, 0.02 * h], [rb, zs], [rn, zn], [rn, h]]
        return {"kind": "bottle", "profile": rounded(prof)}
    h = uniform(rng, 0.08, 0.25)
    k = int(rng.integers(4, 7))
    r = rng.uniform(0.012, 0.05, size=k)
    r[0] = max(r[0], 0.018)  # a base wide enough to stand on
    r[int(rng.integers(1, k))] = rng.uniform(0.01, 0.022)
    return {"kind": "vase", "profile": rounded(np.stack([r, np.linspace(0, h, k)], axis=1))}


def build_bottle(p: dict) -> trimesh.Trimesh:
    """Revolve the smooth (monotone cubic) interpolation of the (radius, z) control points."""
    choice(p, "kind", ("bottle", "vase"), "bottle")
    ctrl = points(p, "profile", "bottle", 2, 2)
    r, z = ctrl[:, 0], ctrl[:, 1]
    if np.any(np.diff(z) <= 0) or z[0] != 0:
        raise FamilyError("bottle: profile heights must start at 0 and increase")
    if r.min() < 0.003 or r.max() > 0.2 or z[-1] > 0.5:
        raise FamilyError("bottle: profile radii must lie in [0.003, 0.2] m and heights below 0.5 m")
    zz = np.linspace(0, z[-1], 32)
    rr = PchipInterpolator(z, r)(zz)
    poly = np.concatenate([[[0, 0]], np.stack([rr, zz], axis=1), [[0, z[-1]]]])
    return to_trimesh(revolve(poly, "bottle"), "bottle")
