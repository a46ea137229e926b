"""The world's up direction read from the depth image itself: the table's normal.

For a client that does not know how its camera is mounted (``level=table`` on the service's
routes, ``vgq-plan --level table``). The table the objects stand on is horizontal, so the
normal of the dominant plane (RANSAC, as the planner finds the table: :func:`planning.sampler.find_table`),
pointing towards the camera, is the world's up in the camera frame (x right, y down, z along
the principal ray). Its roll (:func:`vgq.camera.level_roll`) turns the image level, as the
training cameras were.

A camera within :data:`MIN_TILT` of looking straight down reads as looking straight down (up
= (0, 0, -1), nothing turned): there the roll of a fitted normal is mostly its noise, and such
cameras were trained at every roll.
"""

from __future__ import annotations

from dataclasses import dataclass
from math import radians

import numpy as np

from vgq.camera import Intrinsics, camera_tilt, level_roll

from .cloud import backproject
from .sampler import find_table
from .types import PlanParams

#: tilt from straight down (radians) under which a table-read up direction turns nothing
MIN_TILT = radians(2.0)
#: the RANSAC draw of :func:`table_level`: fixed, so one image always reads the same up
SEED = 0
#: the table fit: 4x the planner's points (its normal, not just its height, is what counts here:
#: on the realistic sensor model's images the roll's p90 error drops from 1.6 to 0.7 deg)
PARAMS = PlanParams(ransac_points=6000, ransac_iterations=100)


@dataclass(frozen=True)
class TableLevel:
    """``up`` (3,) unit, the world's up in the camera frame (the table's normal towards the
    camera; (0, 0, -1) within MIN_TILT of straight down); ``roll`` (radians) that levels the
    image, ``vgq.camera.level_roll(up)``; ``inlier_fraction`` of the sampled valid pixels on
    the table."""

    up: np.ndarray
    roll: float
    inlier_fraction: float


def table_level(depth: np.ndarray, intr: Intrinsics, params: PlanParams = PARAMS) -> TableLevel | None:
    """The up direction of ``depth`` (H, W, metres, 0 / non-finite = no reading) seen with
    ``intr``, from its table plane; None when no plane holds ``params.min_table_fraction`` of
    the valid pixels. Deterministic: the same image gives the same answer."""
    pts, valid = backproject(depth, intr)
    table = find_table(pts, valid, params, np.random.default_rng(SEED))
    if table is None:
        return None
    up = np.asarray(table.normal, dtype=np.float64)
    if camera_tilt(up) < MIN_TILT:
        up = np.array([0.0, 0.0, -1.0])
    return TableLevel(up=up, roll=level_roll(up), inlier_fraction=table.inlier_fraction)
