"""Placement rows (``vgq.placement``) for a model whose head reads them (``card.placement_columns``).

An upload is analysed once (:meth:`planning.placement.ImagePlacement.analyse`: the table plane and
the object regions) as the client sent it: the depth in metres before any resampling, levelling or
inpainting (0 or non-finite: no reading), with the upload's own intrinsics, as datagen's crop stage
analyses each sensor image. The analysis is kept with the cached image (``CachedImage.placement``;
the Redis backend stores it too) and each scored grasp's row comes from its (u, v, z, q) as the
client sent them, appended after the head's 7 pose columns. Models without placement never get
here: no analysis, no extra column.

The planner (``planning.policy.window_scorer``) analyses the image it plans on and appends its
candidates' rows itself.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from planning.placement import ImagePlacement
from vgq.camera import Intrinsics
from vgq.placement import unknown_rows


def analyse(depth: np.ndarray, camera: Intrinsics) -> ImagePlacement:
    """The analysis of an upload ``depth`` (H, W) metres as sent, seen with ``camera`` (its own
    intrinsics), its region map stored in the smallest unsigned type that holds its labels
    (1 B/px for up to 255 objects; :meth:`ImagePlacement.rows` reads any integer type alike)."""
    return compact(ImagePlacement.analyse(depth, camera))


def compact(p: ImagePlacement) -> ImagePlacement:
    if p.region is None:
        return p
    n = len(p.centres) - 1
    dtype = np.uint8 if n <= 0xFF else np.uint16 if n <= 0xFFFF else np.int32
    return dataclasses.replace(p, region=p.region.astype(dtype, copy=False))


def nbytes(p: ImagePlacement | None) -> int:
    """Bytes of an analysis kept in the cache (its region map and per-region arrays)."""
    if p is None:
        return 0
    return sum(int(a.nbytes) for a in (p.region, p.centres, p.tops, p.normal) if a is not None)


def rows(p: ImagePlacement | None, grasps: np.ndarray) -> np.ndarray:
    """(k, 7) float32 placement rows of (k, 7) client grasps (u, v in the uploaded image's pixels,
    z, qw, qx, qy, qz in its camera frame); unknown (all 0) without an analysis."""
    g = np.asarray(grasps, np.float64)
    if p is None:
        return unknown_rows(len(g))
    return p.rows(g[:, :3], g[:, 3:7])


def describe(p: ImagePlacement | None) -> dict:
    """An upload answer's ``placement``: did the image show a table, how many object regions on it."""
    return {
        "table_found": p is not None and p.normal is not None,
        "objects": 0 if p is None or p.centres is None else len(p.centres) - 1,
    }
