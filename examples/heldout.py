"""Load ``heldout_images.npz`` (made by ``make_heldout_images.py``): whole depth images of
held-out test objects of the bundled model's recipe, with labelled grasps.

Arrays: ``depth`` (n, 300, 300) float32 metres (camera frame, 0 = no reading: none here,
the renders are clean); ``object_id`` (n,) int32 recipe object ids; ``grasps`` (m, 7) float32
u, v (image px), z (m), qw, qx, qy, qz (camera frame), the service's grasp rows;
``labels`` (m,) uint8 (robust Ferrari-Canny > 0.002 and collision-free); ``image_index``
(m,) int32 row -> image; ``center`` (m, 2) float32 the window centre (u, v) image px each
grasp is scored in: the centre of an integer window within kappa (36 px, per axis) of the
grasp, drawn as the crop stage draws training windows (upload with ``center_u``/``center_v``).

Measured (fp32 head, in process: ``vgq.crop.crop`` + ``service.grasps.to_network_poses`` +
the ONNX graphs): the bundled model scores balanced accuracy 0.784 (TPR 0.843, TNR 0.725) on
these 700 grasps, below its card's 0.864 on the recipe's test split, because these grasps are
drawn at random rather than through the sampling stage's positivity equalisation and uniform
(phi, beta) binning. With u and v offsets swapped it falls to 0.661; with offsets mirrored
(u -> 2 c_u - u) to 0.758; a mirrored whole image (0.779) is not separable from clean here.
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
