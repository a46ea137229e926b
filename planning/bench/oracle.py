"""The oracle that judges a benchmark's grasps on the true mesh: robust Ferrari-Canny or the
recipe's noisy pybullet trials, and no collision of the swept gripper with the mesh or the table."""

from __future__ import annotations

import dataclasses

import numpy as np

from .scenes import BenchScene

ORACLES = ("fc", "physics")


def default_oracle(config) -> str:
    """The oracle matching the label the model learnt: physics trials for the physics label,
    robust Ferrari-Canny otherwise."""
    return "physics" if config.label.kind == "physics" else "fc"


def judge(scene: BenchScene, frames_cam: np.ndarray, config, rng: np.random.Generator, oracle: str = "fc") -> dict:
    """Oracle verdicts for grasp frames (n, 4, 4) in the camera frame: ``collides`` (swept
    gripper vs true mesh and table) and ``quality``: with ``oracle`` "fc" the robust
    Ferrari-Canny on the true mesh (positive above the recipe's Ferrari-Canny threshold), with
    "physics" the success rate of the recipe's number of noisy pybullet trials of the grasp on
    the object in its pose (positive above the label's success threshold). ``positive`` also
    needs no collision; colliding grasps get quality 0 under the physics oracle (no trials)."""
    from datagen.collision import CollisionChecker

    if oracle not in ORACLES:
        raise ValueError(f"oracle must be one of {ORACLES}, got {oracle!r}")
    n = len(frames_cam)
    if n == 0:
        z = np.zeros(0)
        return {"quality": z, "collides": z.astype(bool), "positive": z.astype(bool)}
    T_wg = scene.T_world_camera @ frames_cam
    collides = np.asarray(CollisionChecker(scene.mesh_world, config.gripper).collides(T_wg), bool)
    if oracle == "physics":
        from datagen.physics import GraspSimulator, run_trials

        quality = np.zeros(n)
        free = np.flatnonzero(~collides)
        if len(free):
            with GraspSimulator(config.gripper, config.physics) as sim:
                sim.set_object(scene.mesh_object, scene.T_world_object)
                quality[free] = run_trials(sim, T_wg[free], config.label.trials, rng).success_rate
        return {
            "quality": quality,
            "collides": collides,
            "positive": (quality > config.label.success_threshold) & ~collides,
        }
    from datagen.grasps import AntipodalGrasps
    from datagen.quality import robust_ferrari_canny

    T_og = np.linalg.inv(scene.T_world_object) @ T_wg
    grasps = AntipodalGrasps(T_og[:, :3, 3], T_og[:, :3, 0], np.zeros((n, 2, 3)), np.zeros((n, 2, 3)), np.zeros(n))
    qp = dataclasses.replace(config.quality, torque_scaling=scene.torque_scaling)
    quality = robust_ferrari_canny(scene.mesh_object, grasps, qp, rng)
    return {
        "quality": quality,
        "collides": collides,
        "positive": (quality > config.quality.label_threshold) & ~collides,
    }
