"""``python -m planning.bench timing``: p50 / p99 of the planner on rendered 300 x 300 scenes
(256 candidates, encoder included), optionally interleaved with another checkout's planner."""

from __future__ import annotations

import dataclasses
import os
import sys
import time
from pathlib import Path

import numpy as np

from ..types import PlanParams
from .common import load_model
from .scenes import make_scene, recipe_config, scene_objects


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
    from ..policy import plan

    model = load_model(args.model, args.threads)
    ids, config = scene_objects(args.heldout, "test", recipe_config(model))
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
