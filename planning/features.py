"""What the planner knows of each candidate besides the network's score: features a ranker may
combine with it, computed from the depth image alone (the estimated table, the observed points).

All in the camera frame, metres and degrees. Without a table estimate the table-relative
features are NaN (a ranker must treat them as missing)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from vgq.gripper import GripperGeometry, box_corners, gripper_boxes

from .collision import lowest_corner_height
from .sampler import Candidates, Scene, lookup_pixels, object_centres

#: name -> meaning, in column order
PLAN_FEATURES: dict[str, str] = {
    "score": "the network's P(success)",
    "width": "distance between the two contacts (m)",
    "seen": "1 when the second contact lies on an observed surface, 0 when it is inferred behind the object",
    "table_clearance": "lowest gripper point above the estimated table (m)",
    "tcp_height": "grasp centre above the estimated table (m)",
    "approach_tilt": "approach direction from straight down onto the table (deg)",
    "axis_tilt": "jaw axis from the table normal (deg): 90 = jaws close parallel to the table",
    "centre_offset": "TCP from its object's estimated centre of mass, along the table (m): the lever of its weight",
}


def table_features(frames: np.ndarray, up: np.ndarray, offset: float | None, gripper: GripperGeometry) -> dict:
    """Grasp frames (n, 4, 4) against a table plane ``up . x + offset = 0`` given in their frame
    (``up`` (3,) unit, away from the table): ``approach_tilt`` and ``axis_tilt`` (deg) against
    ``up``, and, unless ``offset`` is None (no plane: NaN), ``table_clearance`` (lowest gripper
    point) and ``tcp_height`` (m) above it."""
    z, x = frames[:, :3, 2], frames[:, :3, 0]
    out = {
        "approach_tilt": np.degrees(np.arccos(np.clip(-(z @ up), -1.0, 1.0))),
        "axis_tilt": np.degrees(np.arccos(np.clip(np.abs(x @ up), 0.0, 1.0))),
    }
    if offset is None:
        out["table_clearance"] = out["tcp_height"] = np.full(len(frames), np.nan)
    else:
        corners = box_corners(*gripper_boxes(gripper, swept=False))
        out["table_clearance"] = lowest_corner_height(frames, corners, up, offset)
        out["tcp_height"] = frames[:, :3, 3] @ up + offset
    return out


def centre_offsets(contacts: np.ndarray, tcp: np.ndarray, scene: Scene) -> np.ndarray:
    """(n,) distance (m) in the table plane (normal ``scene.up``) from each TCP (n, 3) to the
    estimated centre of mass of the object region its first contact (``contacts`` (n, 2, 3))
    lies on (:func:`planning.sampler.object_centres`); NaN when that contact is on no region."""
    if scene.centres is not None:
        labels, centres = scene.labels, scene.centres
    else:
        labels, centres = object_centres(scene.points, scene.objects, scene.table)
    r, c, inside = lookup_pixels(scene, contacts[:, 0])
    lab = np.where(inside, labels[r, c], 0)
    d = centres[lab] - tcp
    d -= (d @ scene.up)[:, None] * scene.up
    return np.where(lab > 0, np.linalg.norm(d, axis=1), np.nan)


def plan_features(
    cands: Candidates, scores: np.ndarray, scene: Scene, gripper: GripperGeometry
) -> dict[str, np.ndarray]:
    """:data:`PLAN_FEATURES` (each (n,) float64) of ``cands`` (camera frame) on ``scene``."""
    n = len(cands)
    table = scene.table
    out = {
        "score": np.asarray(scores, np.float64).reshape(n),
        "width": np.asarray(cands.widths, np.float64),
        "seen": np.asarray(cands.seen, np.float64),
        **table_features(cands.frames, scene.up, None if table is None else table.offset, gripper),
        "centre_offset": centre_offsets(cands.contacts, cands.frames[:, :3, 3], scene),
    }
    return {k: out[k] for k in PLAN_FEATURES}


def read_pool(path) -> dict:
    """The ``candidate_rows`` of a pool JSON (``planning.bench pool --json``: one list per column,
    one entry per judged candidate); ValueError naming a file that is not one."""
    try:
        rows = json.loads(Path(path).read_text())["candidate_rows"]
        if not isinstance(rows, dict):
            raise TypeError("candidate_rows is not an object")
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{path}: not a pool JSON of planning.bench pool --json ({e})") from None
    return rows
