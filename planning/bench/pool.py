"""``python -m planning.bench pool``: what makes the sampler's candidates hold (trials of random
candidates and each feature's ROC AUC)."""

from __future__ import annotations

import dataclasses

import numpy as np

from .common import draw_scenes
from .scenes import BenchScene, make_scene

POOL_FEATURES = {
    "fingertip_height": "lowest gripper point above the true table (m)",
    "width": "contact distance (m)",
    "com_line_offset": "distance of the true centre of mass from the jaw line (m)",
    "tcp_height": "TCP above the true table (m)",
    "approach_tilt": "approach from straight down (deg)",
    "axis_tilt": "jaw axis from vertical (deg)",
    "score": "the model's score",
}


def candidate_features(scene: BenchScene, frames_world: np.ndarray, contacts_cam: np.ndarray, scores, gripper) -> dict:
    """:data:`POOL_FEATURES` of grasp frames (n, 4, 4) in the world frame (table z = 0)."""
    from ..features import table_features

    x, t = frames_world[:, :3, 0], frames_world[:, :3, 3]
    d = scene.T_world_object[:3, 3] - t  # meshes are centred on their centre of mass
    f = table_features(frames_world, np.array([0.0, 0.0, 1.0]), 0.0, gripper)  # the true table
    return {
        "fingertip_height": f["table_clearance"],
        "width": np.linalg.norm(contacts_cam[:, 1] - contacts_cam[:, 0], axis=1),
        "com_line_offset": np.linalg.norm(d - np.sum(d * x, axis=1, keepdims=True) * x, axis=1),
        "tcp_height": f["tcp_height"],
        "approach_tilt": f["approach_tilt"],
        "axis_tilt": f["axis_tilt"],
        "score": np.asarray(scores, np.float64),
    }


def run_pool(args) -> dict:
    """What makes the sampler's candidates hold: pybullet trials (datagen.physics, execution
    noise) of ``--per-scene`` random candidates per scene, the trial outcomes, and each
    :data:`POOL_FEATURES`' ROC AUC for "held in more than half the trials"."""
    from datagen.gripper import GripperGeometry as DatagenGripper
    from datagen.physics import REASONS, GraspSimulator, PhysicsParams, run_trials
    from training.metrics import auc

    from ..features import PLAN_FEATURES, plan_features
    from ..policy import plan
    from ..sampler import Candidates

    model, config, params, picked, rng = draw_scenes(args)
    feats: dict[str, list] = {k: [] for k in POOL_FEATURES}
    planned: dict[str, list] = {k: [] for k in PLAN_FEATURES}  # what the planner itself knows (planning.features)
    held, reasons, scenes, scene_of, retest = [], [], 0, [], []
    with GraspSimulator(DatagenGripper(**dataclasses.asdict(config.gripper)), PhysicsParams()) as sim:
        for i, oid in enumerate(picked):
            scene = make_scene(int(oid), config, rng)
            res = plan(scene.depth, config.intrinsics, model, k=5, seed=int(args.seed) + i, params=params)
            if not res.grasps:
                continue
            scenes += 1
            c = res.candidates
            pick = np.random.default_rng(2000 + i).choice(
                len(c["frames"]), min(len(c["frames"]), args.per_scene), False
            )
            Tw = scene.T_world_camera @ c["frames"][pick]
            sim.set_object(scene.mesh_object, scene.T_world_object)
            tr = run_trials(sim, Tw, args.trials, np.random.default_rng(3000 + i))
            held.append(tr.held.mean(axis=1))
            reasons.append(tr.reason)
            scene_of.append(np.full(len(pick), i))
            if args.retest:  # the oracle's own best judged candidate, judged again on fresh trials
                best = int(np.argmax(held[-1]))
                again = run_trials(sim, Tw[best : best + 1], args.trials, np.random.default_rng(4000 + i))
                retest.append((held[-1][best], float(again.held.mean())))
            for k, v in candidate_features(scene, Tw, c["contacts"][pick], c["scores"][pick], params.gripper).items():
                feats[k].append(v)
            seen = Candidates(c["frames"][pick], c["contacts"][pick], c["widths"][pick], c["seen"][pick])
            for k, v in plan_features(seen, c["scores"][pick], c["scene"], params.gripper).items():
                planned[k].append(v)
            print(f"scene {i:2d} object {oid:3d}: {len(pick)} candidates, held {held[-1].mean():.2f}", flush=True)
    rate = np.concatenate(held) if held else np.zeros(0)
    outcome = np.concatenate(reasons) if reasons else np.zeros((0, args.trials), np.int8)
    y = rate > 0.5
    out = {
        "scenes": len(picked),
        "scenes_with_candidates": scenes,
        "candidates": int(len(rate)),
        "trials_per_candidate": args.trials,
        "mean_held": float(rate.mean()) if len(rate) else 0.0,
        "positive": float(y.mean()) if len(rate) else 0.0,
        "outcomes": {r: float((outcome == j).mean()) if outcome.size else 0.0 for j, r in enumerate(REASONS)},
        "table_margin": params.table_margin,
        "auc": {k: auc(np.concatenate(v), y) if v else float("nan") for k, v in feats.items()},
        "seed": args.seed,
        # --retest: per scene, the judged candidate that held most, and its share of fresh trials held
        "retest": {
            "first": [a for a, _ in retest],
            "again": [b for _, b in retest],
            "positive_again": float(np.mean([b > 0.5 for _, b in retest])) if retest else None,
            "positive_first": float(np.mean([a > 0.5 for a, _ in retest])) if retest else None,
        },
        # one row per judged candidate: its scene (index into the drawn objects), features, trials held
        "candidate_rows": {
            "scene": np.concatenate(scene_of).tolist() if scene_of else [],
            "object_id": [int(picked[j]) for j in np.concatenate(scene_of)] if scene_of else [],
            "held": rate.tolist(),
            **{k: np.concatenate(v).tolist() if v else [] for k, v in feats.items()},
            **{f"plan_{k}": np.concatenate(v).tolist() if v else [] for k, v in planned.items()},
        },
    }
    print(
        f"\n{out['candidates']} candidates of {scenes} scenes, {args.trials} trials each (table margin "
        f"{1e3 * params.table_margin:g} mm): held {100 * out['mean_held']:.1f}% of trials, "
        f"{100 * out['positive']:.1f}% held in more than half"
    )
    print("trial outcomes: " + ", ".join(f"{k} {100 * v:.1f}%" for k, v in out["outcomes"].items()))
    if retest:
        print(
            f"retest: the candidate that held most in each scene held in more than half of {args.trials} "
            f"fresh trials in {100 * out['retest']['positive_again']:.1f}% of {len(retest)} scenes "
            f"(first judging: {100 * out['retest']['positive_first']:.1f}%)"
        )
    print("ROC AUC of each feature for 'held in more than half':")
    for k, v in out["auc"].items():
        print(f"  {k:18s} {v:.3f}   ({POOL_FEATURES[k]})")
    return out
