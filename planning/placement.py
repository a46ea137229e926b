"""Placement rows (:mod:`vgq.placement`) of grasps from a depth image alone (camera frame, metres).

The table is the planner's RANSAC plane (:func:`planning.sampler.find_table`, seeded, so one image
gives one answer), the objects its connected regions above it with their centre-of-mass guesses
(:func:`planning.sampler.object_centres`). A grasp belongs to the region under its pixel, or the
nearest one within ``vgq.placement.MAX_REGION_DISTANCE_PX``. Datagen's crop stage and the service
both call :meth:`ImagePlacement.analyse` then :meth:`ImagePlacement.rows`, so training and serving
read the same numbers; the service keeps the analysis with its cached image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from vgq.camera import Intrinsics, deproject
from vgq.placement import MAX_REGION_DISTANCE_PX, rows_from_geometry, unknown_rows
from vgq.pose import matrix_from_quaternion

from .cloud import backproject
from .sampler import find_table, object_centres, region_max
from .types import PlanParams


@dataclass(frozen=True)
class ImagePlacement:
    """What one depth image says about placement: the table plane (None: none found), each pixel's
    object region (H, W) int32 (0: none; or the nearest region within reach; an analysis made
    ``near`` some pixels: only around them), the regions' centre-of-mass guesses (n + 1, 3) and
    tops (n + 1,) (metres above the table)."""

    intr: Intrinsics
    normal: np.ndarray | None
    offset: float
    region: np.ndarray | None
    centres: np.ndarray | None
    tops: np.ndarray | None

    @classmethod
    def analyse(
        cls,
        depth: np.ndarray,
        intr: Intrinsics,
        seed: int = 0,
        params: PlanParams | None = None,
        near: np.ndarray | None = None,
    ):
        """Analyse ``depth`` (H, W) metres (0 or non-finite: no reading) seen with ``intr``. ``near``
        (k, 2) image pixels (u, v): the region map is made only around them (exact at their pixels,
        as :meth:`rows` reads them; a sensor image's noise specks on the table are regions too, and
        the whole map costs ~3 ms of distance transform); None: the whole map (the service's, read
        later at any pixel)."""
        params = params or PlanParams()
        pts, valid = backproject(depth, intr)
        table = find_table(pts, valid, params, np.random.default_rng(seed))
        if table is None:
            return cls(intr, None, 0.0, None, None, None)
        h = table.height(pts)
        objects = valid & (h > params.object_height)
        labels, centres = object_centres(pts, objects, table)
        n = len(centres) - 1
        if n == 0:
            return cls(intr, table.normal, float(table.offset), None, None, None)
        where = np.flatnonzero(objects)
        tops = np.zeros(n + 1)
        tops[1:] = region_max(h.ravel()[where], labels.ravel()[where], n)
        # every pixel off the regions takes its nearest region pixel's label within reach: the distance
        # transform over the regions' bounding box grown by the reach (beyond it nothing is in reach)
        rows, cols = np.flatnonzero(objects.any(axis=1)), np.flatnonzero(objects.any(axis=0))
        r = MAX_REGION_DISTANCE_PX
        r0, r1 = max(rows[0] - r, 0), min(rows[-1] + r + 1, objects.shape[0])
        c0, c1 = max(cols[0] - r, 0), min(cols[-1] + r + 1, objects.shape[1])
        if near is not None:  # only around the pixels asked for: every region pixel in their reach is inside
            u, v = _pixels(np.asarray(near, np.float64).reshape(-1, 2), objects.shape)
            if len(u):
                r0, r1 = max(r0, v.min() - r), min(r1, v.max() + r + 1)
                c0, c1 = max(c0, u.min() - r), min(c1, u.max() + r + 1)
        region = np.zeros(labels.shape, np.int32)
        box = labels[r0:r1, c0:c1]
        if (box != 0).any():  # else no region within reach of any pixel of the box
            dist, (iy, ix) = ndimage.distance_transform_edt(box == 0, return_indices=True)
            region[r0:r1, c0:c1] = np.where(dist <= r, box[iy, ix], 0)
        return cls(intr, table.normal, float(table.offset), region, centres, tops)

    def rows(self, uvz: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Placement rows (k, 7) float32 of grasps at image pixels and depths ``uvz`` (k, 3) (px, px,
        metres) with orientations ``q`` (k, 4) (w, x, y, z, camera frame); ``known`` 0 rows where the
        image shows no table or no object region at the grasp."""
        uvz = np.asarray(uvz, np.float64).reshape(-1, 3)
        out = unknown_rows(len(uvz))
        if self.region is None or len(uvz) == 0:
            return out
        u, v = _pixels(uvz[:, :2], self.region.shape)
        lab = self.region[v, u]
        ok = lab > 0
        if ok.any():
            g = deproject(uvz[ok], self.intr)
            R = matrix_from_quaternion(np.asarray(q, np.float64).reshape(-1, 4)[ok])
            out[ok] = rows_from_geometry(self.centres[lab[ok]], self.tops[lab[ok]], g, R, self.normal, self.offset)
        return out


def _pixels(uv: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The image pixels (columns, rows) (k,) each of points ``uv`` (k, 2), rounded, clipped into ``shape``."""
    h, w = shape
    u = np.clip(np.rint(uv[:, 0]), 0, w - 1).astype(np.intp)
    v = np.clip(np.rint(uv[:, 1]), 0, h - 1).astype(np.intp)
    return u, v


def placement_rows(depth: np.ndarray, intr: Intrinsics, uvz: np.ndarray, q: np.ndarray, seed: int = 0) -> np.ndarray:
    """:meth:`ImagePlacement.rows` of one image's grasps in one call (datagen's crop stage): the
    region map made only around them, the same rows as from the whole map."""
    uvz = np.asarray(uvz, np.float64).reshape(-1, 3)
    return ImagePlacement.analyse(depth, intr, seed, near=uvz[:, :2]).rows(uvz, q)
