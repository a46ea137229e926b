"""The planner's own candidates as a grasp dataset (Dex-Net's fix for a ranker that never saw
the policy's grasps): ``datagen planner-grasps``.

From an existing ``vgq-grasps`` dataset (the source, SRC), per object:

1. reload the mesh exactly as datagen did (:func:`datagen.mesh.load_object` with SRC's
   config, same scale) and its stable poses (:func:`datagen.mesh.stable_poses`);
2. for up to ``images_per_object`` of its rendered images (a seeded order), check the pose:
   the mesh rendered at the image's stable pose from its ``T_world_camera`` must match the
   stored depth (:func:`check_pose`; a mismatch fails the object, it is never labelled);
3. pass the image through the depth-sensor model and run the planner's sampler on it
   (:func:`planner_candidates`: ``planning.sampler.analyse_scene`` + ``sample_grasps`` with
   ``PlanParams()``, as ``planning.policy.plan_resampled`` does; SRC's images are already at
   the model's intrinsics); draw up to ``candidates`` of its collision-free candidates at
   random (TCP inside the image). The sensor model scales every depth by one Gamma draw (3%
   std in the ``realistic`` preset), which would put a candidate found in the scaled scene
   centimetres off the true one (below the table at a scale > 1): each candidate's TCP is moved
   along its camera ray by the scale measured between the two images (:func:`depth_scale`,
   :func:`unscaled_frames`), keeping its pixel and orientation, as datagen's rows keep the true
   grasp while the crop stage scales the image;
4. label them as datagen's physics label does on the true mesh: a grasp whose nominal
   approach collides (:class:`datagen.collision.CollisionChecker`) gets 0 without trials,
   the others ``trials`` noisy pybullet trials (``datagen.pipeline._physics_success``);
   ``p_collision_free`` and ``pad_quality`` as datagen computes them for that label,
   ``fc_quality`` NaN (not computed).

The result is a ``vgq-grasps`` dataset (one shard per object: the used image rows of SRC,
clean depth as datagen stores it, and the candidates' rows; an image where the sampler finds no
candidate is passed over, up to 3 x ``images_per_object`` images are tried), so ``datagen sample`` and
``datagen crops`` run on it unchanged. Its manifest keeps SRC's objects and config and
records ``split_object_ids`` (SRC's objects), over which ``datagen sample`` draws its
object-wise split: every object lands in the split it has when SRC is sampled with the same
seed (:func:`datagen.sampling.split_population`).

Randomness: per object from (run seed, object name) (:func:`planner_object_seed`); the sensor
model's draw of the image that becomes row r of the object's shard is
``datagen.sensor.image_rng(sensor_seed, object_id, r)``, the crop stage's stream, so
``datagen crops --seed <sensor_seed>`` sees the very image the sampler saw (while sampling
keeps every image of the object).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vgq import atomic
from vgq.camera import Intrinsics
from vgq.schema import GRASP_FIELDS, GRASP_LABEL_FIELDS, IMAGE_FIELDS

from . import storage
from .config import ConfigError, DatagenConfig, recorded_config

STAGE = "planner_grasps"  # the manifest key that records this stage


class PoseMismatch(Exception):
    """The mesh at the recorded stable pose does not render to the stored depth image."""


@dataclass(frozen=True)
class PlannerGraspParams:
    """Settings of the stage. ``trials``: noisy physics trials per collision-free candidate;
    ``sensor``: the depth-sensor preset the sampler's image passes through (``clean``: none);
    ``sensor_seed``: the crop stage's seed whose per-image stream draws it; ``max_mismatch``:
    the largest fraction of the object's pixels whose rendered depth may differ from the stored
    one by more than ``depth_tolerance`` metres (pose self-check)."""

    images_per_object: int = 2
    candidates: int = 24
    trials: int = 8
    sensor: str = "realistic"
    sensor_seed: int = 0
    seed: int = 0
    depth_tolerance: float = 0.001
    max_mismatch: float = 0.02

    def __post_init__(self) -> None:
        for name in ("images_per_object", "candidates", "trials"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{name.replace('_', '-')} must be an integer >= 1, got {v!r}")
        for name in ("seed", "sensor_seed"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name.replace('_', '-')} must be >= 0, got {getattr(self, name)}")
        if not (self.depth_tolerance > 0 and 0 <= self.max_mismatch < 1):
            raise ValueError(f"bad self-check tolerances: {self.depth_tolerance} m, {self.max_mismatch}")
        from .sensor import resolve

        resolve(self.sensor)  # ValueError naming an unknown preset

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def planner_object_seed(run_seed: int, name: str) -> int:
    """A 63-bit seed from this stage's run seed and the object name (not datagen generate's)."""
    h = hashlib.sha256(f"vgq-planner-grasps:{int(run_seed)}:{name}".encode()).digest()
    return int.from_bytes(h[:8], "little") >> 1


# ----------------------------------------------------------------------------- pure functions


def depth_mismatch(rendered: np.ndarray, stored: np.ndarray, table: np.ndarray, tolerance: float) -> float:
    """Fraction of the object's pixels whose depths differ by more than ``tolerance`` metres.

    ``rendered``, ``stored``, ``table`` (H, W) metres (0 = no surface): the mesh rendered at the
    recorded pose, the dataset's image, the table alone. The object's pixels are those where
    either image differs from the bare table; 1.0 when neither shows the object."""
    r, s, t = (np.asarray(a, np.float64) for a in (rendered, stored, table))
    obj = (np.abs(r - t) > tolerance) | (np.abs(s - t) > tolerance)
    if not obj.any():
        return 1.0
    return float(np.count_nonzero(np.abs(r - s)[obj] > tolerance) / np.count_nonzero(obj))


def depth_scale(seen: np.ndarray, clean: np.ndarray) -> float:
    """The sensor's global depth-scale error: the median ratio of the pixels both images read
    (``seen`` the sensor's image, ``clean`` the rendered one, metres, 0 = none); 1.0 when none.
    The sensor model multiplies every depth by one Gamma draw (``gamma_shape``); the rest of its
    noise is zero-mean, so the median recovers that draw to ~1e-4."""
    s, c = np.asarray(seen, np.float64), np.asarray(clean, np.float64)
    ok = (s > 0) & (c > 0) & np.isfinite(s) & np.isfinite(c)
    return float(np.median(s[ok] / c[ok])) if ok.any() else 1.0


def unscaled_frames(frames_camera: np.ndarray, scale: float) -> np.ndarray:
    """Grasp frames (n, 4, 4), camera frame, found in an image whose depths read ``scale`` times
    the true ones, moved to the true scene: the TCP slides along its camera ray to 1 / scale of
    its distance (the pixel and the orientation stay)."""
    out = np.array(frames_camera, np.float64, copy=True).reshape(-1, 4, 4)
    out[:, :3, 3] /= float(scale)
    return out


def grasp_omega(T_object_grasp: np.ndarray) -> np.ndarray:
    """Rotations omega (n,) in [0, 2 pi) radians of grasp frames (n, 4, 4) (object frame) about
    their jaw axis, from datagen's deterministic base frame (:func:`datagen.gripper.grasp_frames`
    at omega = 0), as datagen records ``omega``."""
    from .gripper import grasp_frames

    T = np.asarray(T_object_grasp, np.float64).reshape(-1, 4, 4)
    if len(T) == 0:
        return np.zeros(0)
    base = grasp_frames(T[:, :3, 3], T[:, :3, 0], 0.0)
    rel = np.einsum("nji,njk->nik", base[:, :3, :3], T[:, :3, :3])  # R_base^T R = Rx(omega)
    return np.mod(np.arctan2(rel[:, 2, 1], rel[:, 1, 1]), 2 * np.pi)


def grasp_rows(T_world_grasp: np.ndarray, T_world_camera: np.ndarray, T_world_object: np.ndarray, intr: Intrinsics):
    """GRASP_FIELDS columns (except ``image_index``, ``grasp_id`` and the labels) of world grasp
    frames (n, 4, 4) seen from ``T_world_camera``, and whether each TCP lies in the image."""
    from .project import project_grasps

    pr = project_grasps(T_world_grasp, T_world_camera, intr)
    u, v = np.asarray(pr["u"]), np.asarray(pr["v"])
    rows = {k: np.asarray(pr[k], np.float32) for k in ("u", "v", "z", "q", "beta", "psi", "jaw_angle")}
    rows["omega"] = grasp_omega(np.linalg.inv(T_world_object) @ T_world_grasp).astype(np.float32)
    return rows, np.asarray(pr["in_image"], bool) & np.isfinite(u) & np.isfinite(v)


def planner_candidates(depth: np.ndarray, intr: Intrinsics, rng: np.random.Generator, params=None):
    """The planner's collision-free candidates on ``depth`` (H, W metres, 0 = no reading, at the
    model's intrinsics ``intr``): ``(planning.sampler.Candidates`` (camera frame), stage counts)``,
    drawn as ``planning.policy.plan_resampled`` draws them (without the network)."""
    from planning.sampler import Candidates, analyse_scene, collision_checker, sample_grasps
    from planning.types import PlanParams

    params = params or PlanParams()
    scene = analyse_scene(np.asarray(depth, np.float32), intr, params, rng)
    counts = {"object_pixels": int(scene.objects.sum())}
    if counts["object_pixels"] == 0:
        return Candidates.empty(), counts
    cands, c = sample_grasps(scene, params, rng, collision_checker(scene, params, rng))
    counts.update(c)
    return cands, counts


# ----------------------------------------------------------------------------- one object


def mesh_source(rec: dict):
    """The :class:`datagen.mesh.MeshSource` of a manifest object record (as datagen listed it)."""
    from .mesh import MeshSource

    source = str(rec["source"])
    procedural = source.startswith("family:")
    return MeshSource(
        name=str(rec["name"]),
        path=Path(source),
        scale=float(rec.get("source_scale", 1.0)),
        family=rec.get("family") if procedural else None,
        params=(rec.get("params") or None) if procedural else None,
    )


def check_pose(mesh_world, T_world_camera: np.ndarray, stored: np.ndarray, intr: Intrinsics, params) -> float:
    """Render ``mesh_world`` from ``T_world_camera`` and compare with the ``stored`` image
    (:func:`depth_mismatch`); raise :class:`PoseMismatch` above ``params.max_mismatch``. Returns
    the mismatch."""
    from .render import render_depth, table_depth

    rendered = render_depth(mesh_world, T_world_camera, intr)
    mis = depth_mismatch(rendered, stored, table_depth(T_world_camera, intr), params.depth_tolerance)
    if mis > params.max_mismatch:
        raise PoseMismatch(
            f"{100 * mis:.1f}% of the object's pixels differ by more than {1e3 * params.depth_tolerance:g} mm "
            f"from the stored depth (allowed {100 * params.max_mismatch:g}%)"
        )
    return mis


def _check_object(obj, rec: dict, probs: np.ndarray) -> None:
    """The reloaded object has the scale and stable-pose probabilities SRC recorded."""
    if "mesh_scale" in rec and not np.isclose(obj.scale, rec["mesh_scale"], rtol=1e-6, atol=0):
        raise PoseMismatch(f"mesh scale {obj.scale:.6g} differs from the recorded {rec['mesh_scale']:.6g}")
    want = rec.get("stable_pose_probabilities")
    if want is not None and (len(want) != len(probs) or not np.allclose(probs, want, rtol=1e-6, atol=1e-9)):
        raise PoseMismatch(f"stable poses {np.round(probs, 4).tolist()} differ from the recorded {want}")


def planner_object(
    src_root: str, entry: dict, rec: dict, config: DatagenConfig, params: PlannerGraspParams, seed: int
) -> tuple[dict, dict, dict]:
    """One object's shard arrays (IMAGE_FIELDS, GRASP_FIELDS + GRASP_LABEL_FIELDS) and facts
    for the manifest. ``entry``: SRC's shard entry; ``rec``: SRC's object record; ``config``:
    SRC's config; ``seed``: :func:`planner_object_seed`. Raises :class:`PoseMismatch` when the
    mesh does not reproduce SRC's images, MeshError when it cannot be loaded."""
    from planning.types import PlanParams

    from .collision import CollisionChecker
    from .labels import label_score
    from .mesh import load_object, stable_poses
    from .pipeline import _concat, _physics_success, _robust_fields
    from .quality import resolve_torque_scaling
    from .sensor import image_rng, resolve

    t_start = time.perf_counter()
    intr = config.intrinsics
    oid = int(entry["object_id"])
    obj = load_object(mesh_source(rec), config.mesh)
    T_poses, probs = stable_poses(obj, config.stable_pose_min_probability, config.max_stable_poses)
    _check_object(obj, rec, probs)
    sh = storage.GraspDataset(src_root).load(entry)
    images = sh.images
    qparams = dataclasses.replace(config.quality, torque_scaling=resolve_torque_scaling(obj.mesh, config.quality))
    cfg_trials = dataclasses.replace(config, label=dataclasses.replace(config.label, trials=params.trials))
    _, sensor = resolve(params.sensor)
    plan_params = dataclasses.replace(PlanParams(), gripper=config.gripper)

    ss_order, ss_images = np.random.SeedSequence(seed).spawn(2)
    n_src = len(images["depth"])
    order = np.random.default_rng(ss_order).permutation(n_src)[: 3 * params.images_per_object]
    info: dict = {"images_tried": 0, "pool": [], "self_check_mismatch": [], "depth_scale": []}
    image_parts, grasp_parts = [], []
    n_rows = 0
    for img, ss_img in zip(order, ss_images.spawn(len(order))):
        if len(image_parts) >= params.images_per_object:
            break
        img = int(img)
        pose_id = int(images["stable_pose_id"][img])
        if not 0 <= pose_id < len(T_poses):
            raise PoseMismatch(f"image {img} has stable_pose_id {pose_id}, the mesh has {len(T_poses)} poses")
        T_wo, T_wc = T_poses[pose_id], np.asarray(images["T_world_camera"][img], np.float64)
        mesh_world = obj.mesh.copy()
        mesh_world.apply_transform(T_wo)
        info["self_check_mismatch"].append(check_pose(mesh_world, T_wc, images["depth"][img], intr, params))
        info["images_tried"] += 1
        ss_plan, ss_pick, ss_robust, ss_physics = ss_img.spawn(4)
        rng_plan, rng_pick, rng_robust = (np.random.default_rng(s) for s in (ss_plan, ss_pick, ss_robust))
        seen = sensor.apply(images["depth"][img], image_rng(params.sensor_seed, oid, len(image_parts)), intr)
        cands, _ = planner_candidates(seen, intr, rng_plan, plan_params)
        scale = depth_scale(seen, images["depth"][img])
        info["depth_scale"].append(scale)
        T_wg_all = T_wc @ unscaled_frames(cands.frames, scale)
        rows, inside = grasp_rows(T_wg_all, T_wc, T_wo, intr)
        info["pool"].append(int(len(cands)))
        ok = np.flatnonzero(inside)
        if len(ok) == 0:
            continue
        pick = np.sort(rng_pick.choice(ok, size=min(params.candidates, len(ok)), replace=False))
        T_wg = T_wg_all[pick]
        collides = np.asarray(CollisionChecker(mesh_world, config.gripper).collides(T_wg), bool)
        success = _physics_success(obj.mesh, T_wo, T_wg, ~collides, cfg_trials, ss_physics, info)
        checker_c = CollisionChecker(mesh_world, config.gripper, clearance=config.collision.clearance)
        p_cf, pad_q = _robust_fields("physics", obj.mesh, T_wo, T_wg, collides, checker_c, config, qparams, rng_robust)
        n = len(pick)
        grasp_parts.append(
            {
                "image_index": np.full(n, len(image_parts), np.int32),
                "grasp_id": np.arange(n_rows, n_rows + n, dtype=np.int32),
                **{k: v[pick] for k, v in rows.items()},
                "quality": label_score("physics", np.full(n, np.nan), ~collides, p_cf, pad_q, success),
                "collision_free": ~collides,
                "fc_quality": np.full(n, np.nan),
                "p_collision_free": p_cf,
                "pad_quality": pad_q,
                "success_rate": np.where(collides, np.nan, success),
            }
        )
        image_parts.append({k: images[k][img : img + 1] for k in IMAGE_FIELDS})
        n_rows += n
    info["images_used"] = len(image_parts)
    info["candidates"] = n_rows
    info["seconds"] = time.perf_counter() - t_start
    fields = {**GRASP_FIELDS, **GRASP_LABEL_FIELDS}
    return _concat(image_parts, IMAGE_FIELDS), _concat(grasp_parts, fields), info


def object_task(src_root: str, entry: dict, rec: dict, config_d: dict, params: PlannerGraspParams, seed: int) -> dict:
    """Worker task: one object's shard (bytes) and counts; never raises for a bad object (the
    result says why it failed; ``retry``: an unexpected error, retried on resume)."""
    from .mesh import MeshError

    config = DatagenConfig.from_dict(config_d)
    oid = int(entry["object_id"])
    try:
        images, grasps, info = planner_object(src_root, entry, rec, config, params, seed)
    except PoseMismatch as e:
        return {"object_id": oid, "status": "failed", "reason": f"pose self-check failed: {e}"}
    except MeshError as e:
        return {"object_id": oid, "status": "failed", "reason": f"mesh does not load as in the source: {e}"}
    except Exception as e:  # keep the run going; the object is retried on resume
        return {"object_id": oid, "status": "failed", "reason": f"error: {type(e).__name__}: {e}", "retry": True}
    if len(grasps["grasp_id"]) == 0:
        return {
            "object_id": oid,
            "status": "empty",
            "reason": "the planner found no candidate in the image",
            "info": info,
        }
    data = storage.encode_shard(images, grasps, where=storage.shard_relpath(oid))
    return {
        "object_id": oid,
        "status": "done",
        "data": data,
        "counts": storage.shard_counts(images, grasps, config.label_threshold),
        "info": info,
    }


# ----------------------------------------------------------------------------- run driver


def output_config(src_manifest: dict, params: PlannerGraspParams) -> dict:
    """SRC's config as this dataset's: the physics label with ``params.trials`` trials."""
    cfg = DatagenConfig.from_dict(recorded_config(src_manifest["config"]))
    label = dataclasses.replace(cfg.label, kind="physics", trials=params.trials)
    return json.loads(json.dumps(dataclasses.replace(cfg, label=label).to_dict()))


def source_trials(src_manifest: dict) -> int | None:
    """The label trials of a physics-labelled SRC (None for another label)."""
    cfg = DatagenConfig.from_dict(recorded_config(src_manifest["config"]))
    return int(cfg.label.trials) if cfg.label.kind == "physics" else None


def prepare_run(src: str | Path, out: str | Path, params: PlannerGraspParams) -> tuple[storage.GraspDataset, dict]:
    """Open SRC and the output manifest (new, or the existing one to resume). On resume, objects
    SRC has finished since (a source still being generated) become pending, and the split
    population follows SRC's. Raises ConfigError when ``out`` holds a dataset of another source,
    object list or settings."""
    ds = storage.open_dataset(src)
    src_root = str(Path(src).resolve())
    stage = {"source": src_root, "params": params.to_dict()}
    src_m = ds.manifest
    have = set(ds.object_ids)
    out = Path(out)
    if (out / storage.MANIFEST).exists():
        m = storage.read_manifest(out, storage.GRASP_FORMAT)
        if json.loads(json.dumps(m.get(STAGE, {}))) != json.loads(json.dumps(stage)):
            raise ConfigError(
                f"{out} holds planner grasps of another source or settings ({m.get(STAGE)}); use a new --out"
            )
        if [o["name"] for o in m["objects"]] != [o["name"] for o in ds.objects]:
            raise ConfigError(f"{out} holds planner grasps of another object list than {src}; use a new --out")
        for o in m["objects"]:
            if o.get("not_in_source") and o["object_id"] in have:
                for k in ("not_in_source", "reason"):
                    o.pop(k, None)
                o["status"] = "pending"
        m["split_object_ids"] = [int(i) for i in src_m.get("split_object_ids", ds.object_ids)]
        storage.update_counts(m)
        return ds, m
    keep = ("object_id", "name", "source", "source_scale", "family", "params")
    objects = [{k: o[k] for k in keep if k in o} for o in ds.objects]
    cfg = output_config(src_m, params)
    m = storage.new_grasp_manifest(
        cfg,
        src_m["seed"],
        objects,
        DatagenConfig.from_dict(cfg).label_threshold,
        **({"intrinsics": src_m["intrinsics"]} if src_m.get("intrinsics") else {}),
        source_dataset=src_root,
        split_object_ids=[int(i) for i in src_m.get("split_object_ids", ds.object_ids)],
        **{STAGE: stage},
    )
    for o in m["objects"]:
        if o["object_id"] not in have:
            so = ds.objects[o["object_id"]]
            reason = f"not in the source ({so.get('status')}: {so.get('reason', 'no shard')})"
            storage.record_skip(m, o["object_id"], reason, not_in_source=True)
    return ds, m


def run_planner_grasps(
    src: str | Path,
    out: str | Path,
    params: PlannerGraspParams = PlannerGraspParams(),
    workers: int = 1,
    max_objects: int | None = None,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> dict:
    """Label the planner's candidates on SRC's images into ``out`` (resuming a killed run: objects
    whose shard is listed are skipped). ``max_objects``: only the first N pending objects in
    datagen's work order (round-robin over the families; the same N on every resume). Returns
    the manifest; an object that failed (pose self-check, mesh, error) is ``skipped`` with
    ``failed`` true and its ``reason``."""
    from .parallel import run_tasks
    from .pipeline import interleaved

    out = Path(out)
    ds, m = prepare_run(src, out, params)
    entries = {int(e["object_id"]): e for e in ds.shard_entries}
    chosen = interleaved(sorted(entries), m)[:max_objects]  # the run's objects (all, or a fixed subset)
    todo = [
        i
        for i in chosen
        if m["objects"][i].get("status") == "pending"
        or (m["objects"][i].get("status") == "skipped" and m["objects"][i].get("retry"))
    ]
    done_before = len(chosen) - len(todo)
    for i in todo:
        m["objects"][i]["status"] = "pending"
        m["objects"][i].pop("retry", None)
    storage.update_counts(m)
    storage.write_manifest(out, m)
    if done_before:
        log(f"resuming {out}: {done_before} objects already done, skipped or failed, {len(todo)} to go")
    config_d = m["config"]
    src_root = str(ds.root.resolve())
    tasks = [
        (src_root, entries[i], ds.objects[i], config_d, params, planner_object_seed(params.seed, ds.objects[i]["name"]))
        for i in todo
    ]

    def on_result(r: dict) -> str:
        oid = r["object_id"]
        if r["status"] == "done":
            rel = storage.shard_relpath(oid)
            atomic.write_bytes(out / rel, r["data"])
            entry = {"object_id": oid, "file": rel, "sha256": hashlib.sha256(r["data"]).hexdigest(), **r["counts"]}
            m["objects"][oid].pop("failed", None)
            storage.record_shard(m, entry, **r["info"])
        elif r["status"] == "empty":
            storage.record_skip(m, oid, r["reason"], **r["info"])
        else:
            storage.record_skip(m, oid, r["reason"], failed=True)
            if r.get("retry"):
                m["objects"][oid]["retry"] = True
            log(f"object {m['objects'][oid]['name']} (id {oid}) failed: {r['reason']}")
        m["complete"] = not any(o["status"] == "pending" for o in m["objects"])
        storage.write_manifest(out, m)
        c = m["counts"]
        return f"grasps={c['grasps']} pos={100 * c['positivity_rate']:.1f}%"

    run_tasks(object_task, tasks, workers=workers, on_result=on_result, progress=progress, desc="planner grasps")
    m["complete"] = not any(o["status"] == "pending" for o in m["objects"])
    storage.write_manifest(out, m)
    return m
