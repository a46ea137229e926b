"""The table plane (RANSAC) and gripper collisions with it and with the observed points.

Camera frame, metres. The table is a plane ``normal . x + offset = 0`` with ``normal``
pointing up, towards the camera side (so the camera origin has height ``offset`` > 0).
The gripper is :mod:`vgq.gripper`'s three boxes, opened to ``max_width`` and swept back
along the approach (-z of the grasp frame) by ``approach_distance``, as in datagen.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vgq.gripper import GripperGeometry, box_corners, gripper_boxes


@dataclass(frozen=True)
class TablePlane:
    """A plane n . x + d = 0 (camera frame); ``normal`` (3,) unit, towards the camera;
    ``inlier_fraction`` of the points it was fitted to that lie on it."""

    normal: np.ndarray
    offset: float
    inlier_fraction: float

    def height(self, x: np.ndarray) -> np.ndarray:
        """Signed heights (...,) of points (..., 3) above the plane (metres), float32 for float32
        points (the planner's image-sized clouds: no float64 copy), else float64."""
        x = np.asarray(x)
        n = self.normal.astype(np.float32) if x.dtype == np.float32 else self.normal
        return x @ n + self.offset


def lowest_corner_height(frames: np.ndarray, corners: np.ndarray, normal: np.ndarray, offset: float) -> np.ndarray:
    """(n,) height (metres) above the plane n . x + offset = 0 of the lowest of ``corners`` (k, 3,
    grasp frame) for each grasp frame (n, 4, 4) given in the plane's frame.

    Corner c of frame (R, t) is at c . (R^T n) + t . n + offset: one (n, 3) x (3, k) product
    (the corners moved into the frame, an (n, k, 3) einsum, cost 50x more)."""
    up = np.tensordot(frames[:, :3, :3], normal, axes=([1], [0]))
    return (up @ corners.T).min(axis=1) + frames[:, :3, 3] @ normal + offset


def fit_table(
    points: np.ndarray, rng: np.random.Generator, iterations: int = 60, inlier_distance: float = 0.003
) -> TablePlane | None:
    """The dominant plane of ``points`` (n, 3) by RANSAC: ``iterations`` three-point
    hypotheses scored at once, the best refined by a least-squares fit to its inliers.
    Pass a random subset of a large cloud (a few thousand points are plenty). None when
    there are fewer than 3 points or all hypotheses are degenerate."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) < 3:
        return None
    tri = p[rng.integers(0, len(p), size=(iterations, 3))]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1)
    good = norm > 1e-12
    if not good.any():
        return None
    n = n[good] / norm[good, None]
    d = -np.einsum("ij,ij->i", n, tri[good, 0])
    counts = (np.abs(p @ n.T + d) < inlier_distance).sum(axis=0)
    best = int(np.argmax(counts))
    nb, db = n[best], d[best]
    inl = np.abs(p @ nb + db) < inlier_distance
    if inl.sum() >= 3:
        q = p[inl]
        c = q.mean(axis=0)
        _, _, vt = np.linalg.svd(q - c, full_matrices=False)
        nb = vt[2]
        db = -float(nb @ c)
        inl = np.abs(p @ nb + db) < inlier_distance
    if db < 0:  # camera side up
        nb, db = -nb, -db
    return TablePlane(normal=nb, offset=float(db), inlier_fraction=float(inl.mean()))


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """One point (the first) per occupied cube of side ``voxel`` metres; (m, 3)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0 or voxel <= 0:
        return p
    k = np.floor(p / voxel).astype(np.int64)
    k -= k.min(axis=0)
    span = k.max(axis=0) + 1
    keys = (k[:, 0] * span[1] + k[:, 1]) * span[2] + k[:, 2]  # one integer per cube
    _, first = np.unique(keys, return_index=True)
    return p[np.sort(first)]


class GripperCollision:
    """Collision checks of the swept gripper against a table plane and observed points."""

    def __init__(
        self,
        gripper: GripperGeometry,
        table: TablePlane | None,
        points: np.ndarray,
        table_margin: float = 0.0,
        point_clearance: float = 0.001,
    ):
        """``points`` (m, 3): the observed points the gripper must not enter (the objects,
        not the table); a box grown by ``point_clearance`` may not hold any. The box
        corners must stay ``table_margin`` above the table (negative: may reach that far below)."""
        self.table = table
        self.points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        self.table_margin = float(table_margin)
        self._centres, self._half = gripper_boxes(gripper, swept=True)
        self._half_grown = self._half + float(point_clearance)
        self._corners = box_corners(self._centres, self._half)  # (24, 3) grasp frame
        c = self._centres
        if not (
            np.allclose(c[0], -c[1] * [1, -1, -1])
            and np.allclose(c[2, :2], 0)
            and np.allclose(self._half[0], self._half[1])
        ):
            raise ValueError("GripperCollision expects two fingers mirrored in x and a centred palm")

    def collides_table(self, frames: np.ndarray) -> np.ndarray:
        """(n,) bool: some corner of the swept boxes lies less than ``table_margin`` above the table."""
        if self.table is None or len(frames) == 0:
            return np.zeros(len(frames), dtype=bool)
        lowest = lowest_corner_height(frames, self._corners, self.table.normal, self.table.offset)
        return lowest < self.table_margin

    def collides_points(self, frames: np.ndarray, points: np.ndarray | None = None, chunk: int = 128) -> np.ndarray:
        """(n,) bool: some observed point (``points``, default all) lies inside a swept box
        (grown by the clearance).

        Uses the gripper's symmetry (two fingers mirrored in x, palm centred) and float32
        grasp-frame coordinates: one (m, 3) x (3, 3 f) product (einsum's own loop: OpenBLAS would
        spin a second thread, doubling the CPU time for a third off the wall time) gives every
        point's coordinates in f frames, then ~10 array operations per point and frame test the boxes."""
        pts = (self.points if points is None else np.asarray(points, dtype=np.float64)).astype(np.float32)
        n = len(frames)
        out = np.zeros(n, dtype=bool)
        if n == 0 or len(pts) == 0:
            return out
        (fx, _, fz), (hx, hy, hz) = np.abs(self._centres[1]), self._half_grown[1]
        fz = self._centres[1][2]
        pz, (px, py, phz) = self._centres[2][2], self._half_grown[2]
        for s in range(0, n, chunk):
            T = frames[s : s + chunk]
            f = len(T)
            # grasp-frame coordinate i of point p in frame k: p . r_ki - t_k . r_ki, at column i f + k
            R = np.ascontiguousarray(T[:, :3, :3].transpose(1, 2, 0).reshape(3, 3 * f), dtype=np.float32)
            off = np.einsum("kji,kj->ik", T[:, :3, :3], T[:, :3, 3]).reshape(3 * f).astype(np.float32)
            c = np.einsum("mj,jc->mc", pts, R)  # not pts @ R: a BLAS call this size wakes OpenBLAS's threads
            c -= off
            ax, ay, z = np.abs(c[:, :f]), np.abs(c[:, f : 2 * f]), c[:, 2 * f :]
            finger = (np.abs(ax - fx) < hx) & (ay < hy) & (np.abs(z - fz) < hz)
            palm = (ax < px) & (ay < py) & (np.abs(z - pz) < phz)
            out[s : s + chunk] = (finger | palm).any(axis=0)
        return out

    def collides(self, frames: np.ndarray) -> np.ndarray:
        """(n,) bool for grasp frames (n, 4, 4) in the camera frame (:meth:`collisions`, either)."""
        table, points = self.collisions(frames)
        return table | points

    def collisions(self, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(table (n,), points (n,))`` bool for grasp frames (n, 4, 4) in the camera frame: the
        table first, then, for the rest, every 4th point (most collisions show there), then all
        points (a frame that hits the table is not checked against the points)."""
        frames = np.asarray(frames, dtype=np.float64).reshape(-1, 4, 4)
        table = self.collides_table(frames)
        hit = table.copy()
        for pts in (self.points[::4], self.points):
            open_ = np.flatnonzero(~hit)
            if len(open_):
                hit[open_] = self.collides_points(frames[open_], pts)
        return table, hit & ~table
