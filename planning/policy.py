"""Plan grasps: sample, score with Fast-VGQ-CNN on cached windows, refine, suppress, rank.

:func:`plan` is the entry point an endpoint or the CLI calls. The image is first resampled
to the model's focal lengths (:func:`vgq.camera.resample_depth`) and, given the world's up
direction, turned level about the optical axis (:func:`vgq.camera.level_depth`); grasps are
planned and scored there and returned in the caller's pixels and camera frame.
"""

from __future__ import annotations

import time
from typing import Protocol

import numpy as np
from PIL import Image

from vgq.camera import (
    CameraMismatch,
    Intrinsics,
    focal_lengths,
    footprint,
    level_depth,
    level_roll,
    map_pixels,
    project,
    resample_depth,
    roll_matrix,
    source_pixels,
    tilt_outside_training,
)
from vgq.crop import grid_window_centers, origin_range, pose_uv, window_center, window_origin
from vgq.inpaint import crop_filled
from vgq.ood import flag_names, ood_flags
from vgq.placement import unknown_rows
from vgq.pose import canonical_quaternion, quaternion_from_matrix, roll_quaternions
from vgq.turns import pose_jaw_angles, turn_index, turned_poses, turned_view

from .calibration import p_hold as hold_probability
from .cloud import valid_mask
from .features import plan_features
from .placement import ImagePlacement
from .sampler import Candidates, analyse_scene, collision_checker, feasible_approach, frames_about_axis, sample_grasps
from .types import MAX_K, PlannedGrasp, PlanningError, PlanParams, PlanResult

# ----------------------------------------------------------------------------- inputs


def check_depth(depth, intr: Intrinsics) -> np.ndarray:
    """``depth`` as (H, W) float32 metres matching ``intr``; PlanningError naming the problem."""
    d = np.asarray(depth)
    if d.ndim != 2 or d.size == 0:
        raise PlanningError("depth", f"depth must be a 2-D image (H, W), got shape {d.shape}")
    if not np.issubdtype(d.dtype, np.number):
        raise PlanningError("depth", f"depth must be numeric, got dtype {d.dtype}")
    d = d.astype(np.float32)
    if d.shape != (intr.height, intr.width):
        raise PlanningError(
            "intrinsics", f"the image is {d.shape[1]}x{d.shape[0]} px but the intrinsics say {intr.width}x{intr.height}"
        )
    if (np.isfinite(d) & (d < 0)).any():
        raise PlanningError("depth", "depth has negative pixels; depth is in metres, >= 0 (0 = no reading)")
    if not valid_mask(d).any():
        raise PlanningError("depth", "the image has no valid depth (every pixel is 0 or non-finite)")
    return d


def camera_for(
    shape: tuple[int, int],
    model: Intrinsics,
    fx: float | None = None,
    fy: float | None = None,
    cx: float | None = None,
    cy: float | None = None,
) -> Intrinsics:
    """The intrinsics (pixels) of an (H, W) image: each value given, else the focal lengths of
    :func:`vgq.camera.focal_lengths` (as at the service's upload) and, when the image has the
    model's size, its principal point, otherwise the image centre. PlanningError
    ``intrinsics`` for values no camera has."""
    h, w = shape
    same = (h, w) == (model.height, model.width)
    fx, fy = focal_lengths(fx, fy, model)
    try:
        return Intrinsics(
            fx=fx,
            fy=fy,
            cx=cx if cx is not None else (model.cx if same else (w - 1) / 2),
            cy=cy if cy is not None else (model.cy if same else (h - 1) / 2),
            width=w,
            height=h,
        )
    except ValueError as e:
        raise PlanningError("intrinsics", str(e)) from None


def check_k(k) -> int:
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 1 <= int(k) <= MAX_K:
        raise PlanningError("k", f"k must be an integer in [1, {MAX_K}], got {k!r}")
    return int(k)


def roi_mask(roi, shape: tuple[int, int]) -> np.ndarray | None:
    """The region of interest as an (H, W) bool mask: None (the whole image), a box
    (u0, v0, u1, v1) in pixels (inclusive corners, clipped to the image) or a mask of the
    image's shape. PlanningError for a malformed or empty region."""
    if roi is None:
        return None
    h, w = shape
    a = np.asarray(roi)
    if a.shape == (h, w):
        m = a.astype(bool)
    elif a.shape == (4,) and np.issubdtype(a.dtype, np.number) and np.isfinite(a.astype(float)).all():
        u0, v0, u1, v1 = a.astype(float)
        if u1 < u0 or v1 < v0:
            raise PlanningError("roi", f"roi box (u0, v0, u1, v1) = {tuple(a.tolist())} needs u0 <= u1 and v0 <= v1")
        c0, c1 = int(np.ceil(max(u0, 0))), int(np.floor(min(u1, w - 1)))
        r0, r1 = int(np.ceil(max(v0, 0))), int(np.floor(min(v1, h - 1)))
        m = np.zeros((h, w), bool)
        if c0 <= c1 and r0 <= r1:
            m[r0 : r1 + 1, c0 : c1 + 1] = True
    else:
        raise PlanningError("roi", f"roi must be a box (u0, v0, u1, v1) or a {h}x{w} mask, got shape {a.shape}")
    if not m.any():
        raise PlanningError("roi", "the region of interest is empty (it covers no pixel of the image)")
    return m


# ----------------------------------------------------------------------------- scoring


def grasp_rows(frames: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Grasp rows (n, 7) (u, v, z, qw, qx, qy, qz) of frames (n, 4, 4) camera <- grasp."""
    uvz = project(frames[:, :3, 3], intr)
    q = quaternion_from_matrix(frames[:, :3, :3]) if len(frames) else np.zeros((0, 4))
    return np.column_stack([uvz, q])


def frame_from_row(row: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """The 4 x 4 grasp frame (camera frame) of a grasp row (u, v, z, qw, qx, qy, qz)."""
    from vgq.camera import deproject
    from vgq.pose import matrix_from_quaternion

    r = np.asarray(row, dtype=np.float64)
    T = np.eye(4)
    T[:3, :3] = matrix_from_quaternion(r[3:7])
    T[:3, 3] = deproject(r[None, :3], intr)[0]
    return T


def cover_windows(uv: np.ndarray, geom) -> np.ndarray:
    """Window centres (n, 2) for grasps at pixels ``uv`` (n, 2): few windows, each grasp
    within +-kappa (per axis) of its window's centre, as in the training crops. Greedy set
    cover: the window (centred on a grasp, or on a grasp shifted by kappa / 2 diagonally,
    snapped to the pixel grid as :func:`vgq.crop.crop` does) holding the most grasps not yet
    covered, until all are. Usually one or two windows per object, against up to four of the
    fixed grid."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if len(uv) == 0:
        return uv.copy()
    k = geom.kappa_px
    shifts = np.array([[0, 0], [1, 1], [1, -1], [-1, 1], [-1, -1]]) * (k / 2)
    org = window_origin((uv[None] + shifts[:, None]).reshape(-1, 2), geom)  # integer top-left pixels
    # distinct windows in (u, v) lexicographic order, through one integer key per window
    lo_o = org.min(axis=0)
    span = org.max(axis=0) - lo_o + 1
    keys = np.unique((org[:, 0] - lo_o[0]) * span[1] + (org[:, 1] - lo_o[1]))
    org = np.stack([keys // span[1] + lo_o[0], keys % span[1] + lo_o[1]], axis=1)
    # window o holds grasp uv when |centre(o) - uv| <= kappa per axis: o within [lo, hi]
    lo, hi = (b.astype(np.int64) for b in origin_range(uv, geom))
    covers = (org[:, :1] >= lo[:, 0]) & (org[:, :1] <= hi[:, 0]) & (org[:, 1:] >= lo[:, 1]) & (org[:, 1:] <= hi[:, 1])
    counts_of = covers.astype(np.float32)  # (c, n); counts_of . left: grasps left in each window (exact)
    cand = window_center(org, geom)
    out = np.empty_like(uv)
    left = np.ones(len(uv), np.float32)
    while left.any():
        best = int(np.argmax(np.einsum("cn,n->c", counts_of, left)))  # not a BLAS gemv: no thread wake-ups
        take = covers[best] & (left > 0)
        if not take.any():  # cannot happen: every grasp's own window covers it
            raise RuntimeError("window cover failed")
        out[take] = cand[best]
        left[take] = 0.0
    return out


class WindowStore(Protocol):
    """Encoded windows of one image kept beyond one plan (the service's image cache), keyed
    by the window's integer top-left pixel (u, v) in the image at the model's focal lengths.
    A term is the encoder's (D,) float32 output for :func:`vgq.inpaint.crop_filled` of
    that window; the float is the window's missing-depth fraction."""

    def lookup(self, origins: list[tuple[int, int]]) -> dict[tuple[int, int], tuple[np.ndarray, float]]:
        """The windows among ``origins`` already encoded."""
        ...

    def keep(self, new: dict[tuple[int, int], tuple[np.ndarray, float]]) -> None:
        """Windows this plan just encoded."""
        ...


class WindowScorer:
    """Scores grasp rows on one image: each grasp goes to a window (``windows``: "cover",
    :func:`cover_windows` of the first batch scored, later grasps to the nearest of those
    that holds them; or "grid", :func:`vgq.crop.grid_window_centers`); each window is
    cropped and encoded once (all new windows in one batched encoder call) and cached for
    later calls (the CEM refinement). ``store``: windows encoded before (taken from it, not
    encoded again; ``reused`` counts them) and kept after (those this scorer encodes)."""

    def __init__(
        self,
        model,
        depth: np.ndarray,
        windows: str = "cover",
        store: WindowStore | None = None,
        placement: ImagePlacement | None = None,
    ):
        if windows not in ("cover", "grid"):
            raise ValueError(f"windows must be 'cover' or 'grid', got {windows!r}")
        self.windows = windows
        self.model = model
        #: a placement head's (``vgq.placement``): the image's analysis, whose rows follow the pose
        #: columns (None for a placement head: unknown rows; for any other head: nothing appended)
        self.placement = placement
        self.reads_placement = bool(getattr(getattr(model, "card", None), "placement_columns", ()))
        self.depth = depth
        self.geom = model.geometry
        self.store = store
        self.terms: dict[tuple[float, float], np.ndarray] = {}
        self.actual: dict[tuple[float, float], np.ndarray] = {}
        self.missing: dict[tuple[float, float], float] = {}
        self.reused = 0
        self.scored_poses: list[np.ndarray] = []  # the head's pose rows of every score() call, in order
        self.encode_seconds = 0.0
        self.score_seconds = 0.0

    def _encode(self, keys: list[tuple[float, float]]) -> None:
        new = [k for k in keys if k not in self.terms]
        if not new:
            return
        t = time.perf_counter()
        origin = {k: tuple(int(x) for x in window_origin(np.asarray(k)[None], self.geom)[0]) for k in new}
        if self.store is not None:
            known = self.store.lookup([origin[k] for k in new])
            for k in new:
                if origin[k] in known:
                    term, frac = known[origin[k]]
                    self.terms[k] = np.asarray(term, np.float32).reshape(-1)
                    self.actual[k] = window_center(np.asarray(origin[k]), self.geom)
                    self.missing[k] = float(frac)
                    self.reused += 1
            new = [k for k in new if k not in self.terms]
        imgs = []
        for k in new:
            # the service's and the crop stage's input: missing depth filled (vgq.inpaint), then resized
            img, actual, frac = crop_filled(self.depth, origin[k], self.geom)
            imgs.append(img)
            self.actual[k] = actual
            self.missing[k] = frac
        if new:
            terms = self.model.encode(np.stack(imgs))  # the service's encoder call (service.runtime)
            for k, term in zip(new, terms):
                self.terms[k] = term
            if self.store is not None:
                self.store.keep({origin[k]: (self.terms[k], self.missing[k]) for k in new})
        self.encode_seconds += time.perf_counter() - t

    def _centres(self, uv: np.ndarray) -> np.ndarray:
        if self.windows == "grid":
            return grid_window_centers(uv, self.depth.shape, self.geom)
        out = np.empty_like(uv)
        left = np.ones(len(uv), bool)
        if self.actual:
            known = np.array(list(self.actual))  # keys are actual centres (cover mode)
            d = np.abs(known[:, None] - uv[None]).max(axis=2)  # (w, n)
            ok = d <= self.geom.kappa_px + 1e-9
            has = ok.any(axis=0)
            out[has] = known[np.argmin(np.where(ok, d, np.inf), axis=0)[has]]
            left = ~has
        if left.any():
            out[left] = cover_windows(uv[left], self.geom)
        return out

    def score(self, rows: np.ndarray, placement_rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(P(success) (n,), fraction of missing depth in each grasp's window (n,)) of grasp rows (n, 7)
        (u, v, z, qw, qx, qy, qz); a placement head's rows also get ``placement_rows`` (n, 6) (None:
        the scorer's analysis's rows of the same grasps)."""
        if len(rows) == 0:
            return np.zeros(0), np.zeros(0)
        centres = self._centres(rows[:, :2])
        keys = [tuple(c) for c in centres.tolist()]
        self._encode(list(dict.fromkeys(keys)))
        t = time.perf_counter()
        actual = np.array([self.actual[k] for k in keys])
        poses = np.empty((len(rows), 7), np.float32)
        poses[:, :2] = pose_uv(rows[:, :2], actual, self.geom)
        poses[:, 2:] = rows[:, 2:]
        if self.reads_placement:  # the head reads each grasp's place on its object after its pose
            if placement_rows is None:
                placement_rows = (
                    self.placement.rows(rows[:, :3], rows[:, 3:7])
                    if self.placement is not None
                    else unknown_rows(len(rows))
                )
            poses = np.hstack([poses, placement_rows]).astype(np.float32)
        self.scored_poses.append(poses)
        # one head call per window with its one encoding, as the service scores: a stack of each
        # grasp's own copy (17,408 floats per grasp for a jaw-grid head) took 2.3x as long for 256
        groups: dict[tuple[float, float], list[int]] = {}
        for i, k in enumerate(keys):
            groups.setdefault(k, []).append(i)
        p = np.empty(len(rows), np.float64)
        for k, ix in groups.items():
            ix = slice(None) if len(groups) == 1 else np.asarray(ix)
            p[ix] = self.model.score(np.asarray(self.terms[k], np.float32).reshape(1, -1), poses[ix]).reshape(-1)
        self.score_seconds += time.perf_counter() - t
        return p, np.array([self.missing[k] for k in keys])


class TurnedScorer:
    """:class:`WindowScorer`'s job for a model trained on windows turned towards the jaw
    (``CropGeometry.jaw_turns``, :mod:`vgq.turns`): each grasp is scored by a WindowScorer of the
    image turned by its turn (the camera rolled, :func:`vgq.camera.level_depth`), its (u, v) and
    orientation expressed in that turned camera, as datagen's crops were cut. ``intr``: the
    image's intrinsics; ``store`` serves the unturned windows (turn 0) only."""

    def __init__(
        self,
        model,
        depth: np.ndarray,
        intr: Intrinsics,
        windows: str = "cover",
        store: WindowStore | None = None,
        placement: ImagePlacement | None = None,
    ):
        self.model, self.depth, self.intr, self.windows, self.store = model, depth, intr, windows, store
        self.placement = placement  # of the unturned image: placement rows do not turn
        self.turns = model.geometry.jaw_turns
        self.scorers: dict[int, tuple[WindowScorer, Intrinsics, float]] = {}
        self.scored_poses: list[np.ndarray] = []  # the head's pose rows of every score() call, in order
        WindowScorer(model, depth, windows)  # the same check of ``windows``

    def _scorer(self, turn: int) -> tuple[WindowScorer, Intrinsics, float]:
        if turn not in self.scorers:
            depth, canvas, roll = turned_view(self.depth, self.intr, turn, self.turns)
            store = self.store if turn == 0 else None
            self.scorers[turn] = (WindowScorer(self.model, depth, self.windows, store), canvas, roll)
        return self.scorers[turn]

    def score(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(P(success) (n,), fraction of missing depth in each grasp's window (n,)) of grasp rows
        (n, 7) (u, v, z, qw, qx, qy, qz) in the image's camera."""
        if len(rows) == 0:
            return np.zeros(0), np.zeros(0)
        index = turn_index(pose_jaw_angles(rows[:, :2], rows[:, 2], rows[:, 3:7], self.intr), self.turns)
        p, missing = np.empty(len(rows)), np.empty(len(rows))
        place = self.placement.rows(rows[:, :3], rows[:, 3:7]) if self.placement is not None else None
        poses = None
        for t in np.unique(index).tolist():
            ix = np.flatnonzero(index == t)
            scorer, canvas, roll = self._scorer(t)
            turned = np.array(rows[ix], dtype=np.float64)
            turned[:, :2], turned[:, 3:7] = turned_poses(turned[:, :2], turned[:, 3:7], self.intr, canvas, roll)
            p[ix], missing[ix] = scorer.score(turned, None if place is None else place[ix])
            if poses is None:
                poses = np.empty((len(rows), scorer.scored_poses[-1].shape[1]), np.float32)
            poses[ix] = scorer.scored_poses[-1]
        self.scored_poses.append(poses)
        return p, missing

    @property
    def terms(self) -> list:
        """Every window encoded or reused, over all turns (``len`` counts them)."""
        return [k for s, _, _ in self.scorers.values() for k in s.terms]

    @property
    def reused(self) -> int:
        return sum(s.reused for s, _, _ in self.scorers.values())

    @property
    def encode_seconds(self) -> float:
        return sum(s.encode_seconds for s, _, _ in self.scorers.values())

    @property
    def score_seconds(self) -> float:
        return sum(s.score_seconds for s, _, _ in self.scorers.values())


def window_scorer(
    model, depth: np.ndarray, intr: Intrinsics, windows: str = "cover", store: WindowStore | None = None
) -> WindowScorer | TurnedScorer:
    """The scorer of grasp rows on one image (``intr``: its intrinsics) that suits ``model``'s
    crop geometry: windows of the image as it is, or turned towards each grasp's jaw. A placement
    head (``card.placement_columns``) gets the image's analysis (:mod:`planning.placement`), each
    candidate's placement row computed from its own (u, v, z, q) in this image."""
    reads = bool(getattr(getattr(model, "card", None), "placement_columns", ()))
    placement = ImagePlacement.analyse(depth, intr) if reads else None
    if model.geometry.jaw_turns:
        return TurnedScorer(model, depth, intr, windows, store, placement)
    return WindowScorer(model, depth, windows, store, placement)


# ----------------------------------------------------------------------------- selection


def nms(frames: np.ndarray, scores: np.ndarray, k: int, distance: float, angle: float) -> np.ndarray:
    """Indices of at most ``k`` grasps, highest ``scores`` (any ranking value) first, none of
    which is within ``distance`` (TCP, metres) and ``angle`` (jaw axis, radians, sign ignored)
    of a better kept one."""
    order = np.argsort(-scores, kind="stable")
    c, a = frames[:, :3, 3], frames[:, :3, 0]
    cos_lim = np.cos(angle)
    kept: list[int] = []
    block = max(4 * k, 32)  # candidates judged against each other at once, best first
    for s in range(0, len(order), block):
        idx = order[s : s + block]
        cand = np.concatenate([np.asarray(kept, dtype=np.int64), idx])  # kept ones first
        close = np.linalg.norm(c[cand][:, None] - c[idx][None], axis=2) < distance
        same = close & (np.abs(a[cand] @ a[idx].T) > cos_lim)  # (len(kept) + len(idx), len(idx))
        rows = list(range(len(kept)))  # rows of the kept candidates in `same`
        for j in range(len(idx)):
            if not same[rows, j].any():
                kept.append(int(idx[j]))
                rows.append(len(cand) - len(idx) + j)
                if len(kept) >= k:
                    return np.asarray(kept, dtype=np.int64)
    return np.asarray(kept, dtype=np.int64)


def cem_refine(
    cands: Candidates,
    scores: np.ndarray,
    missing: np.ndarray,
    scorer: WindowScorer,
    scene,
    checker,
    params: PlanParams,
    rng: np.random.Generator,
    intr: Intrinsics,
):
    """Cross-entropy refinement of the approach (rotation omega about the jaw axis, which
    keeps the contacts): each iteration draws ``cem_samples`` rotations of the
    ``cem_elites`` best grasps from N(0, sigma) (sigma the spread of the elites' last
    gains, at first ``cem_sigma``), keeps the feasible collision-free ones and adds them to
    the pool. Returns the grown (candidates, scores, missing)."""
    sigma = params.cem_sigma
    for _ in range(params.cem_iterations):
        elite = np.argsort(-scores)[: params.cem_elites]
        pick = elite[rng.integers(0, len(elite), params.cem_samples)]
        om = rng.normal(0.0, sigma, params.cem_samples)
        frames = frames_about_axis(cands.frames[pick], om)
        ok = feasible_approach(frames, scene, params)
        ok[ok] = ~checker.collides(frames[ok])
        if not ok.any():
            sigma *= 0.5
            continue
        new = Candidates(frames[ok], cands.contacts[pick[ok]], cands.widths[pick[ok]], cands.seen[pick[ok]])
        p, miss = scorer.score(grasp_rows(new.frames, intr))
        better = p > scores[pick[ok]]
        sigma = float(np.std(om[ok][better])) if better.sum() >= 2 else 0.5 * sigma
        sigma = max(sigma, np.radians(2.0))
        cands = Candidates.concat([cands, new])
        scores, missing = np.concatenate([scores, p]), np.concatenate([missing, miss])
    return cands, scores, missing


# ----------------------------------------------------------------------------- plan


def collision_reason(counts: dict, params: PlanParams) -> str:
    """Why no checked candidate was collision-free, from the sampler's counts."""
    table, points = counts["table_collisions"], counts["point_collisions"]
    margin = f"the fingertips would come within {1000 * params.table_margin:g} mm of the table"
    if points == 0:
        return f"every candidate grasp collides with the table: {margin} (too flat or too low to grasp from above?)"
    if table == 0:
        return "every candidate grasp collides with the observed points (no room for the fingers)"
    return f"every candidate grasp collides: {table} with the table ({margin}), {points} with the observed points"


def check_seed(seed) -> None:
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0):
        raise PlanningError("seed", f"seed must be a non-negative integer or None, got {seed!r}")


def plan(
    depth,
    intrinsics: Intrinsics | None,
    model,
    k: int = 5,
    roi=None,
    seed: int | None = 0,
    params: PlanParams | None = None,
    up=None,
) -> PlanResult:
    """The best ``k`` distinct grasps on ``depth`` (H, W, metres, 0 = no reading) taken with
    ``intrinsics`` (None: the model's camera), scored by ``model`` (a
    :class:`service.runtime.FastModel`); ``roi`` a box (u0, v0, u1, v1) or (H, W) mask of
    the caller's image where grasps may lie; ``seed`` makes the sampling repeatable; ``up``
    (3,) the world's up direction in the camera frame (None: the camera is level).

    Raises :class:`PlanningError` (field ``depth``, ``intrinsics``, ``k``, ``roi``, ``seed``
    or ``up``) for input it cannot plan on. When no grasp is found the result has no grasps
    and a ``reason``."""
    t0 = time.perf_counter()
    model_intr = model.card.intrinsics
    cam = intrinsics or model_intr
    k = check_k(k)
    check_seed(seed)
    d = check_depth(depth, cam)
    roi_m = roi_mask(roi, d.shape)
    if roi_m is not None and not (roi_m & valid_mask(d)).any():
        raise PlanningError("roi", "the region of interest has no valid depth")
    try:
        roll = 0.0 if up is None else level_roll(up)
    except ValueError as e:
        raise PlanningError("up", str(e)) from None
    try:
        d_model, intr = resample_depth(np.where(np.isfinite(d), d, 0.0).astype(np.float32), cam, model_intr)
    except CameraMismatch as e:
        raise PlanningError("intrinsics", str(e)) from None
    d_model, intr = level_depth(d_model, intr, roll)
    return plan_resampled(d_model, intr, cam, model, k, roi_m, seed, params, started=t0, up=up)


def plan_resampled(
    depth: np.ndarray,
    intrinsics: Intrinsics,
    camera: Intrinsics,
    model,
    k: int = 5,
    roi=None,
    seed: int | None = 0,
    params: PlanParams | None = None,
    windows: WindowStore | None = None,
    started: float | None = None,
    up=None,
) -> PlanResult:
    """:func:`plan` on an image already at the model's focal lengths: ``depth`` (H', W')
    metres (0 = no reading) with ``intrinsics`` (what :func:`vgq.camera.resample_depth`
    returns; the service caches uploads so), ``camera`` the caller's camera, in whose
    pixels ``roi`` is given and the grasps are answered. ``windows``: encoded windows of
    this image kept between plans (:class:`WindowStore`): those it holds are not encoded
    again (``counts["windows_reused"]``), the new ones are added. ``started``: the
    ``perf_counter`` time the request began (``seconds["resample"]`` runs from it). ``up``: the
    world's up direction in ``camera``'s frame when ``depth`` was turned level by its
    :func:`vgq.camera.level_roll` (:func:`vgq.camera.level_depth`; None: not turned); the
    grasps are answered in ``camera``'s frame."""
    params = params or PlanParams()
    t0 = time.perf_counter() if started is None else started
    try:
        roll = 0.0 if up is None else level_roll(up)
    except ValueError as e:
        raise PlanningError("up", str(e)) from None
    k = check_k(k)
    check_seed(seed)
    d_model, intr, cam = np.asarray(depth, dtype=np.float32), intrinsics, camera
    if d_model.shape != (intr.height, intr.width):
        raise PlanningError(
            "intrinsics",
            f"the image is {d_model.shape[1]}x{d_model.shape[0]} px but the intrinsics say {intr.width}x{intr.height}",
        )
    if not valid_mask(d_model).any():
        raise PlanningError("depth", "the image has no valid depth (every pixel is 0 or non-finite)")
    roi_m = roi_mask(roi, (cam.height, cam.width))
    if roi_m is not None and roll != 0.0:  # each level pixel takes the mask's value at its ray's pixel
        src = np.clip(np.rint(source_pixels(intr, cam, roll)), 0, (cam.width - 1, cam.height - 1)).astype(np.int64)
        inside = footprint(intr, cam, roll)
        m = np.zeros(inside.shape, dtype=bool)
        m[inside] = roi_m[src[inside][:, 1], src[inside][:, 0]]
        roi_m = m
    elif roi_m is not None and intr != cam:
        img = Image.fromarray(roi_m.astype(np.uint8) * 255).resize((intr.width, intr.height), Image.Resampling.NEAREST)
        roi_m = np.asarray(img) > 127
    if roi_m is not None and not (roi_m & valid_mask(d_model)).any():
        raise PlanningError("roi", "the region of interest has no valid depth")
    rng = np.random.default_rng(seed)
    seconds = {"resample": time.perf_counter() - t0}
    ranker = getattr(model, "planner_ranker", None)  # planning.ranker: None orders by the score
    ranked_by = "score" if ranker is None else "ranker"

    t = time.perf_counter()
    scene = analyse_scene(d_model, intr, params, rng, roi_m)
    seconds["scene"] = time.perf_counter() - t
    counts = {"object_pixels": int(scene.objects.sum()), "table": scene.table is not None}
    version = getattr(model, "version", "")
    if counts["object_pixels"] == 0:
        where = " in the region of interest" if roi_m is not None else ""
        return PlanResult((), f"no object points above the table{where}", counts, seconds, version, ranked_by=ranked_by)

    t = time.perf_counter()
    checker = collision_checker(scene, params, rng)
    cands, c = sample_grasps(scene, params, rng, checker)
    counts.update(c)
    seconds["sample"] = time.perf_counter() - t
    if len(cands) == 0:
        reason = (
            "no antipodal contact pair within the jaw opening and friction cone"
            if c["pairs"] == 0
            else "no feasible approach (every one from under the table or behind the object)"
            if c["approaches"] == 0
            else collision_reason(c, params)
        )
        return PlanResult((), reason, counts, seconds, version, ranked_by=ranked_by)

    scorer = window_scorer(model, d_model, intr, params.windows, windows)
    scores, missing = scorer.score(grasp_rows(cands.frames, intr))
    if params.cem_iterations:
        t = time.perf_counter()
        cands, scores, missing = cem_refine(cands, scores, missing, scorer, scene, checker, params, rng, intr)
        seconds["cem"] = time.perf_counter() - t
        counts["after_cem"] = len(cands)
    seconds["encode"] = scorer.encode_seconds
    seconds["score"] = scorer.score_seconds
    counts["windows"] = len(scorer.terms)
    if windows is not None:
        counts["windows_reused"] = scorer.reused

    t = time.perf_counter()
    cal = getattr(model, "planner_calibration", None)  # planning.calibration: p_hold; None: no p_hold
    feats = plan_features(cands, scores, scene, params.gripper) if ranker is not None or cal is not None else None
    utility = ranker.value(feats) if ranker is not None else None
    keep = nms(cands.frames, scores if utility is None else utility, k, params.nms_distance, params.nms_angle)
    top = cands[keep]
    rows = grasp_rows(top.frames, intr)
    tilted = tilt_outside_training(up, model.card.tilt_range()) if up is not None else False
    flags = ood_flags(rows, d_model, model.card.z_range()[0], missing[keep] > params.window_missing_fraction, tilted)
    uv = map_pixels(rows[:, :2], intr, cam, -roll) if intr != cam or roll != 0.0 else rows[:, :2]
    p_hold = hold_probability(cal, {k: v[keep] for k, v in feats.items()}) if cal is not None else [None] * len(keep)
    q, frames, contacts = rows[:, 3:7], top.frames, top.contacts
    if roll != 0.0:  # from the level camera's frame back to the caller's
        R = roll_matrix(roll)
        q = canonical_quaternion(roll_quaternions(q, -roll))
        frames = frames.copy()
        frames[:, :3, :] = np.einsum("ij,njk->nik", R, frames[:, :3, :])
        contacts = contacts @ R.T
    grasps = tuple(
        PlannedGrasp(
            u=float(uv[i, 0]),
            v=float(uv[i, 1]),
            z=float(rows[i, 2]),
            q=tuple(float(x) for x in q[i]),
            pose=frames[i].copy(),
            width=float(top.widths[i]),
            contacts=contacts[i].copy(),
            score=float(scores[keep[i]]),
            ood_flags=int(flags[i]),
            ood=tuple(flag_names(int(flags[i]))),
            p_hold=None if p_hold[i] is None else float(p_hold[i]),
        )
        for i in range(len(keep))
    )
    seconds["select"] = time.perf_counter() - t
    seconds["total"] = time.perf_counter() - t0
    everything = {
        "frames": cands.frames,
        "contacts": cands.contacts,
        "scores": scores,
        "poses": np.concatenate(scorer.scored_poses),  # the head's pose rows (window-relative u, v)
        # frames, contacts and poses above: in the (level) camera frame the plan was made in
        "widths": cands.widths,
        "seen": cands.seen,
        "scene": scene,  # what the sampler estimated (table, points): planning.features reads it
        "utility": utility,  # the model's planner ranker's (None: the planner ranked by the score)
    }
    return PlanResult(grasps, None, counts, seconds, version, everything, ranked_by)
