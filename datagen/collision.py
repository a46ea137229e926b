"""Gripper collision checks along the straight approach (SPEC section 2.5), python-fcl.

World frame: table surface z = 0, z up; metres. The gripper (opened to max width) is the
union of its three boxes swept back along the grasp's -z by ``approach_distance``
(:func:`datagen.gripper.gripper_boxes`). A grasp collides when that swept volume

* reaches below the table (any box corner with z < 0: exact for boxes, vectorised), or
* contains an object vertex (vectorised over a fixed subset of at most
  ``max_probe_vertices`` vertices: a cheap, exact positive), or
* intersects the object surface (fcl BVH-vs-BVH test of the box triangles against the
  object mesh, built once per checker; only for grasps the two tests above left open).

Surface tests miss an object lying wholly inside a box; the vertex test catches that case.
A box lying wholly inside the object is not detected (it would need the approach start,
``approach_distance`` back, to be inside the object too).

``clearance`` (metres) grows every box by that margin on all sides and raises the table
plane to z = clearance: a grasp then collides when the gripper comes closer than the
clearance. :func:`collision_free_probability` checks each grasp under K perturbations of its
pose (:class:`RobustCollisionParams`, execution noise: translation per axis and a rotation
vector about the TCP) and returns the fraction that is free (issue 17: most physical failures
happen on the way in, which one check at the nominal pose with zero clearance misses).
"""

from __future__ import annotations

from dataclasses import dataclass

import fcl
import numpy as np
import trimesh

from .gripper import GripperGeometry, as_frames, box_corners, gripper_boxes


@dataclass(frozen=True)
class RobustCollisionParams:
    """Robust collision check: ``num_samples`` perturbed poses per grasp, translation
    N(0, sigma_translation) per axis (metres), rotation vector N(0, sigma_rotation) per axis
    (radians, about the TCP), and a ``clearance`` (metres) the gripper must keep from the
    object and the table."""

    num_samples: int = 16
    sigma_translation: float = 0.005
    sigma_rotation: float = float(np.radians(3.0))
    clearance: float = 0.002

    def __post_init__(self) -> None:
        if self.num_samples < 1:
            raise ValueError(f"num_samples must be >= 1, got {self.num_samples}")
        for name in ("sigma_translation", "sigma_rotation", "clearance"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"RobustCollisionParams.{name} must be >= 0, got {v!r}")


def _box_mesh(centres: np.ndarray, half: np.ndarray) -> trimesh.Trimesh:
    parts = []
    for c, h in zip(centres, half):
        T = np.eye(4)
        T[:3, 3] = c
        parts.append(trimesh.creation.box(extents=2 * h, transform=T))
    return trimesh.util.concatenate(parts)


def _bvh(mesh: trimesh.Trimesh) -> fcl.BVHModel:
    m = fcl.BVHModel()
    m.beginModel(len(mesh.vertices), len(mesh.faces))
    m.addSubModel(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int32))
    m.endModel()
    return m


class CollisionChecker:
    """Collision checks of the swept gripper against one object pose and the table."""

    def __init__(
        self,
        mesh_world: trimesh.Trimesh,
        gripper: GripperGeometry,
        table: bool = True,
        max_probe_vertices: int = 16,
        seed: int = 0,
        clearance: float = 0.0,
    ):
        if not isinstance(mesh_world, trimesh.Trimesh):
            raise ValueError(f"mesh_world must be a trimesh.Trimesh, got {type(mesh_world).__name__}")
        if len(mesh_world.faces) == 0:
            raise ValueError("mesh_world has no faces")
        verts = np.asarray(mesh_world.vertices, dtype=np.float64)
        if not np.all(np.isfinite(verts)):
            raise ValueError("mesh_world has non-finite vertices")
        if not (np.isfinite(clearance) and clearance >= 0):
            raise ValueError(f"clearance must be >= 0 metres, got {clearance!r}")
        self.gripper = gripper
        self.table = bool(table)
        self.clearance = float(clearance)
        self._centres, self._half = gripper_boxes(gripper, swept=True)
        self._half = self._half + self.clearance
        self._corners = box_corners(self._centres, self._half)  # (24, 3) grasp frame
        rng = np.random.default_rng(seed)
        k = min(int(max_probe_vertices), len(verts))
        self._probe = verts[rng.choice(len(verts), size=k, replace=False)] if k < len(verts) else verts
        self._object = fcl.CollisionObject(_bvh(mesh_world), fcl.Transform())
        self._gripper = fcl.CollisionObject(_bvh(_box_mesh(self._centres, self._half)), fcl.Transform())
        self._request = fcl.CollisionRequest(num_max_contacts=1, enable_contact=False)
        self._result = fcl.CollisionResult()

    def collides_table(self, T_world_grasp: np.ndarray) -> np.ndarray:
        """(n,) bool: the swept gripper (grown by the clearance) reaches below the table plane z = 0."""
        T = as_frames(T_world_grasp, "T_world_grasp")
        c = self._corners  # world z of each box corner (n, 24), written out: no BLAS call
        corner_z = T[:, 2, 0:1] * c[:, 0] + T[:, 2, 1:2] * c[:, 1] + T[:, 2, 2:3] * c[:, 2] + T[:, 2, 3:4]
        return corner_z.min(axis=1) < 0.0

    def contains_vertex(self, T_world_grasp: np.ndarray) -> np.ndarray:
        """(n,) bool: some probe vertex of the object lies strictly inside a swept box."""
        T = as_frames(T_world_grasp, "T_world_grasp")
        out = np.zeros(T.shape[0], dtype=bool)
        k = len(self._probe)
        chunk = max(1, 1_000_000 // max(1, k))
        for s in range(0, T.shape[0], chunk):
            Rt = np.transpose(T[s : s + chunk, :3, :3], (0, 2, 1))
            off = -np.einsum("mij,mj->mi", Rt, T[s : s + chunk, :3, 3])
            local = Rt @ self._probe.T + off[:, :, None]  # (m, 3, k) probe points in grasp frames
            x, y, z = local[:, 0], local[:, 1], local[:, 2]
            hit = out[s : s + chunk]
            for c, h in zip(self._centres, self._half):
                inside = (np.abs(x - c[0]) < h[0]) & (np.abs(y - c[1]) < h[1]) & (np.abs(z - c[2]) < h[2])
                hit |= inside.any(axis=1)
        return out

    def collides_object_fcl(self, T_world_grasp: np.ndarray) -> np.ndarray:
        """(n,) bool: the swept gripper's surface intersects the object surface (fcl)."""
        T = as_frames(T_world_grasp, "T_world_grasp")
        out = np.zeros(T.shape[0], dtype=bool)
        g, o, req, res = self._gripper, self._object, self._request, self._result
        R, t = np.ascontiguousarray(T[:, :3, :3]), np.ascontiguousarray(T[:, :3, 3])
        for i in range(T.shape[0]):
            g.setRotation(R[i])
            g.setTranslation(t[i])
            if fcl.collide(g, o, req, res):
                out[i] = True
                res.contacts.clear()
        res.is_collision = False
        return out

    def collides(self, T_world_grasp: np.ndarray) -> np.ndarray:
        """(n,) bool for grasp frames ``T_world_grasp`` (n, 4, 4): the gripper opened to max
        width, swept along its straight approach (+z) from ``approach_distance`` back to the
        grasp pose, hits the object or (if ``table``) the table."""
        T = as_frames(T_world_grasp, "T_world_grasp")
        hit = self.collides_table(T) if self.table else np.zeros(T.shape[0], dtype=bool)
        open_ = ~hit
        if np.any(open_):
            hit[open_] = self.contains_vertex(T[open_])
        open_ = ~hit
        if np.any(open_):
            hit[open_] = self.collides_object_fcl(T[open_])
        return hit


def perturb_frames(T_world_grasp: np.ndarray, params: RobustCollisionParams, rng: np.random.Generator) -> np.ndarray:
    """``params.num_samples`` perturbed copies (n, K, 4, 4) of grasp frames (n, 4, 4): each
    rotated about its TCP by a rotation vector N(0, sigma_rotation) per axis (world frame)
    and translated by N(0, sigma_translation) per axis."""
    from .quality import rotation_matrices

    T = as_frames(T_world_grasp, "T_world_grasp")
    n, K = T.shape[0], params.num_samples
    R = rotation_matrices(params.sigma_rotation * rng.standard_normal((n * K, 3))).reshape(n, K, 3, 3)
    out = np.tile(T[:, None], (1, K, 1, 1))
    out[:, :, :3, :3] = R @ T[:, None, :3, :3]
    out[:, :, :3, 3] += params.sigma_translation * rng.standard_normal((n, K, 3))
    return out


def collision_free_probability(
    checker: CollisionChecker, T_world_grasp: np.ndarray, params: RobustCollisionParams, rng: np.random.Generator
) -> np.ndarray:
    """(n,) fraction of ``params.num_samples`` perturbed poses of each grasp (n, 4, 4) whose
    approach is collision-free (``checker`` should be built with ``params.clearance``)."""
    T = as_frames(T_world_grasp, "T_world_grasp")
    Tp = perturb_frames(T, params, rng)
    hit = checker.collides(Tp.reshape(-1, 4, 4)).reshape(T.shape[0], params.num_samples)
    return 1.0 - hit.mean(axis=1)
