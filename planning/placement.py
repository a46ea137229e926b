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

from vgq.camera import Intrinsics, deproject
from vgq.placement import MAX_REGION_DISTANCE_PX, rows_from_geometry, unknown_rows
from vgq.pose import matrix_from_quaternion

from .cloud import backproject
from .sampler import find_table, object_centres, region_max
from .types import PlanParams


@dataclass(frozen=True)
class ImagePlacement:
    """What one depth image says about placement: the table plane (None: none found), the object
    regions (H, W) int (0: none; region i is label i; connected regions above the table, as seen),
    the regions' centre-of-mass guesses (n + 1, 3) and tops (n + 1,) (metres above the table). A
    pixel off every region reads the nearest region within reach (:func:`region_at`)."""

    intr: Intrinsics
    normal: np.ndarray | None
    offset: float
    region: np.ndarray | None
    centres: np.ndarray | None
    tops: np.ndarray | None

    @classmethod
    def analyse(cls, depth: np.ndarray, intr: Intrinsics, seed: int = 0, params: PlanParams | None = None):
        """Analyse ``depth`` (H, W) metres (0 or non-finite: no reading) seen with ``intr``."""
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
        return cls(intr, table.normal, float(table.offset), labels, centres, tops)

    def rows(self, uvz: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Placement rows (k, 7) float32 of grasps at image pixels and depths ``uvz`` (k, 3) (px, px,
        metres) with orientations ``q`` (k, 4) (w, x, y, z, camera frame); ``known`` 0 rows where the
        image shows no table or no object region at or within reach of the grasp's pixel."""
        uvz = np.asarray(uvz, np.float64).reshape(-1, 3)
        out = unknown_rows(len(uvz))
        if self.region is None or len(uvz) == 0:
            return out
        u, v = _pixels(uvz[:, :2], self.region.shape)
        lab = region_at(self.region, u, v)
        ok = lab > 0
        if ok.any():
            g = deproject(uvz[ok], self.intr)
            R = matrix_from_quaternion(np.asarray(q, np.float64).reshape(-1, 4)[ok])
            out[ok] = rows_from_geometry(self.centres[lab[ok]], self.tops[lab[ok]], g, R, self.normal, self.offset)
        return out


def _reach_offsets(r: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel offsets (rows, columns) (m,) each within ``r`` px (Euclidean), nearest first (ties: the
    smaller row offset, then the smaller column offset)."""
    dy, dx = np.mgrid[-r : r + 1, -r : r + 1]
    d2 = dy**2 + dx**2
    keep = d2 <= r * r
    dy, dx, d2 = dy[keep], dx[keep], d2[keep]
    order = np.lexsort((dx, dy, d2))
    return dy[order], dx[order]


_REACH_DY, _REACH_DX = _reach_offsets(MAX_REGION_DISTANCE_PX)


def region_at(region: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The object region (k,) int64 of pixels (columns ``u``, rows ``v``) (k,) inside ``region``
    (H, W): the region under the pixel, else the nearest region pixel's within
    ``vgq.placement.MAX_REGION_DISTANCE_PX`` (ties as :func:`_reach_offsets` orders them), else 0.
    Only the pixels asked for are searched: a sensor image's noise specks make hundreds of tiny
    regions, and a whole-image nearest-region map cost ~3-6 ms of distance transform per upload."""
    lab = region[v, u].astype(np.int64)
    off = np.flatnonzero(lab == 0)
    if len(off):
        h, w = region.shape
        y = v[off, None] + _REACH_DY
        x = u[off, None] + _REACH_DX
        inside = (y >= 0) & (y < h) & (x >= 0) & (x < w)
        near = np.where(inside, region[np.clip(y, 0, h - 1), np.clip(x, 0, w - 1)], 0)
        lab[off] = near[np.arange(len(off)), np.argmax(near != 0, axis=1)]  # 0 where none is in reach
    return lab


def _pixels(uv: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The image pixels (columns, rows) (k,) each of points ``uv`` (k, 2), rounded, clipped into ``shape``."""
    h, w = shape
    u = np.clip(np.rint(uv[:, 0]), 0, w - 1).astype(np.intp)
    v = np.clip(np.rint(uv[:, 1]), 0, h - 1).astype(np.intp)
    return u, v


def placement_rows(depth: np.ndarray, intr: Intrinsics, uvz: np.ndarray, q: np.ndarray, seed: int = 0) -> np.ndarray:
    """:meth:`ImagePlacement.rows` of one image's grasps in one call (datagen's crop stage)."""
    return ImagePlacement.analyse(depth, intr, seed).rows(uvz, q)
