"""Parallel-jaw gripper dimensions and its boxes in the grasp frame (SPEC sections 1 and 2.5).

Shared by datagen (collision checks on meshes) and planning (collision checks on observed
points), numpy only. Grasp frame: origin at the tool centre point (TCP, midway between the
contacts), x along the jaw axis, z the approach direction, y = z x x. Metres.

The gripper is three boxes in the grasp frame, opened to ``max_width``: two fingers whose
inner faces sit at x = +-max_width / 2 and whose tips reach ``tip_offset`` past the TCP
along +z, and a palm box behind the fingers. Its straight approach starts
``approach_distance`` back along -z; the volume swept on the way is the same boxes extended
back along -z by that distance (:func:`gripper_boxes` with ``swept=True``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class GripperGeometry:
    """Box gripper dimensions, metres.

    ``finger_width``: finger size along the grasp y-axis; ``finger_depth``: finger thickness
    along x (the jaw axis); ``finger_length``: along z; ``palm_thickness``: palm size along z;
    ``palm_width``: palm size along y (its x size spans both fingers); ``tip_offset``: how far
    the fingertips reach past the TCP along +z; ``approach_distance``: start of the straight
    approach, measured back along -z from the grasp pose.
    """

    max_width: float = 0.05
    finger_width: float = 0.02
    finger_depth: float = 0.01
    finger_length: float = 0.05
    palm_thickness: float = 0.02
    approach_distance: float = 0.1
    palm_width: float = 0.03
    tip_offset: float = 0.01

    def __post_init__(self) -> None:
        for name in ("max_width", "finger_width", "finger_depth", "finger_length", "palm_thickness", "palm_width"):
            v = getattr(self, name)
            if not np.isfinite(v) or v <= 0:
                raise ValueError(f"GripperGeometry.{name} must be a finite number > 0 m, got {v!r}")
        for name in ("approach_distance", "tip_offset"):
            v = getattr(self, name)
            if not np.isfinite(v) or v < 0:
                raise ValueError(f"GripperGeometry.{name} must be a finite number >= 0 m, got {v!r}")
        if self.tip_offset >= self.finger_length:
            raise ValueError(
                f"GripperGeometry.tip_offset ({self.tip_offset}) must be < finger_length ({self.finger_length})"
            )


def gripper_boxes(geom: GripperGeometry, swept: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Box centres (3, 3) and half extents (3, 3) in the grasp frame: finger at -x, finger at
    +x, palm. With ``swept`` each box is extended back along -z by ``approach_distance`` so it
    covers the whole straight approach."""
    back = geom.approach_distance if swept else 0.0
    tip = geom.tip_offset
    f_len = geom.finger_length + back
    f_x = geom.max_width / 2 + geom.finger_depth / 2
    f_z = tip - f_len / 2
    palm_front = tip - geom.finger_length
    p_len = geom.palm_thickness + back
    centres = np.array([[-f_x, 0.0, f_z], [f_x, 0.0, f_z], [0.0, 0.0, palm_front - p_len / 2]])
    half = np.array(
        [
            [geom.finger_depth / 2, geom.finger_width / 2, f_len / 2],
            [geom.finger_depth / 2, geom.finger_width / 2, f_len / 2],
            [geom.max_width / 2 + geom.finger_depth, geom.palm_width / 2, p_len / 2],
        ]
    )
    return centres, half


def box_corners(centres: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Corners (k * 8, 3) of k axis-aligned boxes given centres (k, 3) and half extents (k, 3)."""
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
    return (centres[:, None, :] + signs[None] * half[:, None, :]).reshape(-1, 3)
