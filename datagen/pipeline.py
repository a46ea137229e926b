"""The per-object job of dataset generation (SPEC section 2, steps 1-6) and the run driver.

:func:`generate_object` turns one mesh into the rows of one shard: load the mesh, its
stable poses, antipodal grasps, the robust Ferrari-Canny quality (once per grasp), then for
each stable pose and each of n cameras: a random omega per grasp with the beta flip, the
collision check (a colliding grasp gets quality 0, ``collision_free`` False), the depth
render, the projection; grasps whose TCP projects outside the image are dropped.

Randomness: the per-object seed derives from (run seed, object name) only
(:func:`object_seed`), and each stage draws from its own child stream of it, so the data
of an object does not depend on which worker ran it, in which order, or on other objects.

:func:`run_generate` runs the objects of a config into a ``vgq-grasps`` folder, resuming
a killed run (objects whose shard is listed in the manifest are skipped).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from vgq import atomic
from vgq.schema import GRASP_FIELDS, GRASP_LABEL_FIELDS, IMAGE_FIELDS

from . import storage
from .config import ConfigError, DatagenConfig


class SkipObject(Exception):
    """The object yields no data for a deterministic reason (no stable pose, no grasp)."""


def object_seed(run_seed: int, name: str) -> int:
    """A 63-bit seed from the run seed and the object name (independent of scheduling)."""
    h = hashlib.sha256(f"vgq-datagen:{int(run_seed)}:{name}".encode()).digest()
    return int.from_bytes(h[:8], "little") >> 1


def _concat(parts: list[dict], fields: dict) -> dict[str, np.ndarray]:
    if not parts:
        return storage.empty_arrays(fields)
    return {k: np.concatenate([p[k] for p in parts]).astype(dtype, copy=False) for k, (dtype, _, _) in fields.items()}


def generate_object_with_info(
    src, config: DatagenConfig, object_id: int, seed: int, trials_cache: dict | None = None
) -> tuple[dict, dict, dict]:
    """:func:`generate_object` plus a dict of facts about the object for the manifest
    (stable pose probabilities, grasp count, torque scaling used, mesh scale and repairs).

    ``trials_cache``: the object's recorded physics trials per stable pose id
    (:meth:`datagen.physics_cache.PhysicsCache.for_object`); a pose they cover is replayed
    instead of simulated (:func:`_replayed_success`), with the same result."""
    from .camera import sample_cameras
    from .collision import CollisionChecker
    from .grasps import sample_antipodal_grasps
    from .gripper import align_to_table, grasp_frames
    from .labels import label_score
    from .mesh import load_object, stable_poses
    from .project import project_grasps
    from .quality import resolve_torque_scaling, robust_ferrari_canny
    from .render import render_depth

    intr = config.intrinsics
    ss_grasps, ss_quality, ss_poses = np.random.SeedSequence(seed).spawn(3)
    kind = config.label.kind
    obj = load_object(src, config.mesh)
    T_poses, probs = stable_poses(obj, config.stable_pose_min_probability, config.max_stable_poses)
    info = {
        "mesh_scale": float(getattr(obj, "scale", src.scale)),
        "repairs": list(getattr(obj, "repairs", [])),
        "stable_pose_probabilities": [float(p) for p in probs],
    }
    if len(T_poses) == 0:
        raise SkipObject(f"no stable pose with probability >= {config.stable_pose_min_probability}")
    grasps = sample_antipodal_grasps(obj.mesh, config.antipodal, np.random.default_rng(ss_grasps))
    info["num_grasps"] = len(grasps)
    if len(grasps) == 0:
        raise SkipObject("the antipodal sampler found no grasp")
    qparams = dataclasses.replace(config.quality, torque_scaling=resolve_torque_scaling(obj.mesh, config.quality))
    info["torque_scaling"] = float(qparams.torque_scaling)
    quality = np.asarray(robust_ferrari_canny(obj.mesh, grasps, qparams, np.random.default_rng(ss_quality)), np.float64)
    T_object_grasp0 = grasp_frames(grasps.centers, grasps.axes, 0.0)  # omega = 0 base frames
    grasp_ids = np.arange(len(grasps), dtype=np.int32)

    image_parts: list[dict] = []
    grasp_parts: list[dict] = []
    n_img = 0
    for pose_id, ss_pose in enumerate(ss_poses.spawn(len(T_poses))):
        rng = np.random.default_rng(ss_pose)
        ss_robust, ss_physics = np.random.SeedSequence(ss_pose.entropy, spawn_key=(*ss_pose.spawn_key, 7)).spawn(2)
        rng_robust = np.random.default_rng(ss_robust)
        T_wo = T_poses[pose_id]
        mesh_world = obj.mesh.copy()
        mesh_world.apply_transform(T_wo)
        checker = CollisionChecker(mesh_world, config.gripper)
        checker_c = CollisionChecker(mesh_world, config.gripper, clearance=config.collision.clearance)
        cams = sample_cameras(config.cameras_per_pose, config.camera, rng)
        success = np.full(len(grasps), np.nan)
        if kind == "physics":
            # one approach per grasp and pose, shared by the cameras: its trials, robust collision and
            # pad quality are computed once per pose, not once per camera
            pose_grasp = align_to_table(T_wo @ T_object_grasp0, rng)
            pose_free = ~np.asarray(checker.collides(pose_grasp[0]), dtype=bool)
            # the grasp is the same for every camera: project it once per camera here, for the replay and the rows
            pose_proj = [project_grasps(pose_grasp[0], T_wc, intr) for T_wc in cams.T_world_camera]
            success = _replayed_success((trials_cache or {}).get(pose_id), pose_grasp[0], pose_free, pose_proj, info)
            if success is None:
                success = _physics_success(obj.mesh, T_wo, pose_grasp[0], pose_free, config, ss_physics, info)
            pose_fields = _robust_fields(
                kind, obj.mesh, T_wo, pose_grasp[0], ~pose_free, checker_c, config, qparams, rng_robust
            )
        for j in range(len(cams)):
            T_wc = cams.T_world_camera[j]
            if kind == "physics":
                T_wg, omega, beta = pose_grasp
                collides = ~pose_free
                p_cf, pad_q = pose_fields
            else:
                T_wg, omega, beta = align_to_table(T_wo @ T_object_grasp0, rng)
                collides = np.asarray(checker.collides(T_wg), dtype=bool)
                p_cf, pad_q = _robust_fields(
                    kind, obj.mesh, T_wo, T_wg, collides, checker_c, config, qparams, rng_robust
                )
            score = label_score(kind, quality, ~collides, p_cf, pad_q, success)
            depth = render_depth(mesh_world, T_wc, intr)
            pr = pose_proj[j] if kind == "physics" else project_grasps(T_wg, T_wc, intr)
            u, v, z = (np.asarray(pr[k], np.float64) for k in ("u", "v", "z"))
            inside = _inside(pr)
            image_parts.append(
                {
                    "depth": np.asarray(depth, np.float32)[None],
                    "object_id": np.array([object_id], np.int32),
                    "stable_pose_id": np.array([pose_id], np.int32),
                    "camera_d": np.array([cams.d[j]], np.float32),
                    "camera_phi": np.array([cams.phi[j]], np.float32),
                    "camera_theta": np.array([cams.theta[j]], np.float32),
                    "T_world_camera": np.asarray(T_wc, np.float64)[None],
                }
            )
            k = inside
            grasp_parts.append(
                {
                    "image_index": np.full(int(k.sum()), n_img, np.int32),
                    "grasp_id": grasp_ids[k],
                    "u": u[k],
                    "v": v[k],
                    "z": z[k],
                    "q": np.asarray(pr["q"])[k],
                    "beta": np.asarray(pr["beta"])[k],
                    "psi": np.asarray(pr["psi"])[k],
                    "omega": np.asarray(omega)[k],
                    "jaw_angle": np.asarray(pr["jaw_angle"])[k],
                    "quality": score[k],
                    "collision_free": ~collides[k],
                    "fc_quality": quality[k],
                    "p_collision_free": p_cf[k],
                    "pad_quality": pad_q[k],
                    "success_rate": success[k],
                }
            )
            n_img += 1
    info["label"] = kind
    return _concat(image_parts, IMAGE_FIELDS), _concat(grasp_parts, {**GRASP_FIELDS, **GRASP_LABEL_FIELDS}), info


def _inside(pr: dict) -> np.ndarray:
    """Which projected grasps (``project_grasps`` output) have their TCP within the image: the rows kept."""
    return np.asarray(pr["in_image"], bool) & np.isfinite(pr["u"]) & np.isfinite(pr["v"])


def _replayed_success(trials, T_wg, free, projections: list[dict], info: dict) -> np.ndarray | None:
    """Success rates (n,) of the grasps ``T_wg`` (world frame) at one pose from its recorded
    trials (a :class:`datagen.physics_cache.PoseTrials`, or None), or None when they do not
    cover every grasp whose approach is ``free`` and whose TCP one of the cameras sees
    (``projections``: ``project_grasps`` of ``T_wg`` per camera); records the pose's original
    trial entry (marked cached) in ``info``."""
    if trials is None:
        return None
    seen = np.logical_or.reduce([_inside(pr) for pr in projections]) if projections else np.zeros(len(T_wg), bool)
    success = trials.replay(T_wg, free & seen)
    if success is not None:
        info.setdefault("physics", []).append({**trials.record, "cached": True})
    return success


def _robust_fields(
    kind: str, mesh, T_wo, T_wg, collides, checker_c, config: DatagenConfig, qparams, rng
) -> tuple[np.ndarray, np.ndarray]:
    """Robust collision-free probability and pad quality (n,) of the grasps ``T_wg`` (world frame)
    whose nominal approach is free (NaN elsewhere: those rows are negatives under every label);
    not computed for the paper's label (its cost)."""
    from .collision import collision_free_probability
    from .pads import pad_quality

    p_cf = np.full(len(T_wg), np.nan)
    pad_q = np.full(len(T_wg), np.nan)
    free = np.flatnonzero(~collides) if kind != "paper" else np.zeros(0, np.int64)
    if len(free):
        p_cf[free] = collision_free_probability(checker_c, T_wg[free], config.collision, rng)
        pad_q[free] = pad_quality(
            mesh, np.linalg.inv(T_wo) @ T_wg[free], config.gripper, qparams, qparams.torque_scaling
        )[0]
    return p_cf, pad_q


def _physics_success(
    mesh, T_wo, T_wg, free, config: DatagenConfig, ss: np.random.SeedSequence, info: dict
) -> np.ndarray:
    """Success rate (n,) of ``config.label.trials`` noisy physics trials of each grasp whose
    approach is free at the nominal pose (0 for the others, which get no trials); records the
    trial count, seconds and the stable-pose check in ``info``."""
    from .physics import _worker_sim, run_trials

    out = np.zeros(len(T_wg))
    idx = np.flatnonzero(free)
    sim = _worker_sim(config.gripper, config.physics, None)
    t0 = time.perf_counter()
    pose = sim.set_object(mesh, T_wo)
    n_trials = 0
    if len(idx):
        stop = config.label.success_threshold if config.label.early_stop else None
        res = run_trials(sim, T_wg[idx], config.label.trials, np.random.default_rng(ss), stop_above=stop)
        out[idx] = res.success_rate
        n_trials = res.trials_run
    info.setdefault("physics", []).append(
        {
            "trials": n_trials,
            "seconds": time.perf_counter() - t0,
            "pose_stable": bool(pose["stable"]),
            "pose_drift_m": float(pose["drift_m"]),
        }
    )
    return out


def generate_object(src, config: DatagenConfig, object_id: int, seed: int) -> tuple[dict, dict]:
    """One object's shard arrays: (IMAGE_FIELDS arrays, GRASP_FIELDS arrays).

    ``src``: a :class:`datagen.mesh.MeshSource`; ``seed``: the per-object seed
    (:func:`object_seed`). Raises :class:`datagen.mesh.MeshError` for an unusable mesh and
    :class:`SkipObject` when the object yields nothing."""
    images, grasps, _ = generate_object_with_info(src, config, object_id, seed)
    return images, grasps


# ----------------------------------------------------------------------------- run driver


def object_task(src, config: DatagenConfig, object_id: int, seed: int, trials_cache: dict | None = None) -> dict:
    """Worker task: generate one object and encode its shard (bytes); never raises for a
    bad object (the result says why it was skipped). ``trials_cache``: as for
    :func:`generate_object_with_info`."""
    from .mesh import MeshError

    t0 = time.perf_counter()
    try:
        images, grasps, info = generate_object_with_info(src, config, object_id, seed, trials_cache)
    except (MeshError, SkipObject) as e:
        return {"object_id": object_id, "status": "skipped", "reason": str(e), "info": {}}
    except Exception as e:  # keep the run going; the object is retried on resume
        return {
            "object_id": object_id,
            "status": "skipped",
            "reason": f"error: {type(e).__name__}: {e}",
            "retry": True,
            "info": {},
        }
    data = storage.encode_shard(images, grasps, where=storage.shard_relpath(object_id))
    return {
        "object_id": object_id,
        "status": "done",
        "data": data,
        "counts": storage.shard_counts(images, grasps, config.label_threshold),
        "info": info,
        "seconds": time.perf_counter() - t0,
    }


def _normalised(d: dict) -> dict:
    return json.loads(json.dumps(d))


def _config_diff(a: dict, b: dict, prefix: str = "") -> list[str]:
    out = []
    for k in sorted(set(a) | set(b)):
        va, vb = a.get(k), b.get(k)
        if isinstance(va, dict) and isinstance(vb, dict):
            out += _config_diff(va, vb, f"{prefix}{k}.")
        elif va != vb:
            out.append(f"{prefix}{k}")
    return out


def source_family(source: str | None) -> str:
    """The family recorded for objects of a mesh source: ``random_urdfs`` for the default
    source, else the folder's (or file's) name."""
    from .families import SOURCE_FAMILY

    return SOURCE_FAMILY if source is None else (Path(source).stem or SOURCE_FAMILY)


def run_sources(config: DatagenConfig) -> list:
    """The run's objects in id order: ``num_objects`` of the mesh source from its
    ``first_object``-th (sorted by name; none when 0), then ``families`` (procedural objects,
    ``<family>_<index>``)."""
    from .families import family_sources
    from .mesh import mesh_sources

    sources = [] if config.num_objects == 0 else mesh_sources(config.source)[config.first_object :]
    if config.num_objects is not None:
        sources = sources[: config.num_objects]
    sources += family_sources(config.families, config.seed)
    names = [s.name for s in sources]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise ValueError(f"duplicate object names in the run (mesh source {config.source}, families): {dup[:3]}")
    return sources


def _recorded_config(d) -> dict | None:
    """A manifest's config with the defaults of fields added since it was written."""
    from .config import recorded_config

    try:
        return _normalised(DatagenConfig.from_dict(recorded_config(d)).to_dict())
    except (ConfigError, TypeError):
        return d


IDENTITY = ("source_scale", "family", "params")  # what makes an object's mesh, besides its name (and source file)


def refresh_changed_objects(m: dict, objects: list[dict]) -> list[str]:
    """Objects of manifest ``m`` whose mesh definition (:data:`IDENTITY`: e.g. a family's
    parameters after its size ranges changed) differs from ``objects`` (the code's, same
    order): their recorded definition is replaced and they go back to pending, their shard
    entries dropped (in place). A field a manifest does not record (one written before it
    existed) is taken to match. Returns their names."""
    changed = []
    for rec, new in zip(m["objects"], objects):
        keys = [k for k in IDENTITY if k in rec]
        if json.loads(json.dumps([rec[k] for k in keys])) != json.loads(json.dumps([new[k] for k in keys])):
            for k in list(rec):
                if k not in ("object_id", "name"):
                    del rec[k]
            rec.update({k: new[k] for k in ("source", *IDENTITY)}, status="pending")
            changed.append(rec["name"])
    if changed:
        ids = {o["object_id"] for o in m["objects"] if o["name"] in set(changed)}
        m["shards"] = [s for s in m["shards"] if s["object_id"] not in ids]
        m["complete"] = False
        storage.update_counts(m)
    return changed


def prepare_run(out: str | Path, config: DatagenConfig, log: Callable[[str], None] = print) -> tuple[dict, list]:
    """The run's manifest (new, or the existing one to resume) and its mesh sources. On
    resume, objects whose definition changed since they were made are regenerated
    (:func:`refresh_changed_objects`, logged).

    Raises ConfigError when ``out`` holds a dataset made with a different config or
    object list."""
    out = Path(out)
    sources = run_sources(config)
    objects = [
        {
            "object_id": i,
            "name": s.name,
            "source": str(s.path),
            "source_scale": float(s.scale),
            "family": s.family or source_family(config.source),
            "params": s.params or {},
        }
        for i, s in enumerate(sources)
    ]
    cfg = _normalised(config.to_dict())
    if (out / storage.MANIFEST).exists():
        m = storage.read_manifest(out, storage.GRASP_FORMAT)
        if _recorded_config(m.get("config")) != cfg:
            diff = _config_diff(m.get("config", {}), cfg)
            raise ConfigError(
                f"{out} holds a dataset generated with a different config (differs in: {', '.join(diff[:6])}); "
                "use a new --out, the same settings, or --resume"
            )
        if [o["name"] for o in m["objects"]] != [s.name for s in sources]:
            raise ConfigError(f"{out} holds a dataset of a different object list; use a new --out")
        changed = refresh_changed_objects(m, objects)
        if changed:
            log(
                f"{out}: {len(changed)} objects were made from another definition than the code's now (e.g. a "
                f"family's size ranges changed): regenerating {', '.join(changed[:5])}{', ...' if len(changed) > 5 else ''}"
            )
        return m, sources
    return storage.new_grasp_manifest(
        cfg, config.seed, objects, config.label_threshold, intrinsics=config.intrinsics.to_dict()
    ), sources


def interleaved(todo: list[int], manifest: dict) -> list[int]:
    """The object ids of ``todo`` in work order: round-robin over the families (in order of first
    appearance), so a run stopped part-way holds every family in proportion, not only the first."""
    by_family: dict[str, list[int]] = {}
    for i in todo:
        by_family.setdefault(manifest["objects"][i].get("family", ""), []).append(i)
    n = len(todo)
    # an object's place is its rank within its family scaled by the family's share of the run
    key = {i: (rank * n / len(ids), f) for f, ids in enumerate(by_family.values()) for rank, i in enumerate(ids)}
    return sorted(todo, key=lambda i: key[i])


def run_generate(
    out: str | Path,
    config: DatagenConfig,
    workers: int = 1,
    use_ray: bool = False,
    progress: bool = True,
    log: Callable[[str], None] = print,
    physics_cache=None,
) -> dict:
    """Generate (or resume) the dataset of ``config`` into ``out``; returns the manifest.

    ``physics_cache``: a :class:`datagen.physics_cache.PhysicsCache` whose recorded trials are
    replayed where they cover a pose (only if made with this config's physics settings)."""
    from .parallel import run_tasks
    from .physics_cache import config_key

    out = Path(out)
    m, sources = prepare_run(out, config, log)
    todo = [
        i
        for i, o in enumerate(m["objects"])
        if o.get("status") == "pending"
        or (o.get("status") == "skipped" and o.get("retry"))
        or (o.get("status") == "done" and not any(s["object_id"] == i for s in m["shards"]))
    ]
    for i in todo:
        m["objects"][i]["status"] = "pending"
        m["objects"][i].pop("retry", None)
    storage.update_counts(m)
    storage.write_manifest(out, m)
    done_before = len(m["objects"]) - len(todo)
    if done_before:
        log(f"resuming {out}: {done_before} objects already done or skipped, {len(todo)} to go")
    if physics_cache is not None and physics_cache.key != config_key(config):
        log("physics cache: made with other seed, label, physics or gripper settings; not used")
        physics_cache = None
    if physics_cache is not None:
        n = sum(sources[i].name in physics_cache.objects for i in todo)
        log(f"physics cache: trials recorded for {n} of the {len(todo)} objects to generate")
    tasks = [
        (
            sources[i],
            config,
            i,
            object_seed(config.seed, sources[i].name),
            physics_cache.for_object(sources[i].name) if physics_cache is not None else None,
        )
        for i in interleaved(todo, m)
    ]

    def on_result(r: dict) -> str:
        oid = r["object_id"]
        if r["status"] == "done":
            rel = storage.shard_relpath(oid)
            atomic.write_bytes(out / rel, r["data"])
            entry = {"object_id": oid, "file": rel, "sha256": hashlib.sha256(r["data"]).hexdigest(), **r["counts"]}
            storage.record_shard(m, entry, **r["info"])
        else:
            storage.record_skip(m, oid, r["reason"], **r["info"])
            if r.get("retry"):
                m["objects"][oid]["retry"] = True
        if not any(o["status"] == "pending" for o in m["objects"]):
            m["complete"] = True
        storage.write_manifest(out, m)
        c = m["counts"]
        return f"grasps={c['grasps']} pos={100 * c['positivity_rate']:.1f}% skipped={c['objects_skipped']}"

    run_tasks(object_task, tasks, workers=workers, use_ray=use_ray, on_result=on_result, progress=progress)
    m["complete"] = not any(o["status"] == "pending" for o in m["objects"])
    storage.write_manifest(out, m)
    return m
