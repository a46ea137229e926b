"""``python -m planning.bench precision``: precision@1 and @5 of the plan, judged by the oracle,
against a random collision-free candidate and the pose-only baseline's ranking."""

from __future__ import annotations

import time

import numpy as np

from .common import draw_scenes, pose_only_model
from .oracle import default_oracle, judge
from .scenes import make_scene


def run_precision(args) -> dict:
    from ..policy import nms, plan

    model, config, params, picked, rng = draw_scenes(args)
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
