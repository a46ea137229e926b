"""What the planner knows of each candidate besides the network's score: features a ranker may
combine with it, computed from the depth image alone (the estimated table, the observed points).

All in the camera frame, metres and degrees. Without a table estimate the table-relative
features are NaN (a ranker must treat them as missing)."""

from __future__ import annotations

import numpy as np

from vgq.gripper import GripperGeometry, box_corners, gripper_boxes

from .collision import lowest_corner_height
from .sampler import Candidates, Scene

#: name -> meaning, in column order
PLAN_FEATURES: dict[str, str] = {
    "score": "the network's P(success)",
    "width": "distance between the two contacts (m)",
    "seen": "1 when the second contact lies on an observed surface, 0 when it is inferred behind the object",
    "table_clearance": "lowest gripper point above the estimated table (m)",
    "tcp_height": "grasp centre above the estimated table (m)",
    "approach_tilt": "approach direction from straight down onto the table (deg)",
    "axis_tilt": "jaw axis from the table normal (deg): 90 = jaws close parallel to the table",
}


def plan_features(
    cands: Candidates, scores: np.ndarray, scene: Scene, gripper: GripperGeometry
) -> dict[str, np.ndarray]:
    """:data:`PLAN_FEATURES` (each (n,) float64) of ``cands`` (camera frame) on ``scene``."""
    f = cands.frames
    n = len(f)
    out = {
        "score": np.asarray(scores, np.float64).reshape(n),
        "width": np.asarray(cands.widths, np.float64),
        "seen": np.asarray(cands.seen, np.float64),
    }
    up = scene.up
    z, x = f[:, :3, 2], f[:, :3, 0]
    out["approach_tilt"] = np.degrees(np.arccos(np.clip(-(z @ up), -1.0, 1.0)))
    out["axis_tilt"] = np.degrees(np.arccos(np.clip(np.abs(x @ up), 0.0, 1.0)))
    if scene.table is None:
        out["table_clearance"] = np.full(n, np.nan)
        out["tcp_height"] = np.full(n, np.nan)
    else:
        corners = box_corners(*gripper_boxes(gripper, swept=False))
        out["table_clearance"] = lowest_corner_height(f, corners, scene.table.normal, scene.table.offset)
        out["tcp_height"] = scene.table.height(f[:, :3, 3])
    return {k: out[k] for k in PLAN_FEATURES}
