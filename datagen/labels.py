"""The grasp label of a dataset (issue 17): which score becomes ``quality`` and what threshold
makes a grasp positive.

Kinds (``LabelParams.kind``):

* ``"paper"``: robust Ferrari-Canny at the grasp-line contacts, 0 when the gripper collides at
  the nominal pose; positive above ``quality.label_threshold`` (0.002). This reproduces the
  paper's (VG-dset / Dex-Net 2.0) setup.
* ``"robust"``: robust Ferrari-Canny times P(collision-free) under execution noise with a
  clearance (:func:`datagen.collision.collision_free_probability`); same threshold.
* ``"pad"``: Ferrari-Canny at the pad contacts (:mod:`datagen.pads`) times P(collision-free);
  same threshold.
* ``"physics"``: the success rate of ``trials`` noisy pybullet trials (:mod:`datagen.physics`)
  of the grasp in its stable pose; positive above ``success_threshold`` (0.5: at least 5 of 8). The approach
  (omega) is then drawn once per grasp and stable pose and shared by all cameras, since the
  trials label that 6-DOF grasp; grasps that collide at the nominal pose get 0 without trials.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

KINDS = ("paper", "robust", "pad", "physics")


@dataclass(frozen=True)
class LabelParams:
    """Which label a dataset stores as ``quality`` (see the module doc)."""

    kind: str = "physics"  # the label study (docs/labels.md): the only label near AUC 0.8 vs physical success
    trials: int = 8  # physics: noisy trials per grasp and pose (study: AUC 0.78 with 4, 0.82 with 8, 0.83 with 12)
    success_threshold: float = 0.5  # physics: positive when the success rate exceeds this
    # physics: stop a grasp's trials once its label is decided (5 held or 4 dropped of 8): the same
    # labels from ~30% fewer trials, but ``quality`` is then the rate over the trials run, not of all
    early_stop: bool = False

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"label.kind must be one of {', '.join(KINDS)}, got {self.kind!r}")
        if self.trials < 1:
            raise ValueError(f"label.trials must be >= 1, got {self.trials}")
        if not (0.0 <= self.success_threshold < 1.0):
            raise ValueError(f"label.success_threshold must be in [0, 1), got {self.success_threshold}")
        if not isinstance(self.early_stop, bool):
            raise ValueError(f"label.early_stop must be true or false, got {self.early_stop!r}")

    @property
    def needs_physics(self) -> bool:
        return self.kind == "physics"


def label_score(
    kind: str, fc: np.ndarray, collision_free: np.ndarray, p_cf: np.ndarray, pad_q: np.ndarray, success: np.ndarray
) -> np.ndarray:
    """The ``quality`` column (float, per row) of label ``kind`` from the per-row fields."""
    cf = np.asarray(collision_free, bool)
    if kind == "paper":
        return np.where(cf, fc, 0.0)
    if kind == "robust":
        return np.where(cf, fc * np.nan_to_num(p_cf, nan=0.0), 0.0)
    if kind == "pad":
        return np.where(cf, np.nan_to_num(pad_q * p_cf, nan=0.0), 0.0)
    if kind == "physics":
        return np.where(cf, np.nan_to_num(success, nan=0.0), 0.0)
    raise ValueError(f"unknown label kind {kind!r}")
