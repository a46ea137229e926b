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
"""

from __future__ import annotations

import fcl
import numpy as np
import trimesh

from .gripper import GripperGeometry, as_frames, box_corners, gripper_boxes, gripper_mesh


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
    ):
        if not isinstance(mesh_world, trimesh.Trimesh):
            raise ValueError(f"mesh_world must be a trimesh.Trimesh, got {type(mesh_world).__name__}")
        if len(mesh_world.faces) == 0:
            raise ValueError("mesh_world has no faces")
        verts = np.asarray(mesh_world.vertices, dtype=np.float64)
        if not np.all(np.isfinite(verts)):
            raise ValueError("mesh_world has non-finite vertices")
        self.gripper = gripper
        self.table = bool(table)
        self._centres, self._half = gripper_boxes(gripper, swept=True)
        self._corners = box_corners(self._centres, self._half)  # (24, 3) grasp frame
        rng = np.random.default_rng(seed)
        k = min(int(max_probe_vertices), len(verts))
        self._probe = verts[rng.choice(len(verts), size=k, replace=False)] if k < len(verts) else verts
        self._object = fcl.CollisionObject(_bvh(mesh_world), fcl.Transform())
        self._gripper = fcl.CollisionObject(_bvh(gripper_mesh(gripper, swept=True)), fcl.Transform())
        self._request = fcl.CollisionRequest(num_max_contacts=1, enable_contact=False)
        self._result = fcl.CollisionResult()

    def collides_table(self, T_world_grasp: np.ndarray) -> np.ndarray:
        """(n,) bool: the swept gripper reaches below the table plane z = 0."""
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
