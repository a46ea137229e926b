"""Label study (issue 17): which grasp label predicts physical success under execution noise?

For held-out objects of every shape family (the everyday families of :mod:`datagen.families`
built with a seed no training run uses, pybullet_data random_urdfs past the first 600 that
the recipe trains on, and simple primitives), one stable pose each, the study samples
antipodal grasps with a random approach (omega, beta flip as in datagen) and computes per
grasp, timing each stage:

* ``fc``: robust Ferrari-Canny (datagen's, Dex-Net torque scaling), ``fc_fixed``: the same
  with one torque scaling for every object (1 / 0.02 m);
* ``cf_nominal``: collision-free at the nominal pose with zero clearance (the paper's check);
* ``p_cf``: P(collision-free) under execution noise with a clearance
  (:func:`datagen.collision.collision_free_probability`);
* ``pad_q``: Ferrari-Canny at the pad contacts (:mod:`datagen.pads`);
* physics: ``label_trials`` noisy trials (the physics label: their success rate) and, with
  other seeds, ``eval_trials`` noisy trials (the ground truth the labels are scored against),
  plus one noise-free trial whose first pad touches validate the pad-contact model.

Results are cached per object (``<out>/objects/<name>.npz``), so a killed study resumes;
:func:`summarise` turns them into AUCs, precisions, costs and plots.
"""

from __future__ import annotations

import dataclasses
import io
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from training.metrics import auc
from vgq import atomic

from .collision import RobustCollisionParams
from .config import DatagenConfig
from .physics import PhysicsParams

FIXED_TORQUE_SCALING = 1.0 / 0.02  # 1/m: one scaling for every object (the "fixed" rule studied)
PRIMITIVES = {
    "prim_cube": ("box", (0.04, 0.04, 0.04)),
    "prim_bar": ("box", (0.04, 0.04, 0.16)),  # long: Dex-Net's torque scaling penalises it
    "prim_block": ("box", (0.04, 0.06, 0.09)),
    "prim_cylinder": ("cylinder", (0.02, 0.07)),
    "prim_rod": ("cylinder", (0.02, 0.18)),
    "prim_ring": ("annulus", (0.012, 0.03, 0.03)),
}


@dataclass(frozen=True)
class StudyParams:
    """Study size (objects per source, grasps per object, trials per grasp) and seeds."""

    grasps: int = 24
    label_trials: int = 5
    eval_trials: int = 5
    per_family: int = 2
    random_urdfs: int = 8
    primitives: bool = True
    family_seed: int = 1001  # held out: the training families use other seeds
    seed: int = 17


# ----------------------------------------------------------------------------- objects


def study_sources(params: StudyParams, out: Path) -> list[tuple[str, object]]:
    """``[(family, MeshSource)]`` of the held-out objects."""
    from .mesh import MeshSource, mesh_sources

    out_list: list[tuple[str, object]] = []
    try:
        from .families import family_names, family_sources
    except ImportError:  # the families module is not on this branch
        family_names = None
    if family_names is not None and params.per_family > 0:
        counts = {f: params.per_family for f in family_names()}
        for s in family_sources(counts, seed=params.family_seed):
            out_list.append((s.family, s))
    if params.primitives:
        import trimesh

        d = out / "primitives"
        d.mkdir(parents=True, exist_ok=True)
        for name, (kind, dims) in PRIMITIVES.items():
            f = d / f"{name}.stl"
            if not f.is_file():
                if kind == "box":
                    m = trimesh.creation.box(extents=dims)
                elif kind == "cylinder":
                    m = trimesh.creation.cylinder(radius=dims[0], height=dims[1], sections=48)
                else:
                    m = trimesh.creation.annulus(r_min=dims[0], r_max=dims[1], height=dims[2], sections=48)
                atomic.write_bytes(f, m.export(file_type="stl"))
            out_list.append(("primitive", MeshSource(name, f, 1.0)))
    if params.random_urdfs > 0:
        srcs = mesh_sources(None)[600:]  # the recipe trains on the first 600
        idx = np.linspace(0, len(srcs) - 1, params.random_urdfs).round().astype(int)
        out_list += [("random_urdfs", srcs[i]) for i in idx]
    return out_list


# ----------------------------------------------------------------------------- one object


def _timed(times: dict, key: str, fn, *a, **kw):
    t0 = time.perf_counter()
    r = fn(*a, **kw)
    times[key] = times.get(key, 0.0) + time.perf_counter() - t0
    return r


def _select(src, config: DatagenConfig, params: StudyParams, seed: int, times: dict):
    """The object, its most probable stable pose and up to ``params.grasps`` grasps with a
    collision-free approach (deterministic in ``seed``): a dict, or a skip dict."""
    from .collision import CollisionChecker
    from .grasps import sample_antipodal_grasps
    from .gripper import align_to_table, grasp_frames
    from .mesh import load_object, stable_poses

    ss = np.random.SeedSequence(seed).spawn(8)
    obj = load_object(src, config.mesh)
    T_poses, _ = stable_poses(obj, 0.0, 1)
    if len(T_poses) == 0:
        return {"status": "skipped", "reason": "no stable pose"}
    T_wo = T_poses[0]
    ap = dataclasses.replace(config.antipodal, num_samples=4 * params.grasps)
    grasps = _timed(times, "sample", sample_antipodal_grasps, obj.mesh, ap, np.random.default_rng(ss[0]))
    if len(grasps) == 0:
        return {"status": "skipped", "reason": "no antipodal grasp"}
    mesh_world = obj.mesh.copy()
    mesh_world.apply_transform(T_wo)
    checker0 = CollisionChecker(mesh_world, config.gripper)
    # as in datagen: a random approach (omega, beta flip) per grasp; the study keeps grasps with a
    # collision-free approach at the nominal pose (up to 4 draws each), as the study did
    rng = np.random.default_rng(ss[2])
    T_og0 = grasp_frames(grasps.centers, grasps.axes, 0.0)
    T_wg = np.zeros((len(grasps), 4, 4))
    free = np.zeros(len(grasps), bool)
    n_checked = 0
    for _ in range(4):
        todo = np.flatnonzero(~free)
        if len(todo) == 0:
            break
        T_try, _, _ = align_to_table(T_wo @ T_og0[todo], rng)
        hit = _timed(times, "collision", checker0.collides, T_try)
        n_checked += len(todo)
        T_wg[todo[~hit]] = T_try[~hit]
        free[todo[~hit]] = True
    keep = np.flatnonzero(free)[: params.grasps]
    times["collision"] *= len(keep) / max(n_checked, 1)  # cost of one check per labelled grasp
    n_sampled = len(grasps)
    grasps, T_wg = grasps[keep], T_wg[keep]
    if len(grasps) == 0:
        return {"status": "skipped", "reason": f"none of {n_sampled} antipodal grasps has a collision-free approach"}
    times["sample"] *= len(grasps) / n_sampled
    return {
        "status": "ok",
        "obj": obj,
        "T_wo": T_wo,
        "grasps": grasps,
        "T_wg": T_wg,
        "n_sampled": n_sampled,
        "ss": ss,
        "mesh_world": mesh_world,
    }


def _analytic(
    sel: dict, config: DatagenConfig, robust: RobustCollisionParams, physics: PhysicsParams, times: dict
) -> dict:
    """The analytic scores of the selected grasps (arrays), timing each stage into ``times``."""
    from .collision import CollisionChecker, collision_free_probability
    from .pads import pad_quality, robust_pad_quality
    from .quality import resolve_torque_scaling, robust_ferrari_canny

    obj, T_wo, grasps, T_wg, ss = sel["obj"], sel["T_wo"], sel["grasps"], sel["T_wg"], sel["ss"]
    n = len(grasps)
    T_og = np.linalg.inv(T_wo) @ T_wg
    q = dataclasses.replace(config.quality, torque_scaling=resolve_torque_scaling(obj.mesh, config.quality))
    fc = _timed(times, "fc", robust_ferrari_canny, obj.mesh, grasps, q, np.random.default_rng(ss[1]))
    qf = dataclasses.replace(config.quality, torque_scaling=FIXED_TORQUE_SCALING)
    fc_fixed = robust_ferrari_canny(obj.mesh, grasps, qf, np.random.default_rng(ss[1]))
    checker = CollisionChecker(sel["mesh_world"], config.gripper, clearance=robust.clearance)
    p_cf = _timed(
        times, "robust_collision", collision_free_probability, checker, T_wg, robust, np.random.default_rng(ss[3])
    )
    pad_q, pad_ok, pad_c = _timed(times, "pad", pad_quality, obj.mesh, T_og, config.gripper, q, q.torque_scaling)
    pad_q_fixed = pad_quality(obj.mesh, T_og, config.gripper, qf, FIXED_TORQUE_SCALING)[0]
    noise = RobustCollisionParams(
        num_samples=robust.num_samples,
        sigma_translation=physics.sigma_translation,
        sigma_rotation=physics.sigma_rotation,
        clearance=0.0,
    )
    rpad_q, rpad_ok = _timed(
        times,
        "robust_pad",
        robust_pad_quality,
        obj.mesh,
        T_og,
        config.gripper,
        qf,
        FIXED_TORQUE_SCALING,
        noise,
        np.random.default_rng(ss[6]),
    )
    return {
        "torque_scaling": float(q.torque_scaling),
        "extents": np.sort(obj.mesh.extents).tolist(),
        "fc": fc,
        "fc_fixed": fc_fixed,
        "cf_nominal": np.ones(n, bool),
        "cf_clear": ~checker.collides(T_wg),
        "p_cf": p_cf,
        "pad_q": pad_q,
        "pad_q_fixed": pad_q_fixed,
        "pad_ok": pad_ok,
        "pad_contacts": pad_c,
        "robust_pad_q": rpad_q,
        "robust_pad_ok": rpad_ok,
        "contacts": grasps.contacts,
        "beta": np.arccos(np.clip(-T_wg[:, 2, 2], -1, 1)),
    }


def study_object(
    family: str,
    src,
    config: DatagenConfig,
    params: StudyParams,
    physics: PhysicsParams,
    robust: RobustCollisionParams,
    seed: int,
    cache_dir=None,
) -> dict:
    """All per-grasp scores and trial outcomes of one object (arrays), with stage times (s)."""
    from .physics import _worker_sim, run_trials

    times: dict[str, float] = {}
    sel = _select(src, config, params, seed, times)
    if sel["status"] != "ok":
        return sel
    feats = _analytic(sel, config, robust, physics, times)
    obj, T_wo, T_wg, ss, n = sel["obj"], sel["T_wo"], sel["T_wg"], sel["ss"], len(sel["grasps"])
    sim = _worker_sim(config.gripper, physics, cache_dir)
    pose = _timed(times, "physics_setup", sim.set_object, obj.mesh, T_wo)
    nominal = run_trials(sim, T_wg, 1, None)
    lab = run_trials(sim, T_wg, params.label_trials, np.random.default_rng(ss[4]))
    times["physics_label"] = lab.seconds
    ev = run_trials(sim, T_wg, params.eval_trials, np.random.default_rng(ss[5]))
    return {
        "status": "done",
        "family": family,
        "name": src.name,
        "n": n,
        "n_sampled": sel["n_sampled"],
        "pose": pose,
        "times": times,
        **feats,
        "nominal_held": nominal.held[:, 0],
        "label_reason": lab.reason,
        "nominal_reason": nominal.reason[:, 0],
        "first_touch": nominal.first_touch[:, 0],
        "label_held": lab.held,
        "label_firm": lab.firm,
        "eval_held": ev.held,
        "eval_firm": ev.firm,
        "eval_reason": ev.reason,
    }


def _object_task(family, src, config, params, physics, robust, seed, path: str) -> dict:
    """Worker task: study one object and write its result to ``path`` (npz + json)."""
    try:
        r = study_object(family, src, config, params, physics, robust, seed, Path(path).parent.parent / "vhacd")
    except Exception as e:  # a bad mesh must not stop the study
        r = {"status": "skipped", "reason": f"{type(e).__name__}: {e}"}
    r.setdefault("family", family)
    r.setdefault("name", src.name)
    meta = {k: v for k, v in r.items() if not isinstance(v, np.ndarray)}
    arrays = {k: v for k, v in r.items() if isinstance(v, np.ndarray)}
    buf = io.BytesIO()
    np.savez(buf, meta=np.array(json.dumps(meta)), **arrays)
    atomic.write_bytes(Path(path), buf.getvalue())
    return meta


def run_study(
    out: str | Path,
    params: StudyParams = StudyParams(),
    config: DatagenConfig | None = None,
    physics: PhysicsParams = PhysicsParams(),
    robust: RobustCollisionParams = RobustCollisionParams(),
    workers: int = 1,
    log=print,
) -> list[dict]:
    """Run (or resume) the study into ``out``; returns the per-object results."""
    from .parallel import run_tasks
    from .pipeline import object_seed

    out = Path(out)
    (out / "objects").mkdir(parents=True, exist_ok=True)
    config = config or DatagenConfig()
    atomic.write_bytes(
        out / "study.json",
        json.dumps(
            {
                "study": dataclasses.asdict(params),
                "physics": dataclasses.asdict(physics),
                "robust_collision": dataclasses.asdict(robust),
                "config": config.to_dict(),
            },
            indent=2,
        ).encode(),
    )
    sources = study_sources(params, out)
    tasks = []
    for fam, src in sources:
        path = out / "objects" / f"{src.name}.npz"
        if not path.is_file():
            tasks.append((fam, src, config, params, physics, robust, object_seed(params.seed, src.name), str(path)))
    log(f"label study: {len(sources)} objects, {len(sources) - len(tasks)} cached, {len(tasks)} to run")
    run_tasks(_object_task, tasks, workers=workers, on_result=lambda m: f"{m['name']}: {m['status']}", desc="objects")
    return load_results(out)


def augment(
    out: str | Path,
    config: DatagenConfig | None = None,
    params: StudyParams = StudyParams(),
    physics: PhysicsParams = PhysicsParams(),
    robust: RobustCollisionParams = RobustCollisionParams(),
    log=print,
) -> int:
    """Recompute the analytic scores of cached objects (same grasps: the selection is
    deterministic; checked against the cached ``fc``) and add new ones; trials are kept.
    Returns the number of objects updated."""
    from .pipeline import object_seed

    out = Path(out)
    config = config or DatagenConfig()
    done = {r["name"]: r for r in load_results(out) if r.get("status") == "done"}
    k = 0
    for _fam, src in study_sources(params, out):
        r = done.get(src.name)
        if r is None or "robust_pad_q" in r:
            continue
        times = dict(r["times"])
        sel = _select(src, config, params, object_seed(params.seed, src.name), {})
        feats = _analytic(sel, config, robust, physics, times)
        if not np.allclose(feats["fc"], r["fc"]):
            raise RuntimeError(f"{src.name}: the recomputed grasps differ from the cached ones")
        r.update(feats)
        r["times"] = times
        meta = {kk: v for kk, v in r.items() if not isinstance(v, np.ndarray)}
        arrays = {kk: v for kk, v in r.items() if isinstance(v, np.ndarray)}
        buf = io.BytesIO()
        np.savez(buf, meta=np.array(json.dumps(meta)), **arrays)
        atomic.write_bytes(out / "objects" / f"{src.name}.npz", buf.getvalue())
        k += 1
    log(f"label study: recomputed the analytic scores of {k} cached objects")
    return k


def _more_trials_task(family, src, config, params, physics, robust, seed, path: str, k: int) -> dict:
    """Worker task: ``k`` more noisy label trials (seed stream 7) of a cached object's grasps,
    appended to its ``label_held`` / ``label_firm`` / ``label_reason``."""
    from .physics import _worker_sim, run_trials

    with np.load(path) as z:
        r = json.loads(str(z["meta"]))
        r.update({kk: z[kk] for kk in z.files if kk != "meta"})
    sel = _select(src, config, params, seed, {})
    sim = _worker_sim(config.gripper, physics, Path(path).parent.parent / "vhacd")
    sim.set_object(sel["obj"].mesh, sel["T_wo"])
    rng = np.random.default_rng(np.random.SeedSequence([seed, 7, r["label_held"].shape[1]]))
    res = run_trials(sim, sel["T_wg"], k, rng)
    r["label_held"] = np.concatenate([r["label_held"], res.held], axis=1)
    r["label_firm"] = np.concatenate([r["label_firm"], res.firm], axis=1)
    r["label_reason"] = np.concatenate([r["label_reason"], res.reason], axis=1)
    r["times"]["physics_label"] += res.seconds
    meta = {kk: v for kk, v in r.items() if not isinstance(v, np.ndarray)}
    arrays = {kk: v for kk, v in r.items() if isinstance(v, np.ndarray)}
    buf = io.BytesIO()
    np.savez(buf, meta=np.array(json.dumps(meta)), **arrays)
    atomic.write_bytes(Path(path), buf.getvalue())
    return {"name": src.name, "status": "done"}


def add_label_trials(
    out: str | Path,
    k: int,
    config: DatagenConfig | None = None,
    params: StudyParams = StudyParams(),
    physics: PhysicsParams = PhysicsParams(),
    robust: RobustCollisionParams = RobustCollisionParams(),
    workers: int = 1,
    upto: int | None = None,
) -> None:
    """Run ``k`` more label trials per grasp on every cached object that has fewer than
    ``upto`` (default: current + k) (resumable: objects already there are skipped)."""
    from .parallel import run_tasks
    from .pipeline import object_seed

    out = Path(out)
    config = config or DatagenConfig()
    done = {r["name"]: r for r in load_results(out) if r.get("status") == "done"}
    tasks = []
    for fam, src in study_sources(params, out):
        r = done.get(src.name)
        if r is None or (upto is not None and r["label_held"].shape[1] >= upto):
            continue
        tasks.append(
            (
                fam,
                src,
                config,
                params,
                physics,
                robust,
                object_seed(params.seed, src.name),
                str(out / "objects" / f"{src.name}.npz"),
                k,
            )
        )
    run_tasks(_more_trials_task, tasks, workers=workers, desc="label trials")


def load_results(out: str | Path) -> list[dict]:
    res = []
    for f in sorted((Path(out) / "objects").glob("*.npz")):
        with np.load(f) as z:
            r = json.loads(str(z["meta"]))
            r.update({k: z[k] for k in z.files if k != "meta"})
        res.append(r)
    return res


# ----------------------------------------------------------------------------- analysis


def roc_curve(score, y):
    s = np.asarray(score, np.float64)
    y = np.asarray(y, bool)
    thr = np.unique(s)[::-1]
    tpr = [(s[y] >= t).mean() for t in thr]
    fpr = [(s[~y] >= t).mean() for t in thr]
    return np.r_[0.0, fpr, 1.0], np.r_[0.0, tpr, 1.0]


def candidate_labels(
    r: dict,
    label_threshold: float = 0.002,
    success_threshold: float = 0.5,
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """name -> (continuous score (n,), binary label (n,)) for one object's (or pooled) arrays:
    analytic labels are positive above ``label_threshold``, the physics label above
    ``success_threshold`` (as datagen's ``label`` setting)."""
    fc, cf0, pcf = r["fc"], r["cf_nominal"].astype(bool), r["p_cf"]
    pad, padf = r["pad_q"], r["pad_q_fixed"]
    rpad = r["robust_pad_q"]
    phys = r["label_held"].mean(axis=1)
    return {
        "paper (robust FC > 0.002, nominal collision)": (fc * cf0, (fc > label_threshold) & cf0),
        "paper, fixed torque scaling": (r["fc_fixed"] * cf0, (r["fc_fixed"] > label_threshold) & cf0),
        "robust FC x P(collision-free)": (fc * pcf, (fc > label_threshold) & (pcf >= 0.8)),
        "pad FC x nominal collision": (pad * cf0, (pad > label_threshold) & cf0),
        "pad FC (fixed scaling) x P(cf)": (padf * pcf, (padf > label_threshold) & (pcf >= 0.8)),
        "P(collision-free) alone": (pcf, pcf >= 0.8),
        "robust pad FC (pads under noise)": (rpad, rpad > label_threshold),
        "robust pad FC x P(cf)": (rpad * pcf, (rpad > label_threshold) & (pcf >= 0.8)),
        "physics (success rate of label trials)": (phys, phys > success_threshold),
    }


def pooled(results: list[dict]) -> dict:
    keys = (
        "fc",
        "fc_fixed",
        "cf_nominal",
        "cf_clear",
        "p_cf",
        "pad_q",
        "pad_q_fixed",
        "pad_ok",
        "label_held",
        "robust_pad_q",
        "robust_pad_ok",
        "eval_held",
        "eval_firm",
        "eval_reason",
        "nominal_held",
        "first_touch",
        "pad_contacts",
        "contacts",
    )
    done = [r for r in results if r.get("status") == "done"]
    out = {k: np.concatenate([r[k] for r in done]) for k in keys}
    out["family"] = np.concatenate([[r["family"]] * int(r["n"]) for r in done])
    out["object"] = np.concatenate([[r["name"]] * int(r["n"]) for r in done])
    return out


def _bootstrap_auc(score, y_trials, objects, rng, reps=200) -> tuple[float, float]:
    """95% interval of the trial-level AUC, resampling objects."""
    names = np.unique(objects)
    vals = []
    for _ in range(reps):
        pick = rng.choice(names, len(names))
        idx = np.concatenate([np.flatnonzero(objects == o) for o in pick])
        s = np.repeat(score[idx], y_trials.shape[1])
        v = auc(s, y_trials[idx].reshape(-1))
        if np.isfinite(v):
            vals.append(v)
    return (float(np.percentile(vals, 2.5)), float(np.percentile(vals, 97.5))) if vals else (float("nan"),) * 2


def summarise(
    results: list[dict], out: str | Path | None = None, label_threshold: float = 0.002, success_threshold: float = 0.5
) -> dict:
    """AUC (trial level, against held in the evaluation trials), precision of positives,
    positivity and cost per grasp of every candidate label; pad-contact error; plots in
    ``out`` when given."""
    P = pooled(results)
    done = [r for r in results if r.get("status") == "done"]
    n = len(P["fc"])
    y = P["eval_held"]
    k = y.shape[1]
    rng = np.random.default_rng(0)
    cost_keys = {
        "paper (robust FC > 0.002, nominal collision)": ("fc", "collision"),
        "paper, fixed torque scaling": ("fc", "collision"),
        "robust FC x P(collision-free)": ("fc", "robust_collision"),
        "pad FC x nominal collision": ("pad", "collision"),
        "pad FC (fixed scaling) x P(cf)": ("pad", "robust_collision"),
        "P(collision-free) alone": ("robust_collision",),
        "robust pad FC (pads under noise)": ("robust_pad",),
        "robust pad FC x P(cf)": ("robust_pad", "robust_collision"),
        "physics (success rate of label trials)": ("physics_label", "physics_setup"),
    }
    tot = {}
    for r in done:
        for key, v in r["times"].items():
            tot[key] = tot.get(key, 0.0) + v
    rows = {}
    for name, (score, lab) in candidate_labels(P, label_threshold, success_threshold).items():
        s_t = np.repeat(score, k)
        a = auc(s_t, y.reshape(-1))
        lo, hi = _bootstrap_auc(score, y, P["object"], rng)
        fam_auc = {
            f: auc(np.repeat(score[P["family"] == f], k), y[P["family"] == f].reshape(-1))
            for f in np.unique(P["family"])
        }
        rows[name] = {
            "auc": a,
            "auc_ci95": [lo, hi],
            "auc_firm": auc(s_t, P["eval_firm"].reshape(-1)),
            "positivity": float(lab.mean()),
            "precision": float(y[lab].mean()) if lab.any() else float("nan"),
            "success_of_negatives": float(y[~lab].mean()) if (~lab).any() else float("nan"),
            "cost_ms_per_grasp": 1000.0 * sum(tot.get(c, 0.0) for c in cost_keys[name]) / n,
            "auc_by_family": fam_auc,
        }
    m_all = P["label_held"].shape[1]
    curve = {}
    for m in sorted({1, 2, 4, 8, m_all} & set(range(1, m_all + 1))):
        curve[m] = auc(np.repeat(P["label_held"][:, :m].mean(axis=1), k), y.reshape(-1))
    from .physics import REASONS

    reasons = np.bincount(P["eval_reason"].reshape(-1).astype(int), minlength=len(REASONS))

    # pad contacts vs the noise-free trial's first pad touches (both in the object frame)
    ft, pc, ac = P["first_touch"], P["pad_contacts"], P["contacts"]
    both = np.isfinite(ft).all(axis=(1, 2)) & P["pad_ok"].astype(bool)
    err_pad = np.linalg.norm(ft[both] - pc[both], axis=2).reshape(-1)
    err_line = np.linalg.norm(ft[both] - ac[both], axis=2).reshape(-1)
    ana_vs_pad = np.linalg.norm(pc[P["pad_ok"].astype(bool)] - ac[P["pad_ok"].astype(bool)], axis=2).max(axis=1)
    summary = {
        "objects": len(done),
        "skipped": [(r["name"], r.get("reason")) for r in results if r.get("status") != "done"],
        "grasps": n,
        "eval_trials_per_grasp": k,
        "label_trials_per_grasp": P["label_held"].shape[1],
        "families": {f: int((P["family"] == f).sum()) for f in np.unique(P["family"])},
        "eval_success_rate": float(y.mean()),
        "eval_outcomes": {REASONS[i]: int(c) for i, c in enumerate(reasons)},
        "candidates": rows,
        "physics_auc_by_label_trials": curve,
        "pad_contact_error_mm": {
            "pads_touched": int(both.sum()),
            "median_pad_model": 1000 * float(np.median(err_pad)),
            "median_grasp_line": 1000 * float(np.median(err_line)),
            "p90_pad_model": 1000 * float(np.percentile(err_pad, 90)),
        },
        "pad_vs_line_3mm_fraction": float((ana_vs_pad > 0.003).mean()) if len(ana_vs_pad) else float("nan"),
        "stage_ms_per_grasp": {key: 1000 * v / n for key, v in sorted(tot.items())},
        "unstable_poses": [r["name"] for r in done if not r["pose"]["stable"]],
    }
    if out is not None:
        _plots(Path(out), P, summary, label_threshold, err_pad, err_line, success_threshold)
    return summary


def _plots(
    out: Path, P: dict, summary: dict, label_threshold: float, err_pad, err_line, success_threshold: float = 0.5
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    y = P["eval_held"]
    k = y.shape[1]
    fig, ax = plt.subplots(figsize=(6.5, 5.5))
    for name, (score, _) in candidate_labels(P, label_threshold, success_threshold).items():
        fpr, tpr = roc_curve(np.repeat(score, k), y.reshape(-1))
        ax.plot(fpr, tpr, label=f"{name}: {summary['candidates'][name]['auc']:.2f}")
    ax.plot([0, 1], [0, 1], "k:", lw=1)
    ax.set_xlabel("false positive rate")
    ax.set_ylabel("true positive rate")
    ax.set_title("ROC vs held in noisy physics trials (trial level)")
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(out / "labels_roc.png", dpi=100)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 4))
    bins = np.linspace(0, 30, 31)
    ax.hist(1000 * err_line, bins=bins, histtype="step", lw=1.5, label="grasp-line contacts")
    ax.hist(1000 * err_pad, bins=bins, histtype="step", lw=1.5, label="pad contacts")
    ax.set_xlabel("distance to the simulated pads' first touch (mm)")
    ax.set_ylabel("contacts")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "labels_pad_contacts.png", dpi=100)
    plt.close(fig)

    fam = sorted(np.unique(P["family"]))
    names = list(summary["candidates"])
    fig, ax = plt.subplots(figsize=(9, 4))
    w = 0.8 / len(names)
    for i, nme in enumerate(names):
        vals = [summary["candidates"][nme]["auc_by_family"].get(f, np.nan) for f in fam]
        ax.bar(np.arange(len(fam)) + i * w, vals, w, label=nme)
    ax.set_xticks(np.arange(len(fam)) + 0.4 - w / 2)
    ax.set_xticklabels(fam, rotation=30, ha="right", fontsize=8)
    ax.axhline(0.8, color="k", ls="--", lw=1)
    ax.set_ylabel("AUC")
    ax.set_ylim(0.3, 1.0)
    ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(out / "labels_auc_by_family.png", dpi=100)
    plt.close(fig)


def markdown(summary: dict) -> str:
    """The candidates table (markdown) of a summary."""
    header = (
        "| label | AUC (95% CI, by object) | AUC vs firm | positives | precision of positives | "
        "success of negatives | cost per grasp (ms) |"
    )
    lines = [header, "|---|---|---|---|---|---|---|"]
    for name, v in summary["candidates"].items():
        lo, hi = v["auc_ci95"]
        lines.append(
            f"| {name} | {v['auc']:.2f} ({lo:.2f}-{hi:.2f}) | {v['auc_firm']:.2f} | "
            f"{100 * v['positivity']:.0f}% | {100 * v['precision']:.0f}% | "
            f"{100 * v['success_of_negatives']:.0f}% | {v['cost_ms_per_grasp']:.0f} |"
        )
    return "\n".join(lines) + "\n"


def write_report(out: str | Path, summary: dict) -> Path:
    """``<out>/summary.json`` and ``<out>/summary.md`` (atomic)."""
    p = Path(out) / "summary.json"
    atomic.write_bytes(p, json.dumps(summary, indent=2, default=float).encode())
    atomic.write_bytes(Path(out) / "summary.md", markdown(summary).encode())
    return p
