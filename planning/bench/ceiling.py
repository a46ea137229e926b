"""``python -m planning.bench ceiling``: what the physics oracle lets any planner reach, judged on
datagen's own grasps on the true mesh."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from .common import draw_scenes
from .scenes import make_scene


def run_ceiling(args) -> dict:
    """What the physics oracle lets any planner reach: in each scene (a held-out object, as
    :func:`make_scene`), datagen's own antipodal grasps on the true mesh (its sampler, approaches
    aligned as datagen aligns them, collision-free at the nominal pose) are judged by the oracle's
    trials; the one that held most is judged again on fresh trials (the precision@1 of a planner
    that always picked the best true-mesh grasp of a judging), and so is every grasp that held in
    at least half, for the fresh success by first count (winner's curse and trial noise in one)."""
    from datagen.collision import CollisionChecker
    from datagen.grasps import sample_antipodal_grasps
    from datagen.gripper import align_to_table, grasp_frames
    from datagen.physics import GraspSimulator, run_trials

    _, config, _, picked, rng = draw_scenes(args)
    trials, threshold = args.trials or config.label.trials, config.label.success_threshold
    antipodal = dataclasses.replace(config.antipodal, num_samples=args.grasps or config.antipodal.num_samples)
    first, again, rows = [], [], []  # per scene: the re-judged grasps' two rates; the scene's row
    with GraspSimulator(config.gripper, config.physics) as sim:
        for i, oid in enumerate(picked):
            scene = make_scene(int(oid), config, rng)  # the shared rng draws only scenes: those of `trials`
            rng_g = np.random.default_rng(8000 + i)
            g = sample_antipodal_grasps(scene.mesh_object, antipodal, rng_g)
            if len(g) == 0:
                continue
            T0 = np.repeat(grasp_frames(g.centers, g.axes, 0.0), args.approaches, axis=0)  # omega drawn per copy
            T_wg = align_to_table(scene.T_world_object @ T0, rng_g)[0]
            T_wg = T_wg[~np.asarray(CollisionChecker(scene.mesh_world, config.gripper).collides(T_wg), bool)]
            if len(T_wg) == 0:
                continue
            sim.set_object(scene.mesh_object, scene.T_world_object)
            s1 = run_trials(sim, T_wg, trials, np.random.default_rng(5000 + i)).success_rate
            keep = np.flatnonzero(s1 >= 0.5)
            best = int(np.argmax(s1))
            if best not in keep:
                keep = np.append(keep, best)
            if args.confirm:  # the first judging's top grasps get 3x more trials; the best by all of them
                top = np.argsort(-s1, kind="stable")[: args.confirm]
                more = run_trials(sim, T_wg[top], 3 * trials, np.random.default_rng(7000 + i)).success_rate
                est = (s1[top] + 3 * more) / 4
                pick = int(top[np.argmax(est)])
                if pick not in keep:
                    keep = np.append(keep, pick)
            s2 = run_trials(sim, T_wg[keep], trials, np.random.default_rng(6000 + i)).success_rate
            first.append(s1[keep])
            again.append(s2)
            at = {int(gi): j for j, gi in enumerate(keep)}  # grasp index -> its place in the re-judged ones
            row = {"scene": i, "object_id": int(oid), "free_grasps": len(T_wg)}
            row.update(best_first=float(s1[best]), best_again=float(s2[at[best]]))
            line = f"best held {trials * s1[best]:.0f}/{trials}, again {trials * row['best_again']:.0f}/{trials}"
            if args.confirm:
                row.update(confirmed_estimate=float(est.max()), confirmed_again=float(s2[at[pick]]))
                line += (
                    f"; confirmed pick {100 * row['confirmed_estimate']:.0f}% of {4 * trials}, "
                    f"again {trials * row['confirmed_again']:.0f}/{trials}"
                )
            rows.append(row)
            print(f"scene {i:2d} object {oid:4d}: {len(T_wg)} free grasps, {line}", flush=True)
    f = np.concatenate(first) if first else np.zeros(0)
    a = np.concatenate(again) if again else np.zeros(0)
    by_count = {}
    for k in range(int(np.ceil(trials / 2)), trials + 1):
        m = np.isclose(f * trials, k)
        if m.any():
            by_count[f"{k}/{trials}"] = {
                "grasps": int(m.sum()),
                "held_again": float(a[m].mean()),
                "positive_again": float((a[m] > threshold).mean()),
            }
    scenes = len(rows)
    bf, ba = np.array([r["best_first"] for r in rows]), np.array([r["best_again"] for r in rows])
    confirmed = [(r["confirmed_estimate"], r["confirmed_again"]) for r in rows if "confirmed_estimate" in r]
    out = {
        "scenes": len(picked),
        "scenes_with_grasps": scenes,
        "trials": trials,
        "success_threshold": threshold,
        "best_positive_first": float((bf > threshold).mean()) if scenes else None,
        "best_positive_again": float((ba > threshold).mean()) if scenes else None,
        "best_held_again": float(ba.mean()) if scenes else None,
        "by_first_count": by_count,
        # --confirm K: the pick by 4x the trials among the first judging's top K, and its fresh judging
        "confirmed_estimate": [e for e, _ in confirmed],
        "confirmed_again": [r for _, r in confirmed],
        "confirmed_positive_again": float(np.mean([r > threshold for _, r in confirmed])) if confirmed else None,
        "grasps_per_scene": antipodal.num_samples,
        "approaches_per_grasp": args.approaches,
        "seed": args.seed,
        "rows": rows,  # per scene with grasps: its index among the drawn scenes (those of `trials`, same seed)
    }
    if scenes:
        print(
            f"\nthe best true-mesh grasp of each of {scenes} scenes (by {trials} trials) held in more than "
            f"{threshold:g} of {trials} fresh trials in {100 * out['best_positive_again']:.1f}% of the scenes "
            f"(first judging {100 * out['best_positive_first']:.1f}%), {100 * out['best_held_again']:.1f}% of "
            "its fresh trials"
        )
    if confirmed:
        print(
            f"the pick among each scene's top {args.confirm} by {4 * trials} trials held in more than {threshold:g} of "
            f"{trials} fresh trials in {100 * out['confirmed_positive_again']:.1f}% of the scenes"
        )
    for k, v in by_count.items():
        print(
            f"  held {k} first: {v['grasps']:4d} grasps, held {100 * v['held_again']:.1f}% of fresh trials, "
            f"positive again {100 * v['positive_again']:.1f}%"
        )
    if args.plan and confirmed:
        out["plan_by_ceiling"] = plan_by_ceiling(args.plan_run, out)
        for k, v in out["plan_by_ceiling"].items():
            print(
                f"  the plan's top-1 in scenes whose best true-mesh grasp {k}: {v['positive']}/{v['scenes']} positive"
            )
    return out


def read_trials_run(path: str, seed: int, scenes: int) -> dict:
    """A ``trials --json`` run of ``seed`` and ``scenes`` (so the same scenes), or ValueError saying why not."""
    try:
        run = json.loads(Path(path).read_text())
    except (OSError, ValueError) as e:
        raise ValueError(f"not a readable `trials --json` file ({e})") from None
    rows = run.get("rows") if isinstance(run, dict) else None
    if not isinstance(rows, list) or any(not isinstance(r, dict) or "top1_held" not in r for r in rows):
        raise ValueError("not a `trials --json` file (no per-scene top-1 rows)")
    if run.get("seed") != seed or run.get("scenes") != scenes or len(rows) != scenes:
        raise ValueError(
            f"must be a `trials` run with the same --seed ({seed}) and --scenes ({scenes}): the same scenes"
        )
    return run


#: scene classes by the confirmed pick's success over its 4x trials (``ceiling --confirm``)
CEILING_CLASSES = {"holds >= 75%": (0.75, 1.01), "holds 50-75%": (0.5, 0.75), "holds < 50%": (0.0, 0.5)}


def plan_by_ceiling(trials_out: dict, ceiling_out: dict) -> dict:
    """The plan's top-1 verdicts (a ``trials`` run's rows: same seed and scene count, so the same
    scenes) per class of scene by how well its best true-mesh grasp holds (``ceiling --confirm``);
    scenes the planner found no grasp in count as negatives."""
    if trials_out.get("seed") != ceiling_out["seed"] or trials_out.get("scenes") != ceiling_out["scenes"]:
        raise ValueError("--plan must be a `trials` run with the same --seed and --scenes (the same scenes)")
    plan_rows = trials_out["rows"]
    out = {}
    for name, (lo, hi) in CEILING_CLASSES.items():
        idx = [r["scene"] for r in ceiling_out["rows"] if lo <= r.get("confirmed_estimate", -1) < hi]
        pos = [plan_rows[i]["top1_held"] > ceiling_out["success_threshold"] * plan_rows[i]["trials"] for i in idx]
        out[name] = {"scenes": len(idx), "positive": int(sum(pos))}
    return out
