"""Throughput benchmark: labelled datapoints (grasp rows) per minute and the native
positivity rate of a small generation run on this machine."""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from .config import DatagenConfig


def run_bench(
    config: DatagenConfig, workers: int = 1, out: str | Path | None = None, log: Callable[[str], None] = print
) -> dict:
    """Generate ``config`` (use a small ``num_objects``) into ``out`` (a temporary folder when
    None) and report wall time, datapoints per minute and positivity."""
    from .pipeline import run_generate

    with tempfile.TemporaryDirectory(prefix="datagen-bench-") as tmp:
        root = Path(out) if out is not None else Path(tmp) / "ds"
        t0 = time.perf_counter()
        m = run_generate(root, config, workers=workers, progress=False, log=log)
        wall = time.perf_counter() - t0
    c = m["counts"]
    res = {
        "objects": c["objects"],
        "objects_done": c["objects_done"],
        "objects_skipped": c["objects_skipped"],
        "images": c["images"],
        "datapoints": c["grasps"],
        "positive": c["positive"],
        "positivity_rate": c["positivity_rate"],
        "collision_free_rate": c["collision_free"] / c["grasps"] if c["grasps"] else 0.0,
        "wall_s": wall,
        "datapoints_per_minute": 60.0 * c["grasps"] / wall if wall > 0 else 0.0,
        "workers": workers,
        "cameras_per_pose": config.cameras_per_pose,
    }
    log(
        f"bench: {res['objects_done']}/{res['objects']} objects ({res['objects_skipped']} skipped), "
        f"{res['images']} images, {res['datapoints']} labelled datapoints in {wall:.1f} s with {workers} worker(s)"
    )
    log(f"bench: {res['datapoints_per_minute']:.0f} datapoints/min")
    log(
        f"bench: native positivity rate {100 * res['positivity_rate']:.1f}% "
        f"(collision-free {100 * res['collision_free_rate']:.1f}%; VG-dset ~6%, Dex-Net 2.0 ~19%)"
    )
    for o in m["objects"]:
        if o.get("status") == "skipped":
            log(f"bench: skipped {o['name']}: {o.get('reason')}")
    return res


def physics_grasps(src, config: DatagenConfig, num_grasps: int, seed: int):
    """Up to ``num_grasps`` grasps of one object with a collision-free approach in its most
    probable stable pose: ``(mesh, T_world_object (4, 4), T_world_grasp (n, 4, 4))``, or None."""
    import dataclasses

    import numpy as np

    from .collision import CollisionChecker
    from .grasps import sample_antipodal_grasps
    from .gripper import align_to_table, grasp_frames
    from .mesh import load_object, stable_poses

    rng = np.random.default_rng(seed)
    obj = load_object(src, config.mesh)
    T_poses, _ = stable_poses(obj, 0.0, 1)
    if len(T_poses) == 0:
        return None
    g = sample_antipodal_grasps(obj.mesh, dataclasses.replace(config.antipodal, num_samples=4 * num_grasps), rng)
    if len(g) == 0:
        return None
    mw = obj.mesh.copy()
    mw.apply_transform(T_poses[0])
    T, _, _ = align_to_table(T_poses[0] @ grasp_frames(g.centers, g.axes, 0.0), rng)
    T = T[~CollisionChecker(mw, config.gripper).collides(T)][:num_grasps]
    return (obj.mesh, T_poses[0], T) if len(T) else None


def run_physics_bench(
    config: DatagenConfig,
    workers: int = 1,
    grasps: int = 16,
    trials: int = 4,
    chunk: int = 4,
    log: Callable[[str], None] = print,
) -> dict:
    """Physics trials per second: ``trials`` noisy trials of up to ``grasps`` collision-free
    grasps on each of the config's first objects, ``chunk`` grasps per task on ``workers``
    processes (datagen's pool). Object set-up (V-HACD, cached on disk) is timed apart."""
    import numpy as np

    from .mesh import mesh_sources
    from .parallel import run_tasks
    from .physics import GraspSimulator, object_trials_task

    sources = mesh_sources(config.source)[: config.num_objects or 3]
    t0 = time.perf_counter()
    jobs = []
    with tempfile.TemporaryDirectory(prefix="physics-bench-") as cache:
        sim = GraspSimulator(config.gripper, config.physics, cache)
        for i, src in enumerate(sources):
            r = physics_grasps(src, config, grasps, seed=i)
            if r is None:
                log(f"bench: {src.name}: no collision-free grasp, skipped")
                continue
            mesh, T_wo, T = r
            sim.set_object(mesh, T_wo)  # V-HACD once per object, into the cache the workers read
            jobs.append((src.name, mesh, T_wo, T))
        sim.close()
        setup = time.perf_counter() - t0
        tasks = [
            (
                np.asarray(mesh.vertices),
                np.asarray(mesh.faces),
                T_wo,
                T[s : s + chunk],
                config.gripper,
                config.physics,
                trials,
                1000 * k + s,
                cache,
                name,
            )
            for k, (name, mesh, T_wo, T) in enumerate(jobs)
            for s in range(0, len(T), chunk)
        ]
        out: list[dict] = []
        t1 = time.perf_counter()
        run_tasks(object_trials_task, tasks, workers=workers, on_result=out.append, progress=False, desc="trials")
        wall = time.perf_counter() - t1
    n = int(sum(r["held"].size for r in out))
    cpu = float(sum(r["seconds"] for r in out))
    res = {
        "objects": len(jobs),
        "trials": n,
        "workers": workers,
        "wall_s": wall,
        "setup_s": setup,
        "trials_per_second": n / wall if wall > 0 else 0.0,
        "trial_seconds_in_worker": cpu / n if n else 0.0,
        "held_rate": float(np.mean(np.concatenate([r["held"].reshape(-1) for r in out]))) if n else 0.0,
    }
    log(
        f"bench: {n} physics trials of {len(jobs)} objects in {wall:.1f} s with {workers} worker(s) "
        f"(object set-up {setup:.1f} s, not counted)"
    )
    log(
        f"bench: {res['trials_per_second']:.2f} trials/s; {1000 * res['trial_seconds_in_worker']:.0f} ms per trial "
        f"inside a worker; held {100 * res['held_rate']:.0f}%"
    )
    return res
