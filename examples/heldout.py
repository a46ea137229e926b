"""Load ``heldout_images.npz`` (made by ``make_heldout_images.py``): whole depth images of
held-out test objects of the bundled model's recipe, with labelled grasps.

Arrays: ``depth`` (n, 300, 300) float32 metres (camera frame, 0 = no reading: none here,
the renders are clean); ``object_id`` (n,) int32 recipe object ids; ``grasps`` (m, 7) float32
u, v (image px), z (m), qw, qx, qy, qz (camera frame), the service's grasp rows;
``labels`` (m,) uint8 (robust Ferrari-Canny > 0.002 and collision-free); ``image_index``
(m,) int32 row -> image; ``center`` (m, 2) float32 the window centre (u, v) image px each
grasp is scored in: the centre of an integer window within kappa (36 px, per axis) of the
grasp, drawn as the crop stage draws training windows (upload with ``center_u``/``center_v``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

HELDOUT_IMAGES = Path(__file__).resolve().parent / "heldout_images.npz"


@dataclass(frozen=True)
class HeldoutImages:
    depth: np.ndarray
    object_id: np.ndarray
    grasps: np.ndarray
    labels: np.ndarray
    image_index: np.ndarray
    center: np.ndarray

    def __len__(self) -> int:
        return len(self.labels)


def load_heldout_images(path: str | Path = HELDOUT_IMAGES) -> HeldoutImages:
    with np.load(path) as d:
        return HeldoutImages(**{k: d[k] for k in HeldoutImages.__dataclass_fields__})
