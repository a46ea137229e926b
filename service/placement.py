"""Placement rows (``vgq.placement``) for a model whose head reads them (``card.placement_columns``).

An upload is analysed once (:meth:`planning.placement.ImagePlacement.analyse`: the table plane and
the object regions) as the client sent it: the depth in metres before any resampling, levelling or
inpainting (0 or non-finite: no reading), with the upload's own intrinsics, as datagen's crop stage
analyses each sensor image. The analysis is kept with the cached image (``CachedImage.placement``;
the Redis backend stores it too) and each scored grasp's row comes from its (u, v, z, q) as the
client sent them, appended after the head's 7 pose columns. Models without placement never get
here: no analysis, no extra column.

The planner (``planning.policy``) builds its own head rows: for a placement model it runs through
:class:`UnknownPlacementModel`, whose head appends *unknown* rows (all 0, ``known`` = 0: what an
image without a table gives, and what placement dropout trained the head on).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from planning.placement import ImagePlacement
from vgq.camera import Intrinsics
from vgq.model_card import HEAD_INPUTS
from vgq.placement import PLACEMENT_COLUMNS, unknown_rows

#: how a plan answer says what its scores read (placement models only)
PLAN_PLACEMENT = {
    "known": False,
    "note": "the planner scores its candidates with unknown placement rows (known = 0); score a planned grasp's "
    "row with POST /v1/images/{image_id}/scores for its score with the placement row",
}


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
    """(k, 6) float32 placement rows of (k, 7) client grasps (u, v in the uploaded image's pixels,
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


class _UnknownPlacementHead:
    """A placement head as the planner calls it (``run`` with 7-column poses): each row followed by
    an unknown placement row."""

    def __init__(self, head, width: int):
        self.head, self.width = head, width

    def run(self, outputs, feed):
        poses = np.asarray(feed[HEAD_INPUTS[1]], np.float32)
        if poses.shape[1] < self.width:
            poses = np.hstack([poses, np.zeros((len(poses), self.width - poses.shape[1]), np.float32)])
            feed = {**feed, HEAD_INPUTS[1]: poses}
        return self.head.run(outputs, feed)

    def __getattr__(self, name):
        return getattr(self.head, name)


class UnknownPlacementModel:
    """A :class:`service.runtime.FastModel` of a placement head as the planner runs it: everything
    the model's own, except that the head's pose rows get unknown placement rows (the planner
    builds rows of 7 columns; see the module's note)."""

    def __init__(self, model):
        if tuple(model.card.placement_columns) != PLACEMENT_COLUMNS:
            raise ValueError(f"not a placement model: columns {model.card.placement_columns!r}")
        self._model = model
        self.head = _UnknownPlacementHead(model.head, model.n_pose)

    def __getattr__(self, name):
        return getattr(self._model, name)
