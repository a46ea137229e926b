"""Everyday object families: seeded, parametric, watertight meshes in metres.

A family is a pure builder ``params -> trimesh.Trimesh`` and a seeded sampler
``rng -> params`` with realistic sizes for a parallel-jaw gripper with a 5 cm opening
(every object has a dimension the jaws can span). Objects keep their physical size: the
datagen pipeline does not rescale them. An object is named ``<family>_<index:04d>``; its
parameters depend only on (run seed, family, index) (:func:`family_rng`), so the same
triple always gives the same mesh.

Object frame: metres, z up, the object's base (if it has one) at z = 0; the pipeline
re-centres every mesh on its centre of mass.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from . import freeform, hollow, solids
from .geometry import FamilyError

SOURCE_FAMILY = "random_urdfs"  # the family recorded for objects of the default mesh source


@dataclass(frozen=True)
class Family:
    """One object family. ``extent_range``: (low, high) metres that bound every axis-aligned
    extent of its meshes in their build frame."""

    name: str
    summary: str
    sample: Callable[[np.random.Generator], dict]
    build: Callable[[dict], trimesh.Trimesh]
    extent_range: tuple[float, float]


FAMILIES: dict[str, Family] = {
    f.name: f
    for f in (
        Family("box", "boxes, slabs, dominoes and bars", solids.sample_box, solids.build_box, (0.006, 0.25)),
        Family("cylinder", "cylinders, discs and rods", solids.sample_cylinder, solids.build_cylinder, (0.006, 0.25)),
        Family("cone", "cones and frustums", solids.sample_cone, solids.build_cone, (0.02, 0.15)),
        Family(
            "ellipsoid", "eggs, pebbles and soap bars", solids.sample_ellipsoid, solids.build_ellipsoid, (0.024, 0.16)
        ),
        Family("torus", "tori and flat rings", solids.sample_torus, solids.build_torus, (0.012, 0.15)),
        Family(
            "prism",
            "extruded polygons: n-gons, L, T, U, cross, star",
            solids.sample_prism,
            solids.build_prism,
            (0.008, 0.17),
        ),
        Family(
            "container",
            "open cups, bowls and hollow boxes with walls",
            hollow.sample_container,
            hollow.build_container,
            (0.03, 0.18),
        ),
        Family("mug", "cups with a handle", hollow.sample_mug, hollow.build_mug, (0.06, 0.17)),
        Family(
            "bottle",
            "bottles and vases (revolved random profiles)",
            hollow.sample_bottle,
            hollow.build_bottle,
            (0.016, 0.28),
        ),
        Family(
            "composite",
            "unions of 2-5 boxes, cylinders and spheres",
            freeform.sample_composite,
            freeform.build_composite,
            (0.01, 0.3),
        ),
        Family(
            "metaball",
            "smooth organic blobs (metaball level sets)",
            freeform.sample_metaball,
            freeform.build_metaball,
            (0.012, 0.15),
        ),
    )
}


def family_names() -> list[str]:
    return list(FAMILIES)


def get_family(name: str) -> Family:
    """The family called ``name``, or FamilyError listing the known ones."""
    try:
        return FAMILIES[name]
    except (KeyError, TypeError):
        raise FamilyError(f"unknown object family {name!r} (known: {', '.join(FAMILIES)})") from None


def object_name(family: str, index: int) -> str:
    return f"{family}_{int(index):04d}"


def family_rng(seed: int, family: str, index: int) -> np.random.Generator:
    """The parameter stream of object ``index`` of ``family`` in a run with ``seed``."""
    h = hashlib.sha256(f"vgq-families:{int(seed)}:{family}:{int(index)}".encode()).digest()
    return np.random.default_rng(int.from_bytes(h[:8], "little"))


def sample_params(family: str, index: int, seed: int = 0) -> dict:
    """The JSON-able parameters (metres) of object ``index`` of ``family`` for run ``seed``."""
    if int(index) != index or index < 0:
        raise FamilyError(f"object index must be a non-negative integer, got {index!r}")
    params = get_family(family).sample(family_rng(seed, family, index))
    return json.loads(json.dumps(params))  # plain lists and floats, as a manifest stores them


def build_mesh(family: str, params: dict) -> trimesh.Trimesh:
    """The watertight mesh (metres) of ``family`` with ``params``; FamilyError for bad ones."""
    fam = get_family(family)
    if not isinstance(params, dict):
        raise FamilyError(f"{family}: params must be a JSON object, got {type(params).__name__}")
    return fam.build(params)


@dataclass(frozen=True)
class FamilyObject:
    name: str
    family: str
    params: dict
    mesh: trimesh.Trimesh


def make_object(family: str, index: int, seed: int = 0) -> FamilyObject:
    """Object ``index`` of ``family`` for run ``seed``: name, parameters and mesh."""
    params = sample_params(family, index, seed)
    return FamilyObject(object_name(family, index), family, params, build_mesh(family, params))


def family_sources(counts: dict[str, int], seed: int = 0) -> list:
    """:class:`datagen.mesh.MeshSource` entries for ``{family: count}`` objects of run
    ``seed`` (indices 0..count-1 per family, the families in the order of :data:`FAMILIES`
    whatever the order of ``counts``: a config read back from a manifest, written with sorted
    keys, numbers its objects as the run did). Their meshes are built when loaded; nothing is
    written to disk."""
    from ..mesh import MeshSource

    for family in counts:
        get_family(family)
    out = []
    for family, n in sorted(counts.items(), key=lambda fn: list(FAMILIES).index(fn[0])):
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            raise FamilyError(f"object count of family {family!r} must be an integer >= 0, got {n!r}")
        for i in range(n):
            name = object_name(family, i)
            out.append(MeshSource(name, Path(f"family:{name}"), 1.0, family, sample_params(family, i, seed)))
    return out


__all__ = [
    "FAMILIES",
    "SOURCE_FAMILY",
    "Family",
    "FamilyError",
    "FamilyObject",
    "build_mesh",
    "family_names",
    "family_rng",
    "family_sources",
    "get_family",
    "make_object",
    "object_name",
    "sample_params",
]
