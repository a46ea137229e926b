"""``python -m planning.bench ranker``: the network's ranking alone, of grasps sampled on the true
mesh (the training distribution), isolated from the depth-image sampler."""

from __future__ import annotations

import numpy as np

from ..types import PlanParams
from .common import load_model
from .oracle import judge
from .scenes import make_scene, recipe_config, scene_objects


def run_ranker(args) -> dict:
    """The ranker alone, on the precision benchmark's scenes: grasps sampled on the TRUE mesh
    by datagen's antipodal sampler (the training distribution), 12 rotations omega each,
    kept when collision-free (oracle), approaching from the camera side and inside the image;
    precision@1 / @5 of the network's ranking (NMS as the planner) against a random pick.
    Isolates the network from the depth-image sampler."""
    from datagen.grasps import sample_antipodal_grasps
    from datagen.gripper import align_to_table, grasp_frames

    from ..policy import grasp_rows, nms, window_scorer

    model = load_model(args.model, args.threads)
    params = PlanParams()
    ids, config = scene_objects(args.heldout, "test", recipe_config(model))
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
