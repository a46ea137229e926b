"""6-DOF antipodal grasp candidates from a depth image (camera frame, metres, radians).

1. Back-project the image and estimate normals (:mod:`planning.cloud`); find the table as
   the dominant plane (RANSAC); the points above it (in the region of interest) are the
   objects.
2. Contact pairs: a seed contact on the objects (silhouette and side pixels, whose normals
   are not vertical, are drawn more often); a jaw axis inside the friction cone of its
   inward normal; the opposite contact where that line leaves the object. The depth image
   is read as a height field seen from the camera: space behind an observed surface is
   taken as solid, space in front of it as free, so the line leaves the object where it
   first comes out in front of the observed surface. With a table, the objects are also
   read as seen from above (:class:`TopView`): a point is solid only if it lies below the
   highest object point observed over its spot on the table, so the hidden far side of an
   object ends where its observed top ends (not at the end of its shadow), and the inside
   of an open container, whose top is its floor or was not seen, is free. A line that meets the table first,
   never leaves within the jaw opening, or leaves through a visible surface whose normal is
   outside the friction cone is dropped. Contact 1 may lie on a surface the camera does not
   see; then only contact 0's cone is checked (the network judges the rest).
3. Approaches: rotations omega about each jaw axis, around the straight-down approach
   (or the camera ray where the axis is near vertical), never from under the table or from
   behind the object as the camera sees it.
4. Collisions: the swept gripper may not enter the table or hold an observed point
   (:mod:`planning.collision`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from vgq.camera import Intrinsics

from .cloud import backproject, estimate_normals
from .collision import GripperCollision, TablePlane, fit_table, voxel_downsample
from .types import PlanParams


@dataclass
class Scene:
    """What the sampler knows of the image: points and normals (H, W, 3), their masks,
    the table (None when no plane holds ``min_table_fraction`` of the points) and the
    object mask (valid, above the table, inside the region of interest)."""

    depth: np.ndarray
    intr: Intrinsics
    points: np.ndarray
    valid: np.ndarray
    normals: np.ndarray
    normal_ok: np.ndarray
    table: TablePlane | None
    objects: np.ndarray
    labels: np.ndarray | None = None
    centres: np.ndarray | None = None
    top: TopView | None = None
    _seed_pool: tuple | None = None  # (candidate pixel indices, their normals, cumulative weights)

    @property
    def up(self) -> np.ndarray:
        """Unit 'up' (3,): the table normal, or towards the camera along the principal ray."""
        return self.table.normal if self.table is not None else np.array([0.0, 0.0, -1.0])


@dataclass
class TopView:
    """The objects seen from straight above the table: in each ``cell`` x ``cell`` square of a
    grid on the table plane, the height (metres above the table) of the highest object point
    observed over it, gaps of a cell closed (a grey closing); -inf where none was (camera frame: the
    grid's corner ``origin`` (3,) on the table, its unit axes ``e1``, ``e2`` (3,)).
    ``outward`` (n1, n2, 2): the unit outward normal (e1, e2 components) of the seen
    footprint's outline, from the gradient of the smoothed footprint (0 inside it)."""

    origin: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    cell: float
    heights: np.ndarray
    outward: np.ndarray

    @classmethod
    def build(cls, points: np.ndarray, table: TablePlane, cell: float) -> TopView | None:
        """The top view of object points (n, 3); None without points."""
        if len(points) == 0:
            return None
        n = table.normal.astype(np.float64)
        e1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(n, e1)
        p = np.asarray(points, dtype=np.float64)
        h = p @ n + table.offset
        a, b = p @ e1, p @ e2
        a0, b0 = a.min() - 2 * cell, b.min() - 2 * cell
        i = ((a - a0) / cell).astype(np.int64)
        j = ((b - b0) / cell).astype(np.int64)
        shape = (int(i.max()) + 3, int(j.max()) + 3)
        heights = np.full(shape[0] * shape[1], -np.inf)
        np.maximum.at(heights, i * shape[1] + j, h)  # by flat index: numpy's fast path for ufunc.at
        heights = heights.reshape(shape)
        heights = ndimage.grey_closing(heights, size=3, mode="constant", cval=-np.inf)
        smooth = ndimage.gaussian_filter(np.isfinite(heights).astype(np.float64), 1.0, mode="constant")
        g = -np.stack(np.gradient(smooth), axis=-1)
        outward = g / np.maximum(np.linalg.norm(g, axis=-1, keepdims=True), 1e-9)
        origin = a0 * e1 + b0 * e2 - table.offset * n
        return cls(origin, e1, e2, float(cell), heights, outward)

    def _cells(self, x: np.ndarray):
        """Grid indices (i, j) of points x (..., 3), clipped, and whether they fall on the grid."""
        d = np.asarray(x, dtype=np.float64) - self.origin
        return self._index(d @ self.e1, d @ self.e2)

    def _index(self, a: np.ndarray, b: np.ndarray):
        """Grid indices (i, j), clipped, and whether they fall on the grid, of points at
        ``a``, ``b`` (...,) metres along ``e1``, ``e2`` from ``origin``."""
        i = np.floor(a / self.cell).astype(np.int64)
        j = np.floor(b / self.cell).astype(np.int64)
        n1, n2 = self.heights.shape
        on = (i >= 0) & (i < n1) & (j >= 0) & (j < n2)
        return np.clip(i, 0, n1 - 1), np.clip(j, 0, n2 - 1), on

    def top(self, x: np.ndarray) -> np.ndarray:
        """Heights (...,) of the top view over points x (..., 3); -inf off the grid."""
        i, j, on = self._cells(x)
        return np.where(on, self.heights[i, j], -np.inf)

    def top_along(self, p: np.ndarray, axes: np.ndarray, ts: np.ndarray) -> np.ndarray:
        """Heights (n, T) of the top view over the points p + t * axis of lines from ``p``
        (n, 3) along ``axes`` (n, 3) at the steps ``ts`` (T,) metres; -inf off the grid."""
        d = np.asarray(p, dtype=np.float64) - self.origin
        a = (d @ self.e1)[:, None] + ts * (axes @ self.e1)[:, None]
        b = (d @ self.e2)[:, None] + ts * (axes @ self.e2)[:, None]
        i, j, on = self._index(a, b)
        return np.where(on, self.heights[i, j], -np.inf)

    def outline_normal(self, x: np.ndarray) -> np.ndarray:
        """The footprint outline's unit outward normal (..., 3) (in the table plane, camera
        frame) at points x (..., 3); 0 off the grid and far inside or outside the footprint."""
        i, j, on = self._cells(x)
        o = np.where(on[..., None], self.outward[i, j], 0.0)
        return o[..., :1] * self.e1 + o[..., 1:] * self.e2


@dataclass
class Candidates:
    """n grasps: frames (n, 4, 4) camera <- grasp, contacts (n, 2, 3), widths (n,) and
    whether contact 1 was seen (n,) bool."""

    frames: np.ndarray
    contacts: np.ndarray
    widths: np.ndarray
    seen: np.ndarray

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, idx) -> Candidates:
        return Candidates(self.frames[idx], self.contacts[idx], self.widths[idx], self.seen[idx])

    @classmethod
    def empty(cls) -> Candidates:
        return cls(np.zeros((0, 4, 4)), np.zeros((0, 2, 3)), np.zeros(0), np.zeros(0, bool))

    @classmethod
    def concat(cls, parts: list[Candidates]) -> Candidates:
        parts = [p for p in parts if len(p)]
        if not parts:
            return cls.empty()
        return cls(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("frames", "contacts", "widths", "seen")))


def masked_points(points: np.ndarray, mask: np.ndarray, where: np.ndarray | None = None) -> np.ndarray:
    """``points[mask]`` (n, 3) of an organised cloud (H, W, 3) and mask (H, W), gathered by
    flat index (several times faster than a boolean index over 3-vectors); ``where``:
    ``np.flatnonzero(mask)`` when already known."""
    where = np.flatnonzero(mask) if where is None else where
    return np.take(points.reshape(-1, 3), where, axis=0)


def find_table(
    points: np.ndarray, valid: np.ndarray, params: PlanParams, rng: np.random.Generator
) -> TablePlane | None:
    """The table under the objects: the dominant plane (RANSAC) of ``params.ransac_points`` of
    the valid ``points`` (H, W, 3, camera frame, metres) drawn at random, or None when there is
    none or it holds under ``params.min_table_fraction`` of them."""
    flat = np.flatnonzero(valid.ravel())
    if len(flat) == 0:
        return None
    sub = points.reshape(-1, 3)[flat[rng.integers(0, len(flat), size=min(params.ransac_points, len(flat)))]]
    table = fit_table(sub, rng, params.ransac_iterations, params.table_inlier_distance)
    if table is not None and table.inlier_fraction < params.min_table_fraction:
        return None
    return table


def analyse_scene(
    depth: np.ndarray, intr: Intrinsics, params: PlanParams, rng: np.random.Generator, roi: np.ndarray | None = None
) -> Scene:
    """Points, normals, table and object mask of ``depth`` (H, W, metres) seen with ``intr``;
    ``roi`` (H, W) bool restricts the objects (None: the whole image). Normals are computed
    only around the objects."""
    pts, valid = backproject(depth, intr)
    table = find_table(pts, valid, params, rng)
    objects = valid.copy()
    if table is not None:
        objects &= table.height(pts) > params.object_height
    if roi is not None:
        objects &= roi
    normals = np.zeros_like(pts)
    nok = np.zeros_like(valid)
    if objects.any():
        rows, cols = np.flatnonzero(objects.any(axis=1)), np.flatnonzero(objects.any(axis=0))
        m = params.normal_window // 2 + 2
        r0, r1 = max(rows[0] - m, 0), min(rows[-1] + m + 1, valid.shape[0])
        c0, c1 = max(cols[0] - m, 0), min(cols[-1] + m + 1, valid.shape[1])
        n, ok = estimate_normals(pts[r0:r1, c0:c1], valid[r0:r1, c0:c1], params.normal_window)
        normals[r0:r1, c0:c1], nok[r0:r1, c0:c1] = n, ok
    labels, centres = object_centres(pts, objects, table) if params.max_centre_offset is not None else (None, None)
    top = None
    if table is not None and params.top_view_cell is not None:
        top = TopView.build(masked_points(pts, objects), table, params.top_view_cell)
    return Scene(np.asarray(depth, np.float64), intr, pts, valid, normals, nok, table, objects, labels, centres, top)


def object_centres(points: np.ndarray, objects: np.ndarray, table: TablePlane | None) -> tuple[np.ndarray, np.ndarray]:
    """Connected object regions (H, W) int (0 = none, region i is label i) and a guess of
    each one's centre of mass (n + 1, 3), camera frame: the mean of its points dropped to
    half their height above the table (objects rest on it; without a table, the mean of
    its points). Row 0 is unused."""
    labels, n = ndimage.label(objects, structure=np.ones((3, 3)))
    centres = np.zeros((n + 1, 3))
    if n == 0:
        return labels, centres
    where = np.flatnonzero(objects)
    p = masked_points(points, objects, where)
    lab = labels.ravel()[where]
    cnt = np.maximum(np.bincount(lab, minlength=n + 1), 1).astype(float)
    for i in range(3):
        centres[:, i] = np.bincount(lab, weights=p[:, i], minlength=n + 1) / cnt
    if table is not None:
        # each point dropped onto the table, then raised to half its region's height: the mean
        # point moved along the normal by half the region's top less its mean height
        h = table.height(p)
        top = np.zeros(n + 1)
        top[1:] = h.max() if n == 1 else region_max(h, lab, n)
        mean_h = np.bincount(lab, weights=h, minlength=n + 1) / cnt
        centres += (0.5 * top - mean_h)[:, None] * table.normal
    return labels, centres


def region_max(values: np.ndarray, labels: np.ndarray, n: int) -> np.ndarray:
    """(n,) the largest of ``values`` (m,) in each region 1..n of ``labels`` (m,) (every region has
    a value; ``ndimage.maximum``'s result). The labels are sorted by a stable sort, a radix sort for
    16-bit labels: a sensor image's noise specks make hundreds of regions, where ``ndimage.maximum``'s
    comparison sort took ~0.4 ms per call."""
    order = np.argsort(labels.astype(np.uint16) if n <= 0xFFFF else labels, kind="stable")
    lab = labels[order]
    starts = np.flatnonzero(np.r_[True, lab[1:] != lab[:-1]])
    out = np.empty(n)
    out[lab[starts] - 1] = np.maximum.reduceat(values[order], starts)
    return out


def lookup_pixels(scene: Scene, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest pixel of points x (..., 3): (rows, cols, inside the image and in front)."""
    return _pixels(scene, x[..., 0], x[..., 1], x[..., 2])


def _pixels(scene: Scene, x: np.ndarray, y: np.ndarray, z: np.ndarray):
    """:func:`lookup_pixels` of points given by their coordinates x, y, z (...,) each."""
    with np.errstate(divide="ignore", invalid="ignore"):
        u = scene.intr.fx * x / z + scene.intr.cx
        v = scene.intr.fy * y / z + scene.intr.cy
    h, w = scene.valid.shape
    inside = (z > 1e-6) & (u > -0.5) & (u < w - 0.5) & (v > -0.5) & (v < h - 0.5)
    cols = np.clip(np.floor(np.where(inside, u, 0) + 0.5).astype(np.int64), 0, w - 1)
    rows = np.clip(np.floor(np.where(inside, v, 0) + 0.5).astype(np.int64), 0, h - 1)
    return rows, cols, inside


def _cone_axes(inward: np.ndarray, half_angle_tan: float, rng: np.random.Generator) -> np.ndarray:
    """Unit directions (n, 3) drawn uniformly (by area) inside cones of half-angle
    atan(``half_angle_tan``) around the unit ``inward`` (n, 3)."""
    ref = np.where(np.abs(inward[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(inward, ref)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(inward, t1)
    r = half_angle_tan * np.sqrt(rng.random(len(inward)))
    th = rng.uniform(0, 2 * np.pi, len(inward))
    a = inward + r[:, None] * (np.cos(th)[:, None] * t1 + np.sin(th)[:, None] * t2)
    return a / np.linalg.norm(a, axis=1, keepdims=True)


def seed_pool(scene: Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pixels a contact pair may start from (flat indices (n,): objects with a normal),
    their normals (n, 3) and the cumulative distribution (n,) of their draw: sides and
    silhouettes (normal away from 'up') are likelier to have an opposite contact, so a
    pixel weighs 0.1 + 1 - |n . up|. Computed once per scene (each sampling round draws from it)."""
    if scene._seed_pool is None:
        cand = np.flatnonzero((scene.objects & scene.normal_ok).ravel())
        n_all = scene.normals.reshape(-1, 3)[cand]
        cdf = np.cumsum(0.1 + (1.0 - np.abs(n_all @ scene.up)))
        if len(cdf):
            cdf /= cdf[-1]
        scene._seed_pool = (cand, n_all, cdf)
    return scene._seed_pool


def sample_contact_pairs(scene: Scene, n_seeds: int, params: PlanParams, rng: np.random.Generator):
    """Antipodal contact pairs from ``n_seeds`` seed contacts (see the module docstring).

    Returns ``(contacts (m, 2, 3), axes (m, 3) unit contact 0 -> 1, widths (m,), seen (m,))``."""
    cand, n_all, cdf = seed_pool(scene)
    if len(cand) == 0:
        return (np.zeros((0, 2, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, bool))
    seeds = cdf.searchsorted(rng.random(n_seeds), side="right")  # drawn by weight (inverse CDF)
    p1 = scene.points.reshape(-1, 3)[cand[seeds]]
    n1 = n_all[seeds]
    mu = params.friction_coef
    axes = _cone_axes(-n1, mu * params.cone_fraction, rng)

    step = params.march_step
    ts = step * np.arange(1, int(np.ceil(params.max_opening / step)) + 2)
    # the points p1 + t * axis of every line, one (S, T) array per coordinate
    x, y, z = (p1[:, i : i + 1] + ts * axes[:, i : i + 1] for i in range(3))
    rows, cols, inside = _pixels(scene, x, y, z)
    d = scene.depth.ravel()[rows * scene.depth.shape[1] + cols]
    tol = params.surface_tolerance
    occupied = inside & (d > 0) & (z >= d - tol)
    hx = None
    if scene.table is not None:  # heights above the table, linear along each line
        n, off = scene.table.normal, scene.table.offset
        hx = (p1 @ n + off)[:, None] + ts * (axes @ n)[:, None]
    under_top = None
    if scene.top is not None:  # and under the top seen from above (scene.table is set)
        under_top = hx <= scene.top.top_along(p1, axes, ts) + tol
        occupied &= under_top
    below = (hx < -params.table_inlier_distance) if hx is not None else np.zeros_like(occupied)
    free = ~occupied
    has_exit = free.any(axis=1)
    e = np.argmax(free, axis=1)  # first free step
    idx = np.arange(len(ts))[None, :]
    hits_table = (below & (idx <= e[:, None])).any(axis=1)
    width = ts[e] - 0.5 * step
    ok = occupied[:, 0] & has_exit & ~hits_table & (width >= params.min_width) & (width <= params.max_opening)
    p2 = p1 + width[:, None] * axes
    # contact 1 on a visible surface: its normal must hold the push (friction cone)
    r2, c2, in2 = lookup_pixels(scene, p2)
    d2 = scene.depth[r2, c2]
    seen = in2 & (d2 > 0) & (np.abs(p2[:, 2] - d2) <= tol) & scene.normal_ok[r2, c2] & scene.objects[r2, c2]
    cos_lim = np.cos(np.arctan(mu))
    n2 = scene.normals[r2, c2]
    ok &= ~seen | (np.einsum("ij,ij->i", n2, axes) >= cos_lim)
    if under_top is not None:
        # a hidden contact where the line left the seen footprint: read its wall as upright,
        # whose normal is the outline's; the axis must lie in that normal's friction cone
        left_top = ~under_top[np.arange(len(e)), e]
        wall = scene.top.outline_normal(p2)
        ok &= seen | ~left_top | (np.einsum("ij,ij->i", wall, axes) >= cos_lim)
    if params.max_centre_offset is not None and scene.centres is not None:
        # the jaw line should pass near the object's centre of mass (torques it must resist)
        lab = scene.labels.reshape(-1)[cand[seeds]]
        off = np.linalg.norm(np.cross(scene.centres[lab] - p1, axes), axis=1)
        ok &= off <= params.max_centre_offset
    contacts = np.stack([p1[ok], p2[ok]], axis=1)
    return contacts, axes[ok], width[ok], seen[ok]


def approach_frames(centers: np.ndarray, axes: np.ndarray, scene: Scene, params: PlanParams):
    """Grasp frames (m, 4, 4) for each TCP (n, 3) and unit jaw axis (n, 3): the
    ``num_approaches`` rotations omega in [-max_approach_tilt, +max_approach_tilt] about
    the axis around the straight-down approach (the camera ray where the axis is within
    ~17 deg of vertical); only those with beta < 90 deg and psi < ``max_psi``. Returns
    ``(frames, pair index (m,))``."""
    up = scene.up
    down = np.broadcast_to(-up, axes.shape)
    z0 = down - np.einsum("ij,ij->i", down, axes)[:, None] * axes
    nz = np.linalg.norm(z0, axis=1)
    ray = centers / np.linalg.norm(centers, axis=1, keepdims=True)
    zr = ray - np.einsum("ij,ij->i", ray, axes)[:, None] * axes
    use_ray = nz < 0.3
    z0 = np.where(use_ray[:, None], zr, z0)
    z0 /= np.maximum(np.linalg.norm(z0, axis=1, keepdims=True), 1e-12)
    y0 = np.cross(z0, axes)
    om = np.linspace(-params.max_approach_tilt, params.max_approach_tilt, params.num_approaches)
    c, s = np.cos(om), np.sin(om)
    # R = [x, y0, z0] Rx(omega): y = c y0 + s z0, z = -s y0 + c z0
    y = c[None, :, None] * y0[:, None] + s[None, :, None] * z0[:, None]
    z = -s[None, :, None] * y0[:, None] + c[None, :, None] * z0[:, None]
    ok = (z @ up < -1e-6) & (np.einsum("naj,nj->na", z, ray) > np.cos(params.max_psi))
    pair, which = np.nonzero(ok)  # (pair, approach) of the feasible ones, pair-major as before
    frames = np.zeros((len(pair), 4, 4))
    frames[:, :3, 0] = axes[pair]
    frames[:, :3, 1] = y[pair, which]
    frames[:, :3, 2] = z[pair, which]
    frames[:, :3, 3] = centers[pair]
    frames[:, 3, 3] = 1.0
    return frames, pair


def frames_about_axis(frames: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """``frames`` (n, 4, 4) rotated about their own x-axes by ``omega`` (n,) radians."""
    c, s = np.cos(omega)[:, None], np.sin(omega)[:, None]
    out = frames.copy()
    y0, z0 = frames[:, :3, 1], frames[:, :3, 2]
    out[:, :3, 1] = c * y0 + s * z0
    out[:, :3, 2] = -s * y0 + c * z0
    return out


def feasible_approach(frames: np.ndarray, scene: Scene, params: PlanParams) -> np.ndarray:
    """(n,) bool: beta < 90 deg (not from under the table) and psi < ``max_psi``."""
    z = frames[:, :3, 2]
    ray = frames[:, :3, 3] / np.linalg.norm(frames[:, :3, 3], axis=1, keepdims=True)
    return (z @ scene.up < -1e-6) & (np.einsum("ij,ij->i", z, ray) > np.cos(params.max_psi))


def collision_checker(scene: Scene, params: PlanParams, rng: np.random.Generator) -> GripperCollision:
    """The scene's gripper collision model: the table and the observed points above it,
    inside or outside the region of interest (one per ``collision_voxel`` cube, at most
    ``max_collision_points``)."""
    above = scene.valid.copy()
    if scene.table is not None:
        above &= scene.table.height(scene.points) > params.table_inlier_distance
    pts = voxel_downsample(masked_points(scene.points, above), params.collision_voxel)
    if len(pts) > params.max_collision_points:
        pts = pts[rng.choice(len(pts), size=params.max_collision_points, replace=False)]
    return GripperCollision(params.gripper, scene.table, pts, params.table_margin, params.point_clearance)


def sample_grasps(
    scene: Scene, params: PlanParams, rng: np.random.Generator, checker: GripperCollision
) -> tuple[Candidates, dict]:
    """Up to ``params.num_candidates`` collision-free candidates and the counts of each
    stage (``pairs``, ``approaches``, ``checked``, ``collision_free``) and of the checked
    frames refused for the table (``table_collisions``: a fingertip within ``table_margin``
    of it) or for the observed points (``point_collisions``)."""
    counts = {
        "pairs": 0,
        "approaches": 0,
        "checked": 0,
        "collision_free": 0,
        "table_collisions": 0,
        "point_collisions": 0,
    }
    found: list[Candidates] = []
    n_found = 0
    for _ in range(params.max_rounds):
        contacts, axes, widths, seen = sample_contact_pairs(scene, params.max_seeds, params, rng)
        counts["pairs"] += len(axes)
        if len(axes) == 0:
            continue
        centers = contacts.mean(axis=1)
        frames, pair = approach_frames(centers, axes, scene, params)
        counts["approaches"] += len(frames)
        order = rng.permutation(len(frames))
        chunk = max(params.num_candidates - n_found, 32)
        for s in range(0, len(order), chunk):
            idx = order[s : s + chunk]
            table, points = checker.collisions(frames[idx])
            free = ~(table | points)
            counts["checked"] += len(idx)
            counts["table_collisions"] += int(table.sum())
            counts["point_collisions"] += int(points.sum())
            idx = idx[free]
            p = pair[idx]
            found.append(Candidates(frames[idx], contacts[p], widths[p], seen[p]))
            n_found += len(idx)
            if n_found >= params.num_candidates:
                break
        if n_found >= params.num_candidates:
            break
    out = Candidates.concat(found)[: params.num_candidates]
    counts["collision_free"] = len(out)
    return out, counts
