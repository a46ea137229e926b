"""Planning benchmark: speed, and precision judged by datagen's oracle.

``python -m planning.bench timing``: p50 / p99 of :func:`planning.policy.plan` on a
300 x 300 rendered scene (256 candidates, encoder included), with the stages' medians.

``python -m planning.bench precision``: scenes of held-out test objects of the bundled
model's recipe (the ``object_id``s of examples/heldout_test_crops.npz, or of a crop
dataset's test split given as ``--heldout DIR``, index the recipe's objects), each on a
stable pose drawn by probability under a camera drawn from the recipe's ranges, rendered by
datagen. The planner sees only the depth image. Every
candidate it scored is judged by the oracle: robust Ferrari-Canny on the true mesh
(datagen.quality, the recipe's parameters) > its threshold, or with ``--oracle physics``
(the default for a model trained on the physics label) the recipe's noisy pybullet trials
(datagen.physics) succeeding more often than the label's threshold, for the top 5 and a
random sample of the candidates; and no collision of the swept gripper with the true mesh or
the table (datagen.collision) at the known camera pose. Reported: precision@1 and @5 of the plan (top-k after NMS), of a random
collision-free candidate of the same sampler (its expectation: the positive share of the
candidates), and of the pose-only baseline's ranking of the same candidates when its model
file exists (``--baseline FILE`` or ``baseline_mlp.npz`` in the model folder).

``python -m planning.bench ceiling``: the same scenes, judged on datagen's own grasps on the
true mesh instead of the planner's: how often the best of a scene's true-mesh grasps by one
judging of the physics oracle passes a second one (what no ranking of any pool can beat by much).

Needs the datagen extra (trimesh, python-fcl, embree); the planner itself does not.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from .types import PlanParams

MODEL_DIR = "models/fast-vgqcnn-default"
HELDOUT = "examples/heldout_test_crops.npz"


def _model(model_dir: str, threads: int, head_precision: str = "auto"):
    from service.runtime import FastModel

    m = FastModel(model_dir, threads=threads, head_precision=head_precision)
    m.warm_up(5)
    return m


def _recipe_config(model):
    from datagen.config import DatagenConfig, recorded_config

    try:  # upgraded like a dataset manifest's: a recipe recorded before the label setting had the paper's
        return DatagenConfig.from_dict(recorded_config(model.card.dataset["source"]["config"]))
    except Exception:  # an older card without the full config: the defaults are the recipe's
        return DatagenConfig()


def heldout_object_ids(path: str = HELDOUT, split: str = "test") -> list[int]:
    """Test object ids: those of a held-out crop file (.npz with ``object_id``), or the ``split``
    (test by default; train or val to fit something on other objects) of a crop dataset folder
    (e.g. data/v2/crops, whose ids index the recipe's objects, families included)."""
    p = Path(path)
    if p.is_dir():
        from vgq.schema import CROP_FORMAT, read_manifest

        ids = read_manifest(p, CROP_FORMAT)["counts"].get(split, {}).get("objects") or []
        if not ids:
            raise ValueError(f"{p}: its manifest lists no {split} objects")
        return sorted(int(i) for i in ids)
    return sorted(int(i) for i in np.unique(np.load(p)["object_id"]))


UNSEEN = "unseen"  # --heldout: objects outside the model's dataset


def unseen_config(config):
    """The recipe's config with objects outside its dataset: every mesh of its source (the recipe
    takes the first ``num_objects``) and each family's objects drawn with another seed."""
    return dataclasses.replace(config, num_objects=None, seed=config.seed + 1)


def scene_objects(heldout: str, split: str, config) -> tuple[list[int], object]:
    """(object ids, the config whose sources they index) of a benchmark's scenes: ``heldout``
    a held-out crop file or dataset folder (:func:`heldout_object_ids`, the recipe's objects),
    or ``unseen``: objects the model's dataset never held (:func:`unseen_config`; the mesh
    source's meshes past the recipe's and newly drawn family objects), to fit the planner's
    ranker and calibration on objects as new to the model as a user's."""
    if heldout != UNSEEN:
        return heldout_object_ids(heldout, split), config
    cfg = unseen_config(config)
    sources = _recipe_sources(json.dumps(cfg.to_dict(), sort_keys=True))
    n = config.num_objects
    ids = [i for i, src in enumerate(sources) if src.family is not None or (n is not None and i >= n)]
    if not ids:
        raise ValueError("the recipe's config leaves no object outside its dataset")
    return ids, cfg


@dataclasses.dataclass
class BenchScene:
    object_id: int
    mesh_object: object  # trimesh, object frame (centre of mass at the origin)
    mesh_world: object
    T_world_object: np.ndarray
    T_world_camera: np.ndarray
    depth: np.ndarray
    torque_scaling: float


@functools.lru_cache(maxsize=4)
def _recipe_sources(config_json: str) -> list:
    """The recipe's mesh sources (families included; drawing their parameters takes seconds)."""
    from datagen.config import DatagenConfig
    from datagen.pipeline import run_sources

    return run_sources(DatagenConfig.from_dict(json.loads(config_json)))


def make_scene(object_id: int, config, rng: np.random.Generator) -> BenchScene:
    """One held-out object on a stable pose (drawn by probability), seen by a recipe camera."""
    from datagen.camera import sample_cameras
    from datagen.mesh import load_object, stable_poses
    from datagen.quality import resolve_torque_scaling
    from datagen.render import render_depth

    sources = _recipe_sources(json.dumps(config.to_dict(), sort_keys=True))
    obj = load_object(sources[object_id], config.mesh)  # the recipe's objects, families included
    T_poses, probs = stable_poses(obj, config.stable_pose_min_probability, config.max_stable_poses)
    T_wo = T_poses[rng.choice(len(probs), p=probs / probs.sum())]
    mesh_world = obj.mesh.copy()
    mesh_world.apply_transform(T_wo)
    T_wc = sample_cameras(1, config.camera, rng).T_world_camera[0]
    depth = render_depth(mesh_world, T_wc, config.intrinsics)
    return BenchScene(
        object_id, obj.mesh, mesh_world, T_wo, T_wc, depth, resolve_torque_scaling(obj.mesh, config.quality)
    )


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


def pose_only_model(model_dir: str, path: str | None = None):
    """The pose-only baseline (:class:`vgq.pose_only.PoseOnlyModel`): ``path`` (a
    ``training baseline`` output), else the model folder's ``baseline_mlp.npz`` /
    ``baseline_logreg.npz`` (export copies it there), else None."""
    from vgq.pose_only import PoseOnlyModel, file_name

    if path:
        return PoseOnlyModel.load(path), Path(path)
    for name in (file_name("mlp"), file_name("logreg")):
        p = Path(model_dir) / name
        if p.exists():
            return PoseOnlyModel.load(p), p
    return None, None


def plan_params(args) -> PlanParams:
    """The planner settings a benchmark's command line asks for (the rest: ``PlanParams()``)."""
    return dataclasses.replace(
        PlanParams(),
        cem_iterations=args.cem,
        windows=args.windows,
        max_centre_offset=args.centre_offset,
        min_width=args.min_width,
        table_margin=args.table_margin,
        max_approach_tilt=np.radians(args.max_approach_tilt),
        top_view_cell=args.top_view_cell if args.top_view_cell > 0 else None,
    )


def _setup(args):
    """(model, recipe config, planner params, held-out object ids drawn, rng) of a benchmark run:
    the same seed draws the same objects for every benchmark."""
    model = _model(args.model, args.threads)
    params = plan_params(args)
    ids, config = scene_objects(args.heldout, args.split, _recipe_config(model))
    rng = np.random.default_rng(args.seed)
    picked = rng.choice(ids, size=args.scenes, replace=args.scenes > len(ids))
    return model, config, params, picked, rng


def run_precision(args) -> dict:
    from .policy import nms, plan

    model, config, params, picked, rng = _setup(args)
    oracle = args.oracle or default_oracle(config)
    baseline, baseline_file = pose_only_model(args.model, args.baseline)
    rows = []
    for i, oid in enumerate(picked):
        t = time.perf_counter()
        scene = make_scene(int(oid), config, rng)
        res = plan(scene.depth, config.intrinsics, model, k=5, seed=int(args.seed) + i, params=params)
        cand = res.candidates or {"frames": np.zeros((0, 4, 4)), "scores": np.zeros(0)}
        n = len(cand["frames"])
        order = cand["scores"] if cand.get("utility") is None else cand["utility"]  # what the planner ranked by
        top = nms(cand["frames"], order, 5, params.nms_distance, params.nms_angle) if n else np.zeros(0, int)
        # the network's score alone (the planner's order when the model has no ranker)
        score_top = nms(cand["frames"], cand["scores"], 5, params.nms_distance, params.nms_angle) if n else top
        base_top = np.zeros(0, int)
        if baseline is not None and n:  # the same candidates, ranked by the pose alone
            base_top = nms(cand["frames"], baseline.predict(cand["poses"]), 5, params.nms_distance, params.nms_angle)
        jrng = np.random.default_rng(1000 + i)
        # the physics oracle costs trials: it judges the top 5 and a random sample of the candidates
        sample = jrng.choice(n, size=min(n, args.random_sample), replace=False) if oracle == "physics" else np.arange(n)
        judged = np.union1d(np.union1d(np.union1d(top, score_top), base_top), sample).astype(int)
        v = judge(scene, cand["frames"][judged], config, jrng, oracle)
        pos = np.zeros(n, bool)
        pos[judged] = v["positive"]
        verdict = {k: np.full(n, np.nan) for k in ("quality", "collides")}
        for k in verdict:
            verdict[k][judged] = v[k]
        row = {
            "object_id": int(oid),
            "candidates": int(n),
            "reason": res.reason,
            "top1": bool(pos[top[0]]) if len(top) else False,
            "top5": float(pos[top].mean()) if len(top) else 0.0,
            "n_top": int(len(top)),
            "random": float(pos[sample].mean()) if len(sample) else 0.0,
            "score_top1": bool(pos[score_top[0]]) if len(score_top) else False,
            "score_top5": float(pos[score_top].mean()) if len(score_top) else 0.0,
            "baseline_top1": bool(pos[base_top[0]]) if len(base_top) else False,
            "baseline_top5": float(pos[base_top].mean()) if len(base_top) else 0.0,
            "top1_score": float(cand["scores"][top[0]]) if len(top) else None,
            "top1_quality": float(verdict["quality"][top[0]]) if len(top) else None,
            "top1_collides": bool(verdict["collides"][top[0]]) if len(top) else None,
            "oracle_best_exists": bool(pos.any()),  # among the judged candidates
            "plan_ms": 1e3 * res.seconds.get("total", 0.0),
            "seconds": time.perf_counter() - t,
        }
        rows.append(row)
        print(
            f"scene {i:2d} object {oid:3d}: {row['candidates']:3d} candidates, {100 * row['random']:5.1f}% positive; "
            f"top-1 {'ok ' if row['top1'] else 'BAD'} (p={row['top1_score'] if row['top1_score'] is None else round(row['top1_score'], 3)}, "
            f"q={row['top1_quality'] if row['top1_quality'] is None else round(row['top1_quality'], 4)}, coll={row['top1_collides']}), "
            f"top-5 {100 * row['top5']:5.1f}%  [{row['seconds']:.1f} s]",
            flush=True,
        )
    planned = [r for r in rows if r["candidates"]]
    summary = {
        "scenes": len(rows),
        "scenes_with_candidates": len(planned),
        "precision_at_1": float(np.mean([r["top1"] for r in rows])) if rows else 0.0,
        "precision_at_5": float(np.mean([r["top5"] for r in rows])) if rows else 0.0,
        "random_candidate_precision": float(np.mean([r["random"] for r in rows])) if rows else 0.0,
        "ranked_by": res.ranked_by if rows else None,
        "score_precision_at_1": float(np.mean([r["score_top1"] for r in rows])) if rows else 0.0,
        "score_precision_at_5": float(np.mean([r["score_top5"] for r in rows])) if rows else 0.0,
        "scenes_with_a_positive_candidate": int(sum(r["oracle_best_exists"] for r in rows)),
        "oracle": oracle,
        "pose_only_baseline": str(baseline_file) if baseline_file else None,
        "baseline_precision_at_1": float(np.mean([r["baseline_top1"] for r in rows])) if rows and baseline else None,
        "baseline_precision_at_5": float(np.mean([r["baseline_top5"] for r in rows])) if rows and baseline else None,
        "params": {
            "cem_iterations": args.cem,
            "windows": args.windows,
            "num_candidates": params.num_candidates,
            "max_centre_offset": args.centre_offset,
            "min_width": args.min_width,
            "max_approach_tilt_deg": args.max_approach_tilt,
        },
        "seed": args.seed,
        "model": model.version,
        "rows": rows,
    }
    print()
    print("| ranking | precision@1 | precision@5 |")
    print("|---|---|---|")
    print(
        f"| Fast-VGQ-CNN planner, ranked by its {summary['ranked_by']} (top-k after NMS) | {100 * summary['precision_at_1']:.1f}% | {100 * summary['precision_at_5']:.1f}% |"
    )
    if summary["ranked_by"] == "ranker":
        s1, s5 = 100 * summary["score_precision_at_1"], 100 * summary["score_precision_at_5"]
        print(f"| the same candidates by the network's score alone (no planner ranker) | {s1:.1f}% | {s5:.1f}% |")
    r = 100 * summary["random_candidate_precision"]
    print(f"| random collision-free candidate (expectation) | {r:.1f}% | {r:.1f}% |")
    if baseline is None:
        print("| pose-only baseline ranking | not run: no baseline_mlp.npz in the model folder (--baseline FILE) | |")
    else:
        b1, b5 = 100 * summary["baseline_precision_at_1"], 100 * summary["baseline_precision_at_5"]
        print(f"| pose-only baseline ranking ({baseline_file.name}) | {b1:.1f}% | {b5:.1f}% |")
    print(f"scenes: {len(rows)} ({summary['scenes_with_a_positive_candidate']} with at least one positive candidate)")
    return summary


def run_trials_bench(args) -> dict:
    """pybullet lift-and-shake trials (datagen.physics) of the plan's top-1 grasp, of the top-1
    by the network's score alone (when the model's planner ranker ordered the plan: both judged
    on the same trials' noise, a paired comparison) and of a random collision-free candidate, on
    the first ``--scenes`` scenes of the precision benchmark's draw (same seed: the same
    objects, poses and cameras). A grasp is positive when it holds in more than the label's
    share of its trials (the physics oracle's rule, with ``--trials`` trials). ``--robust P``
    also judges the top-1 by the network's score averaged over P copies of each candidate under
    the trials' execution noise (the score of the grasp the robot would execute)."""
    try:
        from datagen.physics import GraspSimulator, PhysicsParams, run_trials
    except ImportError as e:
        raise SystemExit(f"physical trials need datagen.physics (pybullet grasp trials): {e}") from None
    from datagen.gripper import GripperGeometry as DatagenGripper

    from .policy import nms, plan

    model, config, params, picked, rng = _setup(args)
    threshold = config.label.success_threshold
    rows, ranked_by = [], "score"
    gripper = DatagenGripper(**dataclasses.asdict(config.gripper))
    with GraspSimulator(gripper, PhysicsParams()) as sim:
        for i, oid in enumerate(picked):
            t = time.perf_counter()
            scene = make_scene(int(oid), config, rng)
            res = plan(scene.depth, config.intrinsics, model, k=5, seed=int(args.seed) + i, params=params)
            ranked_by = res.ranked_by
            if not res.grasps:
                rows.append(
                    {
                        "object_id": int(oid),
                        "planned": False,
                        "trials": 0,
                        "top1_held": 0,
                        "score_top1_held": 0,
                        "random_held": 0,
                        **({"robust_top1_held": 0} if args.robust else {}),
                    }
                )
                print(f"scene {i:2d} object {oid:3d}: no grasp ({res.reason})", flush=True)
                continue
            c = res.candidates
            picks = {
                "top1": int(
                    nms(
                        c["frames"],
                        c["scores"] if c["utility"] is None else c["utility"],
                        1,
                        params.nms_distance,
                        params.nms_angle,
                    )[0]
                ),
                "score_top1": int(nms(c["frames"], c["scores"], 1, params.nms_distance, params.nms_angle)[0]),
                "random": int(np.random.default_rng(2000 + i).integers(len(c["frames"]))),
            }
            if args.robust:
                picks["robust_top1"] = int(
                    np.argmax(noisy_scores(model, scene.depth, config.intrinsics, c["frames"], args.robust, params, i))
                )
            uniq = sorted(set(picks.values()))  # a grasp picked twice is judged once
            sim.set_object(scene.mesh_object, scene.T_world_object)
            tr = run_trials(sim, scene.T_world_camera @ c["frames"][uniq], args.trials, np.random.default_rng(3000 + i))
            held = {j: int(h) for j, h in zip(uniq, tr.held.sum(axis=1))}
            firm = {j: int(f) for j, f in zip(uniq, tr.firm.sum(axis=1))}
            row = {"object_id": int(oid), "planned": True, "trials": args.trials}
            row.update({f"{k}_held": held[j] for k, j in picks.items()})
            row["top1_firm"] = firm[picks["top1"]]
            row["seconds"] = time.perf_counter() - t
            rows.append(row)
            print(
                f"scene {i:2d} object {oid:3d}: top-1 held {row['top1_held']}/{args.trials}, by the score alone "
                f"{row['score_top1_held']}/{args.trials}, random candidate {row['random_held']}/{args.trials}  "
                f"[{row['seconds']:.1f} s]",
                flush=True,
            )
    n = sum(r["trials"] for r in rows)
    summary = {
        "scenes": len(rows),
        "trials_per_grasp": args.trials,
        "trials": n,
        "ranked_by": ranked_by,
        "scenes_without_grasp": int(sum(not r["planned"] for r in rows)),
        "seed": args.seed,
    }
    judged = ("top1", "score_top1", "random") + (("robust_top1",) if args.robust else ())
    for k in judged:
        h = np.array([r[f"{k}_held"] / r["trials"] if r["trials"] else 0.0 for r in rows])
        summary[f"{k}_held"] = int(sum(r[f"{k}_held"] for r in rows))
        summary[f"{k}_success"] = summary[f"{k}_held"] / n if n else 0.0
        summary[f"{k}_precision"] = float(np.mean(h > threshold)) if rows else 0.0  # scenes without a grasp: 0
        # over the scenes drawn; the oracle's own noise comes on top (two judgings of the same grasps
        # on 300 scenes were 5.4 points apart: docs/planning.md)
        pr = summary[f"{k}_precision"]
        summary[f"{k}_precision_se"] = float(np.sqrt(pr * (1 - pr) / len(rows))) if rows else float("nan")
    d = np.array([(r["top1_held"] - r["score_top1_held"]) / r["trials"] for r in rows if r["trials"]])
    summary["top1_minus_score_top1"] = {
        "mean": float(d.mean()) if len(d) else 0.0,
        "se": float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1 else float("nan"),
    }
    summary["rows"] = rows
    print()
    print(
        f"| top-1 of ({args.trials} trials each, {len(rows)} scenes) | trials held | positive (held > {threshold:g}) |"
    )
    print("|---|---:|---:|")
    names = {
        "top1": f"the plan (ranked by its {ranked_by})",
        "score_top1": "the network's score alone",
        "random": "a random collision-free candidate",
        **({"robust_top1": f"the network's score averaged over {args.robust} noisy copies"} if args.robust else {}),
    }
    for k, name in names.items():
        if k == "score_top1" and ranked_by == "score":
            continue
        print(
            f"| {name} | {summary[f'{k}_held']}/{n} ({100 * summary[f'{k}_success']:.1f}%) | "
            f"{100 * summary[f'{k}_precision']:.1f}% (se {100 * summary[f'{k}_precision_se']:.1f}) |"
        )
    if ranked_by != "score":
        dd = summary["top1_minus_score_top1"]
        print(
            f"plan - score alone: {100 * dd['mean']:+.1f} points of trials held (paired, standard error {100 * dd['se']:.1f})"
        )
    print("scenes without a grasp count as no trials held")
    return summary


def noisy_scores(model, depth, intr, frames: np.ndarray, copies: int, params, seed: int) -> np.ndarray:
    """(n,) the network's score of each grasp frame (n, 4, 4, camera frame) averaged over
    ``copies`` copies under the physics trials' execution noise (datagen.physics.PhysicsParams:
    translation per axis, rotation vector per axis about the TCP; isotropic, so drawn in the
    camera frame), scored on the image's windows as the planner scores."""
    from datagen.physics import PhysicsParams, execution_noise, perturbed_frames

    from .policy import grasp_rows, window_scorer

    dt, R, _ = execution_noise(len(frames), copies, PhysicsParams(), np.random.default_rng(7000 + seed))
    noisy = perturbed_frames(frames, dt, R).reshape(-1, 4, 4)
    p, _ = window_scorer(model, np.asarray(depth, np.float32), intr, params.windows).score(grasp_rows(noisy, intr))
    return p.reshape(len(frames), copies).mean(axis=1)


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
    from .features import table_features

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

    from .features import PLAN_FEATURES, plan_features
    from .policy import plan
    from .sampler import Candidates

    model, config, params, picked, rng = _setup(args)
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

    _, config, _, picked, rng = _setup(args)
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


def run_ranker(args) -> dict:
    """The ranker alone, on the precision benchmark's scenes: grasps sampled on the TRUE mesh
    by datagen's antipodal sampler (the training distribution), 12 rotations omega each,
    kept when collision-free (oracle), approaching from the camera side and inside the image;
    precision@1 / @5 of the network's ranking (NMS as the planner) against a random pick.
    Isolates the network from the depth-image sampler."""
    from datagen.grasps import sample_antipodal_grasps
    from datagen.gripper import align_to_table, grasp_frames

    from .policy import grasp_rows, nms, window_scorer

    model = _model(args.model, args.threads)
    params = PlanParams()
    ids, config = scene_objects(args.heldout, "test", _recipe_config(model))
    rng = np.random.default_rng(args.seed)
    picked = rng.choice(ids, size=args.scenes, replace=args.scenes > len(ids))
    rows = []
    n_om = 12
    for i, oid in enumerate(picked):
        scene = make_scene(int(oid), config, rng)
        g = sample_antipodal_grasps(scene.mesh_object, config.antipodal, np.random.default_rng(5000 + i))
        if len(g) == 0:
            rows.append({"object_id": int(oid), "grasps": 0, "top1": False, "top5": 0.0, "random": 0.0})
            continue
        G = np.repeat(scene.T_world_object @ grasp_frames(g.centers, g.axes, 0.0), n_om, axis=0)
        T_wg, _, _ = align_to_table(G, omega=np.tile(2 * np.pi * np.arange(n_om) / n_om, len(g)))
        F = np.linalg.inv(scene.T_world_camera) @ T_wg
        r = grasp_rows(F, config.intrinsics)
        keep = (
            (F[:, 2, 2] > 0)
            & (r[:, 0] >= 0)
            & (r[:, 0] <= config.intrinsics.width - 1)
            & (r[:, 1] >= 0)
            & (r[:, 1] <= config.intrinsics.height - 1)
        )
        F, r = F[keep], r[keep]
        v = judge(scene, F, config, np.random.default_rng(1000 + i))
        free = ~v["collides"]
        F, r, pos = F[free], r[free], v["positive"][free]
        if len(F) == 0:
            rows.append({"object_id": int(oid), "grasps": 0, "top1": False, "top5": 0.0, "random": 0.0})
            continue
        s, _ = window_scorer(model, scene.depth.astype(np.float32), config.intrinsics).score(r)
        top = nms(F, s, 5, params.nms_distance, params.nms_angle)
        rows.append(
            {
                "object_id": int(oid),
                "grasps": int(len(F)),
                "top1": bool(pos[top[0]]),
                "top5": float(pos[top].mean()),
                "random": float(pos.mean()),
            }
        )
        print(
            f"scene {i:2d} object {oid:3d}: {len(F):4d} collision-free true-mesh grasps, {100 * pos.mean():5.1f}% "
            f"positive; network top-1 {'ok ' if pos[top[0]] else 'BAD'}, top-5 {100 * pos[top].mean():5.1f}%",
            flush=True,
        )
    out = {
        "scenes": len(rows),
        "precision_at_1": float(np.mean([x["top1"] for x in rows])),
        "precision_at_5": float(np.mean([x["top5"] for x in rows])),
        "random": float(np.mean([x["random"] for x in rows])),
        "rows": rows,
        "seed": args.seed,
    }
    print(
        f"\nnetwork ranking of true-mesh grasps: precision@1 {100 * out['precision_at_1']:.1f}%, "
        f"precision@5 {100 * out['precision_at_5']:.1f}%, random {100 * out['random']:.1f}%"
    )
    return out


def other_planner(checkout: str):
    """``(plan, PlanParams)`` of the ``planning`` package of another checkout (a folder holding
    planning/, e.g. a ``git worktree`` of an earlier commit), imported beside this one under
    another name (its modules import each other relatively; vgq and service are this checkout's)."""
    import atexit
    import importlib
    import shutil
    import tempfile

    src = Path(checkout) / "planning"
    if not (src / "policy.py").is_file():
        raise ValueError(f"--against {checkout}: no planning/policy.py there")
    root = Path(tempfile.mkdtemp(prefix="planning-against-"))
    atexit.register(shutil.rmtree, root, True)
    shutil.copytree(src, root / "planning_against", ignore=shutil.ignore_patterns("__pycache__"))
    sys.path.insert(0, str(root))
    policy = importlib.import_module("planning_against.policy")
    types = importlib.import_module("planning_against.types")
    return policy.plan, types.PlanParams


def run_timing(args) -> dict:
    from .policy import plan

    model = _model(args.model, args.threads)
    ids, config = scene_objects(args.heldout, "test", _recipe_config(model))
    rng = np.random.default_rng(args.seed)
    scenes = []
    while len(scenes) < args.scenes:
        s = make_scene(int(rng.choice(ids)), config, rng)
        scenes.append(s.depth)
    params = dataclasses.replace(PlanParams(), num_candidates=256, windows=args.windows)
    planners = {"this": (plan, params)}
    if args.against:
        other, other_params = other_planner(args.against)
        planners["against"] = (other, dataclasses.replace(other_params(), num_candidates=256, windows=args.windows))
    totals, cpu, stages, counts, checked = [], [], {}, [], []
    other_totals = []
    for r in range(args.repeats):
        for j, d in enumerate(scenes):
            # with --against, the two planners take turns on each scene, the first alternating
            order = list(planners) if (r + j) % 2 == 0 else list(planners)[::-1]
            for name in order:
                f, p = planners[name]
                c0 = time.process_time()
                res = f(d, config.intrinsics, model, k=5, seed=r * 1000 + j, params=p)
                c1 = time.process_time()
                if r == 0:
                    continue  # warm-up pass
                if name == "against":
                    other_totals.append(res.seconds.get("total", np.nan))
                    continue
                cpu.append(c1 - c0)
                totals.append(res.seconds.get("total", np.nan))
                counts.append(res.counts.get("collision_free", 0))
                checked.append(res.counts.get("checked", 0))
                for k, v in res.seconds.items():
                    stages.setdefault(k, []).append(v)
    t = 1e3 * np.asarray(totals)
    c = 1e3 * np.asarray(cpu)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    out = {
        "runs": len(t),
        "p50_ms": float(np.nanpercentile(t, 50)),
        "p99_ms": float(np.nanpercentile(t, 99)),
        "cpu_p50_ms": float(np.percentile(c, 50)),
        "cpu_p99_ms": float(np.percentile(c, 99)),
        "load_average_1min": load,
        "cpu_cores": os.cpu_count(),
        "mean_candidates": float(np.mean(counts)),
        "collision_checks": [int(np.min(checked)), int(np.median(checked)), int(np.max(checked))],
        "stage_median_ms": {k: float(1e3 * np.median(v)) for k, v in stages.items()},
        "threads": args.threads,
        "model": model.version,
        "head": model.head_precision,
    }
    print(
        f"plan {out['runs']} runs on {args.scenes} scenes (300 x 300, up to 256 candidates, mean "
        f"{out['mean_candidates']:.0f}), onnxruntime threads={args.threads}, head {model.head_precision}:"
    )
    print(
        f"  wall: p50 {out['p50_ms']:.1f} ms   p99 {out['p99_ms']:.1f} ms   (load average {load:.1f} on {os.cpu_count()} cores)"
    )
    print(f"  CPU time of the process (all threads): p50 {out['cpu_p50_ms']:.1f} ms   p99 {out['cpu_p99_ms']:.1f} ms")
    print("  collision checks per plan: min {} / median {} / max {}".format(*out["collision_checks"]))
    print("  stage medians (ms): " + ", ".join(f"{k} {v:.1f}" for k, v in out["stage_median_ms"].items()))
    if other_totals:
        o = 1e3 * np.asarray(other_totals)
        out["against"] = {
            "checkout": str(args.against),
            "p50_ms": float(np.nanpercentile(o, 50)),
            "p99_ms": float(np.nanpercentile(o, 99)),
            "ratio_p50": float(np.nanpercentile(t, 50) / np.nanpercentile(o, 50)),
            "median_per_plan_ratio": float(np.nanmedian(t / o)),
        }
        a = out["against"]
        print(
            f"  against {args.against} (interleaved, the same scenes and seeds): p50 {a['p50_ms']:.1f} ms   "
            f"p99 {a['p99_ms']:.1f} ms; this / that: p50 {a['ratio_p50']:.2f}x, per plan (median) "
            f"{a['median_per_plan_ratio']:.2f}x"
        )
    return out


def main(argv=None) -> int:
    args = parse_args(argv)
    run = {
        "timing": run_timing,
        "precision": run_precision,
        "trials": run_trials_bench,
        "ranker": run_ranker,
        "pool": run_pool,
        "ceiling": run_ceiling,
    }[args.what]
    from service.runtime import ModelError

    if args.against and not (Path(args.against) / "planning" / "policy.py").is_file():
        print(
            f"python -m planning.bench: error: --against {args.against}: no planning/policy.py there", file=sys.stderr
        )
        return 2
    try:
        out = run(args)
    except (ModelError, OSError) as e:  # a model folder or held-out file it cannot read
        print(f"python -m planning.bench: error: {e}", file=sys.stderr)
        return 2
    if args.json:
        from vgq import atomic

        atomic.write_bytes(Path(args.json), json.dumps(out, indent=1).encode())
    return 0


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m planning.bench", description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=["timing", "precision", "trials", "ranker", "pool", "ceiling"])
    ap.add_argument("--model", default=MODEL_DIR)
    ap.add_argument(
        "--heldout",
        default=HELDOUT,
        help="the scenes' objects: a held-out crop file, a crop dataset folder (with --split), or "
        "'unseen': objects outside the model's dataset (to fit the ranker and p_hold on)",
    )
    ap.add_argument(
        "--split",
        choices=["train", "val", "test"],
        default="test",
        help="the objects of this split when --heldout is a crop dataset folder (train / val: to fit on other objects)",
    )
    ap.add_argument("--scenes", type=int, default=None, help="timing: 4, precision: 20")
    ap.add_argument("--repeats", type=int, default=26, help="timing: passes over the scenes (the first is warm-up)")
    ap.add_argument("--threads", type=int, default=2, help="onnxruntime intra-op threads")
    ap.add_argument(
        "--against",
        metavar="DIR",
        help="timing: also time the planner of another checkout (a folder holding planning/, e.g. a git "
        "worktree of an earlier commit), plan by plan interleaved with this one's, and print the ratio",
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--trials",
        type=int,
        default=None,
        help="trials / pool / ceiling: pybullet trials per grasp (with execution noise); default 5, ceiling: the "
        "recipe's label trials",
    )
    ap.add_argument("--per-scene", type=int, default=24, help="pool: random candidates tried per scene")
    ap.add_argument(
        "--grasps", type=int, default=None, help="ceiling: antipodal grasps sampled per scene (default: the recipe's)"
    )
    ap.add_argument(
        "--approaches", type=int, default=1, help="ceiling: approaches (random omega) per grasp (datagen: 1)"
    )
    ap.add_argument(
        "--plan",
        metavar="FILE",
        help="ceiling --confirm: a `trials --json` run of the same --seed and --scenes, whose top-1 verdicts are "
        "counted per class of scene by its best true-mesh grasp",
    )
    ap.add_argument(
        "--confirm",
        type=int,
        default=0,
        metavar="K",
        help="ceiling: also judge each scene's top K grasps on 3x more trials and pick the best by all (0: off)",
    )
    ap.add_argument(
        "--robust",
        type=int,
        default=0,
        metavar="P",
        help="trials: also judge the top-1 by the score averaged over P noisy copies of each candidate (0: off)",
    )
    ap.add_argument(
        "--retest",
        action="store_true",
        help="pool: judge each scene's best judged candidate again on fresh trials (what a ranker that knew "
        "the oracle's answer would score on a new judging)",
    )
    ap.add_argument(
        "--table-margin",
        type=float,
        default=PlanParams().table_margin,
        help="fingertips at least this far above the estimated table (m)",
    )
    ap.add_argument("--cem", type=int, default=0, help="CEM iterations over omega (0: off)")
    ap.add_argument("--windows", choices=["cover", "grid"], default="cover")
    ap.add_argument(
        "--centre-offset",
        type=float,
        default=PlanParams().max_centre_offset,
        help="max distance (m) of the jaw line from the estimated centre of mass; <= 0: off",
    )
    ap.add_argument("--min-width", type=float, default=PlanParams().min_width, help="min contact distance (m)")
    ap.add_argument(
        "--max-approach-tilt",
        type=float,
        default=float(np.degrees(PlanParams().max_approach_tilt)),
        help="approaches within this angle (deg) of straight down",
    )
    ap.add_argument(
        "--top-view-cell",
        type=float,
        default=PlanParams().top_view_cell,
        help="grid (m) of the objects' tops seen from above that ends a contact line's hidden part; <= 0: off",
    )
    ap.add_argument(
        "--oracle",
        choices=ORACLES,
        default=None,
        help="precision: judge by robust Ferrari-Canny (fc) or by pybullet trials (physics); default: the one "
        "matching the label of the model's recipe",
    )
    ap.add_argument(
        "--random-sample",
        type=int,
        default=16,
        help="precision with the physics oracle: random candidates judged per scene for the random baseline",
    )
    ap.add_argument(
        "--baseline",
        metavar="FILE",
        help="precision: a pose-only baseline file (`training baseline --out DIR` writes DIR/baseline_mlp.npz) "
        "whose ranking of the same candidates is judged too; default: the one in the model folder, if any",
    )
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args(argv)
    if args.centre_offset is not None and args.centre_offset <= 0:
        args.centre_offset = None
    if args.random_sample < 1:
        ap.error("--random-sample must be >= 1")
    if args.robust < 0:
        ap.error(f"--robust must be >= 0, got {args.robust}")
    if args.scenes is None:
        args.scenes = {"timing": 4, "precision": 20, "trials": 10, "ranker": 20, "pool": 60, "ceiling": 30}[args.what]
    if args.confirm < 0:
        ap.error(f"--confirm must be >= 0, got {args.confirm}")
    args.plan_run = None
    if args.plan:  # read before the run: a bad file must not cost the benchmark's minutes
        try:
            args.plan_run = read_trials_run(args.plan, args.seed, args.scenes)
        except ValueError as e:
            ap.error(f"--plan {args.plan}: {e}")
    if args.approaches < 1 or (args.grasps is not None and args.grasps < 1):
        ap.error(f"--approaches and --grasps must be >= 1, got {args.approaches} and {args.grasps}")
    if args.trials is not None and args.trials < 1:
        ap.error(f"--trials must be >= 1, got {args.trials}")
    if args.trials is None and args.what != "ceiling":
        args.trials = 5
    if not 0 < args.max_approach_tilt <= 90:
        ap.error(f"--max-approach-tilt must be in (0, 90] degrees, got {args.max_approach_tilt:g}")
    return args


if __name__ == "__main__":
    sys.exit(main())
