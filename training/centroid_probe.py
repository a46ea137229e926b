"""What the score misses: does a grasp's distance from the object's centre add to the model?

A lift holds an object against gravity, so a grasp far from the centre of mass must resist a
torque the 32 x 32 window may not show (a tall bottle held by its neck). This probe measures,
on a sampled dataset (``datagen sample``: its shards keep each image with its camera pose) and
its crops:

* per grasp, the horizontal distance (metres, world frame, z up from the table) of the grasp
  centre from the centroid of the object's points that the image sees, the grasp centre's height
  above the table and the visible top's height;
* how success and the model's "good" rate fall with that distance, per family;
* object-wise two-fold cross-validation of class-balanced logistic fits on the same rows: the
  score alone (a recalibration), the score with the geometry from the known camera pose, and the
  score with the same geometry estimated from the depth image alone (the planner's table plane and
  object regions: what a service could compute). The differences are what the geometry adds on
  objects the fit never saw.

``python -m training centroid-probe --sampled data/v2x/sampled_more --crops data/v2x/crops_more
--model-dir models/fast-vgqcnn-default``
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

from vgq.camera import Intrinsics, deproject

from . import metrics as M

#: points this high above the table (metres) belong to the object
OBJECT_MIN_HEIGHT_M = 0.003
#: horizontal offset bins of the report (metres)
OFFSET_BINS_M = (0.0, 0.01, 0.02, 0.04, 0.08, np.inf)


def visible_centroid(depth: np.ndarray, T_world_camera: np.ndarray, intr: Intrinsics) -> tuple[np.ndarray, float]:
    """World-frame centroid (3,) of the object's visible points in a depth image (H, W) (metres)
    and the highest visible point's height; (nan, nan) when the image shows no object."""
    from planning.cloud import backproject

    pts, valid = backproject(depth, intr)
    world = pts[valid].astype(np.float64) @ T_world_camera[:3, :3].T + T_world_camera[:3, 3]
    obj = world[world[:, 2] > OBJECT_MIN_HEIGHT_M]
    if len(obj) == 0:
        return np.full(3, np.nan), float("nan")
    return obj.mean(axis=0), float(obj[:, 2].max())


def grasp_centres(shard: dict, rows: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Camera-frame centres (n, 3) (metres) of the grasp ``rows`` of a sampled shard (its ``u``, ``v``, ``z``)."""
    return deproject(np.stack([shard["u"][rows], shard["v"][rows], shard["z"][rows]], axis=1), intr)


def grasp_offsets(shard: dict, rows: np.ndarray, intr: Intrinsics) -> dict[str, np.ndarray]:
    """For the grasp ``rows`` of a sampled shard (arrays ``depth``, ``T_world_camera``,
    ``image_index``, ``u``, ``v``, ``z``): ``offset`` (horizontal distance of the grasp centre from
    its image's visible centroid), ``height`` (grasp centre above the table) and ``top`` (the
    visible top's height), all (n,) metres."""
    images = np.asarray(shard["image_index"])[rows]
    cent = {int(i): visible_centroid(shard["depth"][i], shard["T_world_camera"][i], intr) for i in np.unique(images)}
    g = grasp_centres(shard, rows, intr)
    T = np.asarray(shard["T_world_camera"])[images]
    gw = np.einsum("nij,nj->ni", T[:, :3, :3], g) + T[:, :3, 3]
    c = np.stack([cent[int(i)][0] for i in images])
    return {
        "offset": np.linalg.norm(gw[:, :2] - c[:, :2], axis=1),
        "height": gw[:, 2],
        "top": np.array([cent[int(i)][1] for i in images]),
    }


def image_offsets(shard: dict, rows: np.ndarray, intr: Intrinsics, seed: int = 0) -> dict[str, np.ndarray]:
    """:func:`grasp_offsets` from the depth image alone, as a service could compute them: the table
    by the planner's RANSAC (``planning.sampler.find_table``), the largest object region's centre of
    mass guess (``planning.sampler.object_centres``), distances in the table plane; NaN where the
    image shows no table or no object."""
    from planning.cloud import backproject
    from planning.sampler import find_table, object_centres
    from planning.types import PlanParams

    params, rng = PlanParams(), np.random.default_rng(seed)
    images = np.asarray(shard["image_index"])[rows]
    g = grasp_centres(shard, rows, intr)
    out = {k: np.full(len(rows), np.nan) for k in ("offset", "height", "top")}
    for i in np.unique(images):
        pts, valid = backproject(np.asarray(shard["depth"][i], np.float64), intr)
        table = find_table(pts, valid, params, rng)
        if table is None:
            continue
        objects = valid & (table.height(pts) > params.object_height)
        labels, centres = object_centres(pts, objects, table)
        if len(centres) < 2:
            continue
        big = 1 + int(np.argmax(np.bincount(labels[labels > 0])[1:]))
        r = images == i
        d = centres[big] - g[r]
        d -= (d @ table.normal)[:, None] * table.normal
        out["offset"][r] = np.linalg.norm(d, axis=1)
        out["height"][r] = table.height(g[r])
        out["top"][r] = table.height(pts[labels == big]).max()
    return out


def fit_balanced_logistic(X: np.ndarray, y: np.ndarray, l2: float = 1e-3):
    """Logistic regression on standardised features with class-balanced weights; returns a function
    (m, d) -> (m,) bool (predicted positive)."""
    mu, sd = X.mean(axis=0), X.std(axis=0) + 1e-9
    Z = np.c_[(X - mu) / sd, np.ones(len(X))]
    y = np.asarray(y, dtype=np.float64)
    w = np.where(y > 0, 0.5 / y.mean(), 0.5 / (1 - y.mean()))

    def loss(b):
        t = Z @ b
        return (
            float(np.sum(w * (np.logaddexp(0, t) - y * t)) + l2 * b @ b),
            Z.T @ (w * (1 / (1 + np.exp(-t)) - y)) + 2 * l2 * b,
        )

    b = minimize(loss, np.zeros(Z.shape[1]), jac=True, method="L-BFGS-B").x
    return lambda X2: np.c_[(X2 - mu) / sd, np.ones(len(X2))] @ b > 0


def features(score: np.ndarray, geo: dict[str, np.ndarray] | None) -> np.ndarray:
    """(n, d) rows: the score's logit, and with ``geo`` the offset, height and top (cm) and log terms."""
    s = np.clip(np.asarray(score, np.float64), 1e-6, 1 - 1e-6)
    lg = np.log(s / (1 - s))
    if geo is None:
        return lg[:, None]
    off, h, top = (100 * geo[k] for k in ("offset", "height", "top"))
    return np.stack([lg, off, np.log1p(off), h, top, h / np.maximum(top, 1e-3), lg * np.log1p(off)], axis=1)


def placement_features(score: np.ndarray, place: np.ndarray) -> np.ndarray:
    """(n, d) rows: the score's logit, the placement rows (n, 7) (cm; ``known`` as is), the logit
    times each of them, and the terms :func:`features` adds (log offset, height over top)."""
    s = np.clip(np.asarray(score, np.float64), 1e-6, 1 - 1e-6)
    lg = np.log(s / (1 - s))
    p = np.asarray(place, np.float64) * np.array([1, 100, 100, 100, 100, 100, 100])
    off, h, top = p[:, 1], p[:, 5], p[:, 6]
    more = np.c_[np.log1p(np.maximum(off, 0)), h / np.maximum(top, 1e-1), lg * np.log1p(np.maximum(off, 0))]
    return np.c_[lg, p, lg[:, None] * p, more]


def object_cv(
    X: dict[str, np.ndarray], y: np.ndarray, object_id: np.ndarray, family: np.ndarray, repeats: int = 5
) -> dict[str, dict[str, float]]:
    """Mean balanced accuracy over ``repeats`` object-wise two-fold splits (objects halved within
    each family) of a balanced logistic fit per feature set ``X`` (name -> (n, d)): name -> family
    (and "all") -> fraction."""
    fams = sorted(set(family.tolist()))
    out: dict[str, dict[str, list]] = {k: {} for k in X}
    for rep in range(repeats):
        rng = np.random.default_rng(rep)
        half = {}
        for f in fams:
            objs = np.unique(object_id[family == f])
            rng.shuffle(objs)
            half.update({int(o): i % 2 for i, o in enumerate(objs)})
        fold = np.array([half[int(o)] for o in object_id])
        for name, Xs in X.items():
            pred = np.zeros(len(y), bool)
            for k in (0, 1):
                pred[fold == k] = fit_balanced_logistic(Xs[fold != k], y[fold != k])(Xs[fold == k])
            for f in ["all", *fams]:
                r = np.ones(len(y), bool) if f == "all" else family == f
                out[name].setdefault(f, []).append(M.from_confusion(M.confusion(y[r], pred[r]))["balanced_accuracy"])
    return {n: {f: float(np.mean(v)) for f, v in d.items()} for n, d in out.items()}


def probe(sampled: str | Path, crops: str | Path, model_dir: str | Path, per_object: int = 1500, seed: int = 0) -> dict:
    """Run the probe on the test split of ``crops`` (cut from ``sampled``, rows in shard order) with
    the exported model ``model_dir``: up to ``per_object`` random grasps of each object."""
    from datagen import storage
    from export.evaluate import raw_scores

    crops, sampled = Path(crops), Path(sampled)
    m = json.loads((crops / storage.MANIFEST).read_text())
    intr = Intrinsics(**m["intrinsics"])
    fam = {int(o["object_id"]): o.get("family") or "random_urdfs" for o in m["source"]["objects"]}
    arr = storage.open_crops(crops, "test")
    test_objects = set(np.unique(np.asarray(arr["object_id"])).tolist())
    rng = np.random.default_rng(seed)
    start, parts = 0, []
    for path in sorted((sampled / "shards").glob("*.npz")):
        with np.load(path) as z:
            if int(z["object_id"][0]) not in test_objects:
                continue
            shard = {k: z[k] for k in ("depth", "T_world_camera", "image_index", "u", "v", "z", "quality", "object_id")}
        n = len(shard["quality"])
        if not np.array_equal(shard["quality"], np.asarray(arr["quality"][start : start + n])):
            raise ValueError(f"{crops} test rows are not {sampled}'s shards in order (at {path.name})")
        take = np.sort(rng.choice(n, min(n, per_object), replace=False))
        parts.append((start + take, grasp_offsets(shard, take, intr), image_offsets(shard, take, intr, seed)))
        start += n
    if start != len(arr["quality"]):
        raise ValueError(f"{crops} test split has {len(arr['quality'])} rows; {sampled}'s test shards {start}")
    ix = np.concatenate([p[0] for p in parts])
    geo = {k: np.concatenate([p[1][k] for p in parts]) for k in ("offset", "height", "top")}
    seen = {k: np.concatenate([p[2][k] for p in parts]) for k in ("offset", "height", "top")}
    ok = np.isfinite(geo["offset"]) & np.isfinite(seen["offset"])
    ix, geo, seen = ix[ok], {k: v[ok] for k, v in geo.items()}, {k: v[ok] for k, v in seen.items()}
    y = np.asarray(arr["labels"][ix]).astype(bool)
    oid = np.asarray(arr["object_id"][ix])
    family = np.array([fam[int(o)] for o in oid])
    place = np.asarray(arr["placement"][ix], np.float32) if "placement" in arr else None
    score = raw_scores(
        model_dir, np.asarray(arr["images"][ix], np.float32), np.asarray(arr["poses"][ix], np.float32), placement=place
    )
    good = score > 0.5  # the threshold of training.metrics and export.evaluate
    bins = {}
    for f in np.unique(family):
        r = family == f
        rows = []
        for lo, hi in zip(OFFSET_BINS_M[:-1], OFFSET_BINS_M[1:]):
            b = r & (geo["offset"] >= lo) & (geo["offset"] < hi)
            if b.sum() >= 50:
                rows.append(
                    {
                        "offset_m": [lo, hi],
                        "n": int(b.sum()),
                        "success": float(y[b].mean()),
                        "good": float(good[b].mean()),
                    }
                )
        bins[str(f)] = rows
    X = {"score": features(score, None), "score_geometry": features(score, geo), "score_image": features(score, seen)}
    if place is not None:  # the placement rows a placement head reads (vgq.placement), with the score
        X["score_placement"] = placement_features(score, place)
    cv = object_cv(X, y, oid, family)
    raw = {"all": M.binary_metrics(y, score)["balanced_accuracy"]}
    raw.update({f: m["balanced_accuracy"] for f, m in M.metrics_by_group(y, score, family).items()})
    agree = float(np.corrcoef(geo["offset"], seen["offset"])[0, 1])
    return {
        "rows": int(len(y)),
        "dropped": int((~ok).sum()),
        "raw": raw,
        "cv": cv,
        "bins": bins,
        "offset_correlation": agree,
    }


def table(rec: dict) -> str:
    """The probe's result as a Markdown table (object-wise CV balanced accuracy) and offset bins."""
    cv = rec["cv"]
    arms = [k for k in ("score", "score_geometry", "score_image", "score_placement") if k in cv]
    lines = [
        "| family | score > 0.5 | score recalibrated | + offset, heights (camera pose known) | + offset, heights (image alone)"
        + (" | + placement rows |" if "score_placement" in cv else " |"),
        "|---|---:" + "|---:" * len(arms) + "|",
    ]
    for f, v in rec["raw"].items():
        cells = " | ".join(f"{100 * cv[k][f]:.1f}%" for k in arms)
        lines.append(f"| {f} | {100 * v:.1f}% | {cells} |")
    lines.append(
        f"\n{rec['rows']} grasps ({rec['dropped']} dropped: no object or table found); the two offsets correlate "
        f"{rec['offset_correlation']:.3f}\nsuccess / scored good (> 0.5) by horizontal offset from the visible centroid:"
    )
    for f, rows in rec["bins"].items():
        cells = ", ".join(
            f"{100 * r['offset_m'][0]:.0f}-{100 * r['offset_m'][1]:.0f} cm {r['success']:.2f} / {r['good']:.2f}"
            for r in rows
        )
        lines.append(f"  {f}: {cells}".replace("-inf cm", "+ cm"))
    return "\n".join(lines)
