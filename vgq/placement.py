"""Placement columns: where a grasp sits on the whole object, as a network input.

The 32 x 32 window shows the grasp's neighbourhood, not the object's mass: a tall bottle held
by its neck must resist a gravity torque the window never sees (``training.centroid_probe``
measured it: on bottles success falls from 0.37 within 1 cm of the visible centroid to 0.07 at
4-8 cm). A placement row carries that to the head, per grasp, computed from the depth image alone
(:func:`planning.placement.placement_rows`, the one function datagen's crop stage and the service
both call, so training and serving read the same numbers):

* ``known``: 1 where the image shows a table and an object region at the grasp, else 0 (and
  every other column 0): the network then scores on the window and the pose alone;
* ``offset``: the horizontal distance (in the table plane) from the grasp centre to the object's
  centre-of-mass guess, metres (what ``training.centroid_probe`` measured success falling with);
* ``along``, ``across``, ``depth``: the object's centre-of-mass guess (its seen points dropped to
  half their height above the table) relative to the grasp centre, in the gripper frame (x along
  the jaw axis, z along the approach), metres; ``along`` and ``across`` as magnitudes, since
  swapping the jaws (a half turn about the approach) is the same grasp;
* ``height``: the grasp centre above the table, metres;
* ``top``: the object region's highest seen point above the table, metres.

The network reads each column divided by :data:`PLACEMENT_SCALE_M` (inside the graphs).
"""

from __future__ import annotations

import numpy as np

PLACEMENT_COLUMNS: tuple[str, ...] = ("known", "offset", "along", "across", "depth", "height", "top")
#: what the network divides each column by (metres; ``known`` is 0 or 1)
PLACEMENT_SCALE_M: tuple[float, ...] = (1.0, 0.05, 0.05, 0.05, 0.05, 0.1, 0.1)
#: a grasp whose pixel is off every object region takes the nearest one this close (image px)
MAX_REGION_DISTANCE_PX = 24


def unknown_rows(k: int) -> np.ndarray:
    """(k, len(PLACEMENT_COLUMNS)) float32 rows saying "no placement known" (all zero)."""
    return np.zeros((k, len(PLACEMENT_COLUMNS)), np.float32)


def rows_from_geometry(
    centre_of_mass: np.ndarray,
    top: np.ndarray,
    centres: np.ndarray,
    rotations: np.ndarray,
    normal: np.ndarray,
    offset: float,
) -> np.ndarray:
    """Placement rows (k, 7) float32, ``known`` 1, for grasp centres (k, 3) with rotations (k, 3, 3)
    (gripper to camera frame), their objects' centre-of-mass guesses (k, 3) and tops (k,) (metres
    above the table), and the table plane ``normal . x + offset = 0`` (unit normal towards the
    camera); all camera frame, metres."""
    d = np.asarray(centre_of_mass, np.float64) - centres
    n = np.asarray(normal, np.float64)
    rel = np.einsum("kji,kj->ki", rotations, d)  # R^T (c - g): the gripper frame
    out = np.empty((len(centres), len(PLACEMENT_COLUMNS)), np.float32)
    out[:, 0] = 1.0
    out[:, 1] = np.linalg.norm(d - (d @ n)[:, None] * n, axis=1)
    out[:, 2] = np.abs(rel[:, 0])
    out[:, 3] = np.abs(rel[:, 1])
    out[:, 4] = rel[:, 2]
    out[:, 5] = centres @ n + offset
    out[:, 6] = top
    return out
