"""The planner's settings, errors and results.

Frames and units: camera frame (OpenCV: x right, y down, z along the principal ray),
metres, radians; pixels (u = column, v = row) of the image as given by the caller;
quaternions (w, x, y, z), canonical (w >= 0). A grasp frame has x along the jaw axis
(contact 0 -> contact 1), z the approach direction and its origin at the TCP, midway
between the contacts (as in datagen).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from vgq.gripper import GripperGeometry

#: the most grasps one plan may return
MAX_K = 100


class PlanningError(ValueError):
    """Input the planner cannot work with; ``field`` names it (``depth``, ``intrinsics``,
    ``k``, ``roi``, ``seed``), so an endpoint can answer 422 naming it."""

    def __init__(self, field: str, message: str):
        super().__init__(message)
        self.field = field


@dataclass(frozen=True)
class PlanParams:
    """Planner settings (metres, radians).

    Sampling: ``num_candidates`` collision-free grasps are sought (the network scores them
    all), from at most ``max_seeds`` contact seeds per round; each contact pair gets
    ``num_approaches`` approach directions (rotations omega about the jaw axis) within
    ``max_approach_tilt`` of the straight-down approach, never from under the table or
    from behind the object as the camera sees it (psi < ``max_psi``).
    Contacts: the jaw axis lies within the friction cone (``friction_coef``) of the first
    contact's inward normal (and of the second's where it is visible); the contacts are
    ``min_width`` to ``max_width - 2 * jaw_clearance`` apart.
    Scene: the table is the dominant plane (RANSAC, ``table_inlier_distance``); points more
    than ``object_height`` above it are the objects. The gripper's lowest point (a fingertip)
    stays ``table_margin`` above the estimated table: a robot's execution error (datagen's
    trials: 5 mm per axis) must not put the fingers into it.
    ``top_view_cell``: the grid (metres) on which the objects' tops are read as seen from above
    to end a contact line's hidden part (:class:`planning.sampler.TopView`); None: the camera's
    height field alone (space behind an observed surface is solid).
    Results: two grasps are the same (non-maximum suppression) when their centres are
    closer than ``nms_distance`` and their jaw axes within ``nms_angle``.
    Windows: ``windows`` "cover" places few windows over the candidates (see
    :func:`planning.policy.cover_windows`), "grid" uses the fixed grid of
    :func:`vgq.crop.grid_window_centers`.
    ``cem_iterations`` > 0 refines the best grasps' approach angle with a cross-entropy
    method (``cem_samples`` per iteration around the ``cem_elites`` best).
    """

    num_candidates: int = 256
    max_seeds: int = 600
    max_rounds: int = 3
    num_approaches: int = 5
    max_approach_tilt: float = np.radians(60.0)
    max_psi: float = np.radians(80.0)
    friction_coef: float = 0.5
    cone_fraction: float = 0.8
    min_width: float = 0.0025
    max_centre_offset: float | None = None
    jaw_clearance: float = 0.002
    march_step: float = 0.0015
    surface_tolerance: float = 0.003
    top_view_cell: float | None = 0.0025
    table_inlier_distance: float = 0.003
    object_height: float = 0.004
    table_margin: float = 0.005
    point_clearance: float = 0.001
    collision_voxel: float = 0.004
    max_collision_points: int = 2000
    ransac_iterations: int = 40
    ransac_points: int = 1500
    min_table_fraction: float = 0.1
    normal_window: int = 5
    nms_distance: float = 0.01
    nms_angle: float = np.radians(30.0)
    cem_iterations: int = 0
    cem_samples: int = 64
    cem_elites: int = 8
    cem_sigma: float = np.radians(20.0)
    window_missing_fraction: float = 0.5
    windows: str = "cover"
    gripper: GripperGeometry = field(default_factory=GripperGeometry)

    def __post_init__(self) -> None:
        for name in (
            "num_candidates",
            "max_seeds",
            "max_rounds",
            "num_approaches",
            "ransac_iterations",
            "ransac_points",
            "max_collision_points",
            "cem_samples",
            "cem_elites",
        ):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"PlanParams.{name} must be >= 1, got {getattr(self, name)}")
        if self.cem_iterations < 0:
            raise ValueError(f"PlanParams.cem_iterations must be >= 0, got {self.cem_iterations}")
        if self.normal_window < 1 or self.normal_window % 2 == 0:
            raise ValueError(f"PlanParams.normal_window must be an odd number >= 1, got {self.normal_window}")
        for name in ("march_step", "friction_coef", "max_approach_tilt", "max_psi", "nms_angle", "cone_fraction"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"PlanParams.{name} must be > 0, got {v}")
        if self.top_view_cell is not None and not (np.isfinite(self.top_view_cell) and self.top_view_cell > 0):
            raise ValueError(f"PlanParams.top_view_cell must be > 0 or None, got {self.top_view_cell}")
        if not 0 <= self.min_width < self.max_opening:
            raise ValueError(f"PlanParams.min_width must be in [0, {self.max_opening}), got {self.min_width}")

    @property
    def max_opening(self) -> float:
        """The widest object the jaws close on (metres): the opening less a clearance each side."""
        return self.gripper.max_width - 2 * self.jaw_clearance


@dataclass(frozen=True)
class PlannedGrasp:
    """One planned grasp (camera frame, metres; pixels of the caller's image).

    ``row`` is the service's grasp row (u, v, z, qw, qx, qy, qz); ``pose`` the 4 x 4 grasp
    frame in the camera frame; ``contacts`` (2, 3) the observed contact points (contact 0,
    contact 1 along the jaw axis); ``width`` their distance; ``score`` the network's
    P(success); ``ood_flags`` the :mod:`vgq.ood` bitmask, ``ood`` its names; ``p_hold`` the
    probability that it survives the physics oracle's lift and shake, from the model's planner
    calibration (:mod:`planning.calibration`; None without one)."""

    u: float
    v: float
    z: float
    q: tuple[float, float, float, float]
    pose: np.ndarray
    width: float
    contacts: np.ndarray
    score: float
    ood_flags: int
    ood: tuple[str, ...]
    p_hold: float | None = None

    @property
    def row(self) -> np.ndarray:
        return np.array([self.u, self.v, self.z, *self.q])

    def to_dict(self) -> dict:
        return {
            "u": self.u,
            "v": self.v,
            "z": self.z,
            "q": list(self.q),
            "row": [float(x) for x in self.row],
            "pose": np.asarray(self.pose, dtype=float).round(9).tolist(),
            "width": self.width,
            "contacts": np.asarray(self.contacts, dtype=float).round(9).tolist(),
            "score": self.score,
            "ood_flags": self.ood_flags,
            "ood": list(self.ood),
            "p_hold": self.p_hold,
        }


@dataclass(frozen=True)
class PlanResult:
    """The top grasps, best first (possibly none, then ``reason`` says why), with counts
    of each stage and its seconds. ``ranked_by``: "ranker" when the model's planner ranker
    (:mod:`planning.ranker`) ordered them, "score" when the network's score did."""

    grasps: tuple[PlannedGrasp, ...]
    reason: str | None = None
    counts: dict = field(default_factory=dict)
    seconds: dict = field(default_factory=dict)
    model_version: str = ""
    #: every scored candidate (``frames`` (n, 4, 4), ``contacts`` (n, 2, 3), ``scores`` (n,),
    #: ``poses`` (n, 7): the head's pose rows, ``widths`` (n,), ``seen`` (n,) bool) and the
    #: sampler's ``scene`` estimate, for benchmarks (planning.features); not part of :meth:`to_dict`
    candidates: dict | None = field(default=None, repr=False, compare=False)
    ranked_by: str = "score"

    def to_dict(self) -> dict:
        return {
            "grasps": [g.to_dict() for g in self.grasps],
            "reason": self.reason,
            "counts": dict(self.counts),
            "seconds": {k: round(float(v), 6) for k, v in self.seconds.items()},
            "model_version": self.model_version,
            "ranked_by": self.ranked_by,
        }
