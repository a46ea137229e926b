"""Physical grasp trials in pybullet: approach, close, lift and shake (issue 17).

World frame: table surface z = 0, z up; metres, kilograms, seconds, newtons. Grasp frames
as in :mod:`datagen.gripper` (x = jaw axis, z = approach, origin = TCP). Quaternions
passed to pybullet are (x, y, z, w) (pybullet's order); nothing here returns quaternions.

The object is one rigid body: its convex hull when the mesh is convex (volume within
``convex_tolerance`` of the hull's), else a V-HACD decomposition (pybullet's built-in
``vhacd``, cached per mesh). Mass is ``object_mass``; the inertia tensor is the mesh's
(uniform density) scaled to that mass, about the centre of mass (the object-frame origin).

The gripper has :class:`datagen.gripper.GripperGeometry`'s boxes: a palm and two fingers
whose inner faces are the pads (``finger_width`` x ``finger_length``), on prismatic joints
coupled by a gear constraint (the jaws stay symmetric about the TCP) and driven closed with
at most ``grip_force`` newtons. The palm follows a force-limited constraint that the trial
moves kinematically.

A trial: the gripper, opened to ``max_width``, appears ``approach_distance`` back along the
grasp's -z (a start pose in collision fails the trial), moves straight to the grasp pose,
closes, lifts ``lift_height`` and shakes (a horizontal circle of ``shake_amplitude`` at
``shake_frequency`` for ``shake_duration``). Any gripper contact with the table fails the
trial (a real arm stops). Outcomes: ``held`` (the object is lifted with the gripper at the
end) and ``firm`` (held, and the object moved less than ``firm_translation`` /
``firm_rotation`` in the gripper frame between the end of closing and the end of shaking).
Each trial also reports where each pad first touched the object: the normal-force-weighted
mean of its contact points over its first ``touch_steps`` steps in contact (object frame).

Execution noise (seeded): the grasp pose is translated by N(0, sigma_translation) per axis
and rotated by a rotation vector N(0, sigma_rotation) per axis about the TCP; friction mu is
drawn from N(friction_coef, sigma_friction) truncated at ``min_friction`` (pad friction is
1 and pybullet multiplies the two).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from .gripper import GripperGeometry, gripper_boxes

#: trial outcome reasons (TrialResults.reason)
REASONS = ("held", "dropped", "start_collision", "table")


@dataclass(frozen=True)
class PhysicsParams:
    """Physics trial settings (SI units; angles in radians)."""

    object_mass: float = 0.2
    grip_force: float = 20.0
    close_speed: float = 0.2
    squeeze_speed: float = 0.02  # jaw motor target speed once a pad touches (a fast target lets pads sink in)
    approach_distance: float = 0.05
    approach_speed: float = 0.25
    lift_height: float = 0.12
    lift_speed: float = 0.3
    shake_duration: float = 1.0
    shake_amplitude: float = 0.02
    shake_frequency: float = 2.0
    time_step: float = 1.0 / 240.0
    solver_iterations: int = 100  # fewer leave friction unconverged: held grasps pivot out of the pads
    table_friction: float = 0.5
    friction_coef: float = 0.5
    sigma_friction: float = 0.1
    min_friction: float = 0.05
    sigma_translation: float = 0.005
    sigma_rotation: float = float(np.radians(3.0))
    firm_translation: float = 0.005
    firm_rotation: float = float(np.radians(5.0))
    convex_tolerance: float = 0.02
    vhacd_resolution: int = 400000  # V-HACD voxels; with vhacd_concavity fine enough that pads touch the
    vhacd_concavity: float = 0.0002  # decomposition within ~3 mm of the mesh (coarser: bottles lose their necks)
    settle_time: float = 0.5
    collision_margin: float = 0.0002  # pybullet's default 1 mm per body makes shapes touch ~2 mm early
    touch_steps: int = 6  # first touch: force-weighted contact points of a pad's first steps in contact
    stable_translation: float = 0.005
    stable_rotation: float = float(np.radians(5.0))
    # soft-finger contact: the pads' contact patch (radius, m) resists rotation about the contact
    # normal up to (2/3) mu N r (uniform pressure), as pybullet spinning friction on the fingers.
    # 0 gives rigid point contacts, about which an object gripped on a tapered or curved face swings
    # freely: such grasps fell out in the shake (a 5 deg frustum: 0 of 8 trials held, 5 of 8 with 3 mm)
    pad_contact_radius: float = 0.003

    def __post_init__(self) -> None:
        for name in (
            "object_mass",
            "grip_force",
            "close_speed",
            "squeeze_speed",
            "approach_speed",
            "lift_speed",
            "time_step",
            "shake_frequency",
            "firm_translation",
            "firm_rotation",
            "min_friction",
        ):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"PhysicsParams.{name} must be > 0, got {v!r}")
        for name in (
            "approach_distance",
            "lift_height",
            "shake_duration",
            "shake_amplitude",
            "table_friction",
            "friction_coef",
            "sigma_friction",
            "sigma_translation",
            "sigma_rotation",
            "convex_tolerance",
            "settle_time",
            "stable_translation",
            "stable_rotation",
            "pad_contact_radius",
        ):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"PhysicsParams.{name} must be >= 0, got {v!r}")
        if self.solver_iterations < 1:
            raise ValueError(f"PhysicsParams.solver_iterations must be >= 1, got {self.solver_iterations}")


@dataclass
class TrialResults:
    """Outcomes of n grasps x k trials. ``first_touch``: where each pad first touched the
    object while closing, object frame (metres), NaN where it did not touch; ``mu``: the
    friction drawn."""

    held: np.ndarray  # (n, k) bool
    firm: np.ndarray  # (n, k) bool
    reason: np.ndarray  # (n, k) int8 index into REASONS
    first_touch: np.ndarray  # (n, k, 2, 3)
    mu: np.ndarray  # (n, k)
    seconds: float = 0.0
    ran: np.ndarray | None = None  # (n, k) bool: the trials run (None: all; see run_trials' stop_above)

    @property
    def success_rate(self) -> np.ndarray:
        """Share of the trials run that held (n,)."""
        if self.ran is None:
            return self.held.mean(axis=1)
        return self.held.sum(axis=1) / np.maximum(self.ran.sum(axis=1), 1)

    @property
    def trials_run(self) -> int:
        return int(self.held.size if self.ran is None else self.ran.sum())


# ----------------------------------------------------------------------------- helpers


@contextlib.contextmanager
def _quiet_stdout():
    """Silence C-level stdout (V-HACD prints its progress)."""
    try:
        fd = os.dup(1)
    except OSError:  # pragma: no cover
        yield
        return
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 1)
            yield
    finally:
        os.dup2(fd, 1)
        os.close(fd)


def _quat_xyzw(R: np.ndarray) -> list[float]:
    """Quaternion (x, y, z, w) of a rotation matrix (pybullet's order; no scipy: this runs per step)."""
    R = np.asarray(R, dtype=np.float64)
    t = R[0, 0] + R[1, 1] + R[2, 2]
    if t > 0:
        s = 2.0 * np.sqrt(t + 1.0)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s]
    q = np.asarray(q)
    return (q / np.linalg.norm(q)).tolist()


def _matrix(quat_xyzw) -> np.ndarray:
    import pybullet as p

    return np.asarray(p.getMatrixFromQuaternion(quat_xyzw), dtype=np.float64).reshape(3, 3)


def _rotvec_matrices(rv: np.ndarray) -> np.ndarray:
    from .quality import rotation_matrices

    return rotation_matrices(rv)


def is_convex(mesh: trimesh.Trimesh, tolerance: float = 0.02) -> bool:
    """The mesh's volume is within ``tolerance`` (fraction) of its convex hull's."""
    hv = float(mesh.convex_hull.volume)
    return hv > 0 and float(mesh.volume) >= (1.0 - tolerance) * hv


def mesh_key(mesh: trimesh.Trimesh) -> str:
    """A content hash of a mesh (vertices and faces)."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    return h.hexdigest()[:24]


def default_cache_dir() -> Path:
    return Path(os.environ.get("VGQ_CACHE", Path.home() / ".cache" / "vgq")) / "vhacd"


def vhacd_file(
    mesh: trimesh.Trimesh, client: int, resolution: int, cache_dir: str | Path | None = None, concavity: float = 0.0002
) -> Path:
    """Path of the V-HACD decomposition (an .obj of convex parts) of ``mesh``, computed
    with pybullet's ``vhacd`` once per mesh and cached in ``cache_dir``."""
    import pybullet as p

    cache = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    cache.mkdir(parents=True, exist_ok=True)
    out = cache / f"{mesh_key(mesh)}_{resolution}_{concavity:g}.obj"
    if out.is_file():
        return out
    with tempfile.TemporaryDirectory(prefix="vhacd-") as tmp:
        src = Path(tmp) / "in.obj"
        mesh.export(str(src))
        dst = Path(tmp) / "out.obj"
        with _quiet_stdout():
            p.vhacd(
                str(src),
                str(dst),
                str(Path(tmp) / "log.txt"),
                resolution=int(resolution),
                concavity=float(concavity),
                physicsClientId=client,
            )
        if not dst.is_file():
            raise RuntimeError("V-HACD produced no decomposition")
        from vgq import atomic

        atomic.write_bytes(out, dst.read_bytes())
    return out


# ----------------------------------------------------------------------------- the world


class GraspSimulator:
    """One pybullet DIRECT client with a table and the pad gripper; objects are swapped in
    with :meth:`set_object` and trials reuse the client (bodies are reset, not rebuilt)."""

    def __init__(
        self,
        gripper: GripperGeometry = GripperGeometry(),
        params: PhysicsParams = PhysicsParams(),
        cache_dir: str | Path | None = None,
    ):
        import pybullet as p

        self.p = p
        self.g = gripper
        self.params = params
        self.cache_dir = cache_dir
        self.cid = p.connect(p.DIRECT)
        c = self.cid
        p.setGravity(0, 0, -9.81, physicsClientId=c)
        p.setPhysicsEngineParameter(
            fixedTimeStep=params.time_step,
            numSolverIterations=params.solver_iterations,
            numSubSteps=0,
            physicsClientId=c,
        )
        plane = p.createCollisionShape(p.GEOM_PLANE, physicsClientId=c)
        self.table = p.createMultiBody(0, plane, physicsClientId=c)
        p.changeDynamics(self.table, -1, lateralFriction=params.table_friction, physicsClientId=c)
        self._build_gripper()
        self.obj = None
        self._shapes: dict[str, int] = {}
        self._obj_T0 = None

    def close(self) -> None:
        if self.cid is not None:
            self.p.disconnect(self.cid)
            self.cid = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- gripper
    def _build_gripper(self) -> None:
        p, c, g = self.p, self.cid, self.g
        centres, half = gripper_boxes(g, swept=False)
        palm = p.createCollisionShape(p.GEOM_BOX, halfExtents=half[2].tolist(), physicsClientId=c)
        finger = p.createCollisionShape(p.GEOM_BOX, halfExtents=half[0].tolist(), physicsClientId=c)
        travel = g.max_width / 2
        self.gripper = p.createMultiBody(
            baseMass=0.5,
            baseCollisionShapeIndex=palm,
            basePosition=[0, 0, 5.0],
            baseInertialFramePosition=[0, 0, 0],
            linkMasses=[0.05, 0.05],
            linkCollisionShapeIndices=[finger, finger],
            linkVisualShapeIndices=[-1, -1],
            linkPositions=[(centres[0] - centres[2]).tolist(), (centres[1] - centres[2]).tolist()],
            linkOrientations=[[0, 0, 0, 1], [0, 0, 0, 1]],
            linkInertialFramePositions=[[0, 0, 0], [0, 0, 0]],
            linkInertialFrameOrientations=[[0, 0, 0, 1], [0, 0, 0, 1]],
            linkParentIndices=[0, 0],
            linkJointTypes=[p.JOINT_PRISMATIC, p.JOINT_PRISMATIC],
            linkJointAxis=[[1, 0, 0], [-1, 0, 0]],
            physicsClientId=c,
        )
        self._palm_offset = centres[2].copy()  # base (palm centre) in the grasp frame
        for j in (0, 1):
            p.changeDynamics(
                self.gripper,
                j,
                lateralFriction=1.0,
                jointLowerLimit=0.0,
                jointUpperLimit=travel,
                collisionMargin=self.params.collision_margin,
                physicsClientId=c,
            )
        p.changeDynamics(
            self.gripper, -1, lateralFriction=1.0, collisionMargin=self.params.collision_margin, physicsClientId=c
        )
        self._drive = p.createConstraint(
            self.gripper, -1, -1, -1, p.JOINT_FIXED, [0, 0, 0], [0, 0, 0], [0, 0, 5.0], physicsClientId=c
        )
        self._travel = travel
        self._mirror_force = 10.0 * self.params.grip_force

    def _step(self, n: int = 1) -> None:
        """Step the simulation n times, jaw 1 mirroring jaw 0 (coupled jaws: jaw 0 is driven
        with the grip force, jaw 1 is held at jaw 0's opening)."""
        p, c = self.p, self.cid
        for _ in range(n):
            q0 = p.getJointState(self.gripper, 0, physicsClientId=c)[0]
            p.setJointMotorControl2(
                self.gripper, 1, p.POSITION_CONTROL, targetPosition=q0, force=self._mirror_force, physicsClientId=c
            )
            p.stepSimulation(physicsClientId=c)

    def _drive_jaw(self, speed: float) -> None:
        self.p.setJointMotorControl2(
            self.gripper,
            0,
            self.p.VELOCITY_CONTROL,
            targetVelocity=speed,
            force=self.params.grip_force,
            physicsClientId=self.cid,
        )

    def _base_pose(self, T_wg: np.ndarray):
        pos = T_wg[:3, :3] @ self._palm_offset + T_wg[:3, 3]
        return pos.tolist(), _quat_xyzw(T_wg[:3, :3])

    def _place_gripper(self, T_wg: np.ndarray) -> None:
        p, c = self.p, self.cid
        pos, orn = self._base_pose(T_wg)
        p.resetBasePositionAndOrientation(self.gripper, pos, orn, physicsClientId=c)
        p.resetBaseVelocity(self.gripper, [0, 0, 0], [0, 0, 0], physicsClientId=c)
        for j in (0, 1):
            p.resetJointState(self.gripper, j, 0.0, 0.0, physicsClientId=c)
        self._drive_jaw(0.0)
        p.setJointMotorControl2(
            self.gripper, 1, p.POSITION_CONTROL, targetPosition=0.0, force=self._mirror_force, physicsClientId=c
        )
        self._drive_to(T_wg)

    def _drive_to(self, T_wg: np.ndarray) -> None:
        pos, orn = self._base_pose(T_wg)
        self.p.changeConstraint(self._drive, pos, orn, maxForce=500.0, physicsClientId=self.cid)

    # -- object
    def set_object(self, mesh: trimesh.Trimesh, T_world_object: np.ndarray) -> dict:
        """Make ``mesh`` (object frame, centre of mass at the origin) the trial object, resting
        in the stable pose ``T_world_object``; let it settle for ``settle_time`` and report
        ``{"stable": bool, "drift_m": float, "drift_rad": float, "convex": bool, "parts": int}``.
        Trials start from the settled pose."""
        p, c, prm = self.p, self.cid, self.params
        if self.obj is not None:
            p.removeBody(self.obj, physicsClientId=c)
            self.obj = None
        key = mesh_key(mesh)
        convex = is_convex(mesh, prm.convex_tolerance)
        if key not in self._shapes:
            if convex:
                shape = p.createCollisionShape(
                    p.GEOM_MESH, vertices=np.asarray(mesh.convex_hull.vertices).tolist(), physicsClientId=c
                )
            else:
                f = vhacd_file(mesh, c, prm.vhacd_resolution, self.cache_dir, prm.vhacd_concavity)
                shape = p.createCollisionShape(p.GEOM_MESH, fileName=str(f), physicsClientId=c)
            if shape < 0:
                raise RuntimeError("pybullet could not build the object's collision shape")
            self._shapes[key] = shape
        shape = self._shapes[key]
        inertia = np.asarray(mesh.moment_inertia, dtype=np.float64) * (prm.object_mass / float(mesh.mass))
        evals, evecs = np.linalg.eigh(inertia)
        if np.linalg.det(evecs) < 0:
            evecs[:, 0] *= -1
        T0 = np.asarray(T_world_object, dtype=np.float64)
        # pybullet poses a base by its inertial frame: keep the object -> inertial transform
        self._T_oi = np.eye(4)
        self._T_oi[:3, :3] = evecs
        self._T_io = np.linalg.inv(self._T_oi)
        Ti = T0 @ self._T_oi
        self.obj = p.createMultiBody(
            baseMass=prm.object_mass,
            baseCollisionShapeIndex=shape,
            basePosition=Ti[:3, 3].tolist(),
            baseOrientation=_quat_xyzw(Ti[:3, :3]),
            baseInertialFramePosition=[0, 0, 0],
            baseInertialFrameOrientation=_quat_xyzw(evecs),
            physicsClientId=c,
        )
        p.changeDynamics(
            self.obj,
            -1,
            localInertiaDiagonal=np.maximum(evals, 1e-9).tolist(),
            lateralFriction=prm.friction_coef,
            collisionMargin=prm.collision_margin,
            physicsClientId=c,
        )
        n_parts = len(p.getCollisionShapeData(self.obj, -1, physicsClientId=c))
        self._obj_T0 = None
        self._park_gripper()
        self._reset_object(T0)
        for _ in range(int(round(prm.settle_time / prm.time_step))):
            p.stepSimulation(physicsClientId=c)
        T1 = self.object_pose()
        dt = float(np.linalg.norm(T1[:3, 3] - T0[:3, 3]))
        dr = _angle(T0[:3, :3], T1[:3, :3])
        self._obj_T0 = T1
        self._park_gripper()  # the first trial starts from the same state as every later one
        return {
            "stable": dt <= prm.stable_translation and dr <= prm.stable_rotation,
            "drift_m": dt,
            "drift_rad": dr,
            "convex": convex,
            "parts": n_parts,
        }

    def _park_gripper(self) -> None:
        """Move the gripper far away, put the object back in its settled pose (when set) and
        drop stale contact pairs, so that every trial starts from the same state."""
        T = np.eye(4)
        T[:3, 3] = [0.0, 0.0, 5.0]
        self._place_gripper(T)
        if self.obj is not None and self._obj_T0 is not None:
            self._reset_object(self._obj_T0)
        self.p.performCollisionDetection(physicsClientId=self.cid)

    def _reset_object(self, T: np.ndarray) -> None:
        p, c = self.p, self.cid
        T = T @ self._T_oi
        p.resetBasePositionAndOrientation(self.obj, T[:3, 3].tolist(), _quat_xyzw(T[:3, :3]), physicsClientId=c)
        p.resetBaseVelocity(self.obj, [0, 0, 0], [0, 0, 0], physicsClientId=c)

    def object_pose(self) -> np.ndarray:
        """``T_world_object`` (4, 4) of the trial object now."""
        pos, orn = self.p.getBasePositionAndOrientation(self.obj, physicsClientId=self.cid)
        T = np.eye(4)
        T[:3, :3] = _matrix(orn)
        T[:3, 3] = pos
        return T @ self._T_io

    def gripper_pose(self) -> np.ndarray:
        """Current grasp frame of the gripper (from its palm's pose)."""
        pos, orn = self.p.getBasePositionAndOrientation(self.gripper, physicsClientId=self.cid)
        T = np.eye(4)
        T[:3, :3] = _matrix(orn)
        T[:3, 3] = np.asarray(pos) - T[:3, :3] @ self._palm_offset
        return T

    # -- trials
    def _touching(self, a: int, b: int, link: int | None = None) -> bool:
        kw = {} if link is None else {"linkIndexA": link}
        return len(self.p.getContactPoints(a, b, physicsClientId=self.cid, **kw)) > 0

    def trial(self, T_world_grasp: np.ndarray, mu: float) -> tuple[str, bool, np.ndarray]:
        """One trial of the grasp ``T_world_grasp`` (4, 4) with object friction ``mu`` (no
        noise is added here). Returns ``(reason, firm, first_touch (2, 3) object frame)``;
        the grasp held when reason is "held"."""
        p, c, prm = self.p, self.cid, self.params
        touch = np.full((2, 3), np.nan)
        if self.obj is None:
            raise RuntimeError("set_object first")
        self._reset_object(self._obj_T0)
        # the pads' torsion limit per newton, (2/3) mu r: set on the object, as pybullet takes a pad
        # contact's spinning friction from the object's side (set on the finger links it had no effect)
        spin = 2.0 / 3.0 * float(mu) * prm.pad_contact_radius
        p.changeDynamics(self.obj, -1, lateralFriction=float(mu), spinningFriction=spin, physicsClientId=c)
        T_g = np.asarray(T_world_grasp, dtype=np.float64)
        T_start = T_g.copy()
        T_start[:3, 3] -= prm.approach_distance * T_g[:3, 2]
        self._place_gripper(T_start)
        p.performCollisionDetection(physicsClientId=c)
        if p.getClosestPoints(self.gripper, self.obj, 0.0, physicsClientId=c) or p.getClosestPoints(
            self.gripper, self.table, 0.0, physicsClientId=c
        ):
            self._park_gripper()
            return "start_collision", False, touch
        dt = prm.time_step
        # approach: straight line to the grasp pose
        n_app = max(1, int(np.ceil(prm.approach_distance / prm.approach_speed / dt)))
        for i in range(1, n_app + 1):
            T = T_g.copy()
            T[:3, 3] = T_start[:3, 3] + (i / n_app) * (T_g[:3, 3] - T_start[:3, 3])
            self._drive_to(T)
            self._step()
            if self._touching(self.gripper, self.table):
                self._park_gripper()
                return "table", False, touch
        # close
        self._drive_jaw(prm.close_speed)
        n_close = int(np.ceil((self._travel / prm.close_speed + 0.15) / dt))
        still = 0
        squeezing = False
        seen = [0, 0]
        touch_sum, touch_w = np.zeros((2, 3)), np.zeros(2)
        for _ in range(n_close):
            self._step()
            if not squeezing and self._touching(self.gripper, self.obj):
                squeezing = True
                self._drive_jaw(prm.squeeze_speed)
            if self._touching(self.gripper, self.table):
                self._park_gripper()
                return "table", False, touch
            for j in (0, 1):
                if seen[j] < prm.touch_steps:
                    pts = p.getContactPoints(self.gripper, self.obj, linkIndexA=j, physicsClientId=c)
                    if pts or seen[j] > 0:
                        seen[j] += 1
                    if pts:
                        Tw = self.object_pose()
                        pw = np.array([q[6] for q in pts])  # positionOnB: on the object
                        wt = np.array([max(q[9], 1e-6) for q in pts])  # normal force
                        touch_sum[j] += wt @ ((pw - Tw[:3, 3]) @ Tw[:3, :3])
                        touch_w[j] += wt.sum()
            vel = [s[1] for s in p.getJointStates(self.gripper, [0, 1], physicsClientId=c)]
            still = still + 1 if max(abs(v) for v in vel) < 1e-3 else 0
            if still >= 5:
                break
        for j in (0, 1):
            if touch_w[j] > 0:
                touch[j] = touch_sum[j] / touch_w[j]
        T_go_closed = np.linalg.inv(self.gripper_pose()) @ self.object_pose()
        z0 = self.object_pose()[2, 3]
        # lift
        T_top = T_g.copy()
        n_lift = max(1, int(np.ceil(prm.lift_height / prm.lift_speed / dt)))
        lost = False
        for i in range(1, n_lift + 1):
            T_top[2, 3] = T_g[2, 3] + prm.lift_height * _smooth(i / n_lift)
            self._drive_to(T_top)
            self._step()
            if i % 12 == 0 and not self._touching(self.gripper, self.obj):
                lost = True  # the object is out of the jaws: it cannot be held at the end
                break
        # shake: a horizontal circle
        n_shake = int(round(prm.shake_duration / dt))
        w = 2 * np.pi * prm.shake_frequency
        for i in range(1, 0 if lost else n_shake + 1):
            if i % 12 == 0 and not self._touching(self.gripper, self.obj):
                break
            t = i * dt
            T = T_top.copy()
            a = prm.shake_amplitude * _smooth(min(1.0, 4.0 * i / n_shake))  # ramp in over the first quarter
            T[0, 3] += a * np.sin(w * t)
            T[1, 3] += a * (1 - np.cos(w * t))
            self._drive_to(T)
            self._step()
        T_obj = self.object_pose()
        held = T_obj[2, 3] - z0 > 0.5 * prm.lift_height and self._touching(self.gripper, self.obj)
        firm = False
        if held:
            T_go = np.linalg.inv(self.gripper_pose()) @ T_obj
            firm = (
                np.linalg.norm(T_go[:3, 3] - T_go_closed[:3, 3]) <= prm.firm_translation
                and _angle(T_go[:3, :3], T_go_closed[:3, :3]) <= prm.firm_rotation
            )
        self._park_gripper()
        return ("held" if held else "dropped"), bool(firm), touch


def _smooth(s: float) -> float:
    """Smooth 0 -> 1 ramp (zero velocity at both ends) of s in [0, 1]."""
    return 0.5 - 0.5 * np.cos(np.pi * s)


def _angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


# ----------------------------------------------------------------------------- batches


def execution_noise(n: int, k: int, params: PhysicsParams, rng: np.random.Generator):
    """Noise of n grasps x k trials: ``(dt (n, k, 3) metres, R (n, k, 3, 3), mu (n, k))``."""
    dt = params.sigma_translation * rng.standard_normal((n, k, 3))
    R = _rotvec_matrices(params.sigma_rotation * rng.standard_normal((n * k, 3))).reshape(n, k, 3, 3)
    mu = np.maximum(params.friction_coef + params.sigma_friction * rng.standard_normal((n, k)), params.min_friction)
    return dt, R, mu


def perturbed_frames(T_world_grasp: np.ndarray, dt: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Grasp frames (n, k, 4, 4): each frame (n, 4, 4) rotated about its TCP by R (n, k, 3, 3)
    (world-frame rotation) and translated by dt (n, k, 3), world frame."""
    T = np.asarray(T_world_grasp, dtype=np.float64)
    k = dt.shape[1]
    out = np.tile(T[:, None], (1, k, 1, 1))
    out[:, :, :3, :3] = R @ T[:, None, :3, :3]
    out[:, :, :3, 3] = T[:, None, :3, 3] + dt
    return out


def run_trials(
    sim: GraspSimulator,
    T_world_grasp: np.ndarray,
    num_trials: int,
    rng: np.random.Generator | None,
    stop_above: float | None = None,
) -> TrialResults:
    """``num_trials`` trials of each grasp (n, 4, 4) on the simulator's current object. With
    ``rng`` None the trials are noise-free (mu = friction_coef), else execution noise is drawn
    from ``rng`` (all of it first, so a trial's noise does not depend on which trials ran).

    ``stop_above``: a grasp's trials stop once whether its success rate over all ``num_trials``
    exceeds this is decided (e.g. 0.5 of 8: at 5 held or 4 dropped); ``success_rate`` is then over
    the trials run and lies on the same side of the threshold as the full rate would."""
    T = np.asarray(T_world_grasp, dtype=np.float64).reshape(-1, 4, 4)
    n, k = len(T), int(num_trials)
    prm = sim.params
    if rng is None:
        dt, R, mu = np.zeros((n, k, 3)), np.tile(np.eye(3), (n, k, 1, 1)), np.full((n, k), prm.friction_coef)
    else:
        dt, R, mu = execution_noise(n, k, prm, rng)
    Tp = perturbed_frames(T, dt, R)
    held = np.zeros((n, k), bool)
    firm = np.zeros((n, k), bool)
    reason = np.zeros((n, k), np.int8)
    touch = np.full((n, k, 2, 3), np.nan)
    ran = np.zeros((n, k), bool)
    need = k + 1 if stop_above is None else int(np.floor(stop_above * k)) + 1  # held trials for "above"
    t0 = time.perf_counter()
    for i in range(n):
        n_held = 0
        for j in range(k):
            r, f, tt = sim.trial(Tp[i, j], mu[i, j])
            held[i, j] = r == "held"
            firm[i, j] = f
            reason[i, j] = REASONS.index(r)
            touch[i, j] = tt
            ran[i, j] = True
            n_held += int(held[i, j])
            if stop_above is not None and (n_held >= need or j + 1 - n_held > k - need):  # decided
                break
    return TrialResults(held, firm, reason, touch, mu, time.perf_counter() - t0, None if stop_above is None else ran)


_SIMS: dict = {}


def _worker_sim(gripper: GripperGeometry, params: PhysicsParams, cache_dir) -> GraspSimulator:
    """One simulator per worker process (reused across tasks with the same settings)."""
    key = (gripper, params, str(cache_dir))
    sim = _SIMS.get(key)
    if sim is None:
        for s in _SIMS.values():
            s.close()
        _SIMS.clear()
        sim = _SIMS[key] = GraspSimulator(gripper, params, cache_dir)
    return sim


def object_trials_task(
    vertices,
    faces,
    T_world_object,
    T_world_grasp,
    gripper: GripperGeometry,
    params: PhysicsParams,
    num_trials: int,
    seed: int | None,
    cache_dir=None,
    tag=None,
) -> dict:
    """Process-pool / Ray task: the trials of one object's grasps in one stable pose (arrays
    in, arrays out). ``seed`` None -> noise-free. Returns a dict with the TrialResults fields,
    the pose check (``pose``) and ``tag``."""
    mesh = trimesh.Trimesh(vertices=np.asarray(vertices), faces=np.asarray(faces), process=False)
    sim = _worker_sim(gripper, params, cache_dir)
    pose = sim.set_object(mesh, T_world_object)
    rng = None if seed is None else np.random.default_rng(seed)
    res = run_trials(sim, T_world_grasp, num_trials, rng)
    return {
        "tag": tag,
        "pose": pose,
        "held": res.held,
        "firm": res.firm,
        "reason": res.reason,
        "first_touch": res.first_touch,
        "mu": res.mu,
        "seconds": res.seconds,
    }
