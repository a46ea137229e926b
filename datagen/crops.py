"""Crop stage (SPEC section 5): turn a grasp dataset into the training-ready ``vgq-crops``
dataset for one architecture. All crop arithmetic is :mod:`vgq.crop` (shared with the
service); this module only chooses the windows.

* ``fast_vgqcnn``: per grasp, a window whose centre lies within +/- kappa source px (per
  axis, uniformly over the integer window positions) of the grasp; pose (u, v) = the grasp's
  offset from the window centre in crop px (``vgq.crop.pose_uv``).
* ``vgqcnn``: window centred on the grasp (nearest integer window), pose u = v = 0.
* ``gqcnn``: ``vgq.crop.rotated_crop`` about the grasp by its ``jaw_angle``, u = v = 0.

Before cropping, each rendered depth image passes through the depth-sensor model
(:mod:`datagen.sensor`, the ``sensor`` setting: a preset such as ``clean`` or ``realistic``,
seeded per image by (seed, object id, image row)). Missing pixels are then filled by the
shared contract (:mod:`vgq.inpaint`): the window plus a margin for ``fast_vgqcnn`` and
``vgqcnn``, exactly as the service fills an upload; the whole image for ``gqcnn`` (which the
service does not serve). Each grasp also gets its placement row (:mod:`vgq.placement`: where it
sits on its object, from the corrupted image, by the function the service calls).
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from planning.placement import placement_rows
from vgq import atomic, inpaint
from vgq import crop as vcrop
from vgq import turns as vturns
from vgq.camera import DEFAULT_INTRINSICS, Intrinsics
from vgq.pose import canonical_quaternion, roll_quaternions
from vgq.schema import (
    CROP_EXTRA_FIELDS,
    PLACEMENT_GRASP_DEPTH,
    SPLITS,
    WRITTEN_CROP_FIELDS,
    crop_counts,
    write_crop_manifest,
)

from . import sensor as sensor_model
from . import storage
from .sampling import SamplingParams, split_objects, split_population

ARCHS = ("fast_vgqcnn", "vgqcnn", "gqcnn")
DEFAULT_KAPPA_PX = 36.0  # the authors' default for the 96 px window (12 px at 32 x 32)


def geometry_for(
    arch: str,
    kappa_px: float | None = None,
    window: int = 96,
    out: int = 32,
    align_jaw: bool = False,
    jaw_turns: int = 0,
) -> vcrop.CropGeometry:
    """Crop geometry of ``arch``: a ``window`` x ``window`` source px window resized to ``out``;
    Fast-VGQ-CNN uses ``kappa_px`` (default 36 px for the 96 px window, in proportion for
    another), the centred architectures kappa 0 (a non-zero kappa for them is an error).
    ``align_jaw`` (VGQ-CNN only): crops turned so the jaw axis is horizontal, the pose with them.
    ``jaw_turns`` (Fast-VGQ-CNN only): windows cut from the image turned in K steps of pi / K
    (:mod:`vgq.turns`)."""
    if arch not in ARCHS:
        raise ValueError(f"unknown architecture {arch!r}; expected one of {', '.join(ARCHS)}")
    if align_jaw and arch != "vgqcnn":
        raise ValueError(f"align_jaw applies to vgqcnn crops only, not {arch}")
    if jaw_turns and arch != "fast_vgqcnn":
        raise ValueError(f"jaw_turns applies to fast_vgqcnn crops only, not {arch}")
    if arch == "fast_vgqcnn":
        k = DEFAULT_KAPPA_PX * window / 96 if kappa_px is None else float(kappa_px)
    else:
        if kappa_px not in (None, 0, 0.0):
            raise ValueError(f"kappa applies to fast_vgqcnn only; {arch} crops are centred (got kappa {kappa_px})")
        k = 0.0
    if not np.isfinite(k):
        raise ValueError(f"kappa must be finite, got {k}")
    return vcrop.CropGeometry(window=window, out=out, kappa_px=k, align_jaw=bool(align_jaw), jaw_turns=jaw_turns)


def fast_window_origins(grasp_uv: np.ndarray, geom: vcrop.CropGeometry, rng: np.random.Generator) -> np.ndarray:
    """Integer window origins (n, 2) whose centres lie within +/- ``geom.kappa_px`` (per axis)
    of ``grasp_uv`` (n, 2), drawn uniformly among the valid positions. Where none is valid
    (kappa < 0.5 px and a fractional grasp pixel) the nearest window is used."""
    g = np.asarray(grasp_uv, dtype=np.float64).reshape(-1, 2)
    lo, hi = vcrop.origin_range(g, geom)
    span = hi - lo + 1
    draw = lo + np.floor(rng.random(g.shape) * np.maximum(span, 1))
    nearest = vcrop.window_origin(g, geom).astype(np.float64)
    return np.where(span >= 1, draw, nearest).astype(np.int64)


def crop_grasps(
    depth: np.ndarray,
    uv: np.ndarray,
    jaw_angle: np.ndarray,
    arch: str,
    geom: vcrop.CropGeometry,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """Crops of one depth image (H, W) metres (0 or non-finite = missing, filled by
    :mod:`vgq.inpaint`) for k grasps at ``uv`` (k, 2) image px.

    Returns (images (k, out, out) float32, pose (u, v) (k, 2) in crop px, fraction of
    missing pixels in each window (k,))."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    k = len(uv)
    images = np.empty((k, geom.out, geom.out), dtype=np.float32)
    pose_uv = np.zeros((k, 2), dtype=np.float64)
    missing = np.zeros(k, dtype=np.float64)
    if arch == "fast_vgqcnn":
        origins = fast_window_origins(uv, geom, rng)
        for i in range(k):
            images[i], c, missing[i] = inpaint.crop_filled(depth, origins[i], geom)
            pose_uv[i] = vcrop.pose_uv(uv[i], c, geom)
    elif arch == "vgqcnn" and not geom.align_jaw:
        origins = vcrop.window_origin(uv, geom)
        for i in range(k):
            images[i], _, missing[i] = inpaint.crop_filled(depth, origins[i], geom)
    elif arch in ("gqcnn", "vgqcnn"):  # turned about the grasp: the jaw axis horizontal
        miss = inpaint.missing_mask(depth)
        filled = inpaint.fill_nearest(depth, miss) if miss.any() else depth
        for i in range(k):
            images[i] = vcrop.rotated_crop(filled, uv[i], float(jaw_angle[i]), geom)
            missing[i] = vcrop.crop_window(miss.astype(np.float32), vcrop.window_origin(uv[i], geom), geom).mean()
    else:
        raise ValueError(f"unknown architecture {arch!r}")
    return images, pose_uv, missing


def turned_crops(
    depth: np.ndarray,
    uv: np.ndarray,
    z: np.ndarray,
    q: np.ndarray,
    geom: vcrop.CropGeometry,
    intr: Intrinsics,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Fast-VGQ-CNN crops of k grasps (TCP pixel ``uv`` (k, 2), depth ``z`` (k,) metres, unit
    quaternions ``q`` (k, 4) (w, x, y, z), camera ``intr``) from the depth image (H, W) turned,
    per grasp, by its turn of ``geom.jaw_turns`` (:mod:`vgq.turns`; the camera rolled, the image
    on a canvas that holds it whole, as the service turns an upload).

    Returns (images (k, out, out), pose (u, v) (k, 2) crop px in the turned image, missing
    fraction (k,), quaternions (k, 4) in the turned camera's frame, canonical)."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    k, turns = len(uv), geom.jaw_turns
    images = np.empty((k, geom.out, geom.out), dtype=np.float32)
    pose_uv = np.zeros((k, 2), dtype=np.float64)
    missing = np.zeros(k, dtype=np.float64)
    q_out = np.empty((k, 4), dtype=np.float64)
    index = vturns.turn_index(vturns.pose_jaw_angles(uv, z, q, intr), turns)
    for t in np.unique(index):
        sel = index == t
        d_t, intr_t, roll = vturns.turned_view(depth, intr, int(t), turns)
        uv_t, q_out[sel] = vturns.turned_poses(uv[sel], np.asarray(q, dtype=np.float64)[sel], intr, intr_t, roll)
        images[sel], pose_uv[sel], missing[sel] = crop_grasps(d_t, uv_t, None, "fast_vgqcnn", geom, rng)
    return images, pose_uv, missing, q_out


JOB_FILE = ".crops-job.json"  # an unfinished run's inputs (deleted when the manifest is written)
DONE_FILE = ".crops-done.jsonl"  # its finished objects, one JSON line each, written after their rows
SAVE_EVERY_S = 30.0  # how often an unfinished run records its progress (what a stop can lose)

_OPEN: dict[str, storage.GraspDataset] = {}  # per process: folder -> opened dataset (workers read it once)


def crop_object(
    src: str,
    entry: dict,
    arch: str,
    geom: vcrop.CropGeometry,
    sensor,
    seed: int,
    intr: Intrinsics,
    thr: float,
    context_scale: int = 0,
) -> dict:
    """The WRITTEN_CROP_FIELDS rows (in image order) of one shard ``entry`` of the grasp dataset ``src``
    (and with ``context_scale`` each window's context view, field ``context``), plus ``missing`` (the
    summed missing fraction of its windows). Seeded by (seed, object id) and the sensor model's
    per-image seeds, so it is the same in any process and any order."""
    if src not in _OPEN:  # one manifest read per process, not per object
        _OPEN[src] = storage.open_dataset(src)
    sh = _OPEN[src].load(entry)
    g, im = sh.grasps, sh.images
    n = len(g["u"])
    fields = {**WRITTEN_CROP_FIELDS, **({"context": CROP_EXTRA_FIELDS["context"]} if context_scale else {})}
    out = {k: np.empty((n, *shape), dtype) for k, (dtype, shape, _) in fields.items()}
    ctx = vcrop.context_geometry(geom, context_scale) if context_scale else None
    rng = np.random.default_rng([seed, sh.object_id])
    order = np.argsort(g["image_index"], kind="stable")
    bounds = np.flatnonzero(np.diff(g["image_index"][order])) + 1
    missing, fill = 0.0, 0
    for rows in np.split(order, bounds) if len(order) else []:
        img_i = int(g["image_index"][rows[0]])
        uv = np.stack([g["u"][rows], g["v"][rows]], axis=1)
        depth, scale = sensor.read(im["depth"][img_i], sensor_model.image_rng(seed, sh.object_id, img_i), intr)
        q = g["q"][rows]
        # the grasps' places on their object, from the image as the sensor gives it, each grasp at the
        # depth this image shows it (the sensor's scale error applied), as a client reads its grasps off
        # the image it uploads: with the true depth against a scaled image the rows lose most of what
        # they carry (docs/training.md, "The placement rows' skew")
        place = placement_rows(depth, intr, np.stack([uv[:, 0], uv[:, 1], scale * g["z"][rows]], 1), q)
        if geom.jaw_turns:  # windows of the image turned in steps towards each jaw axis
            crops, puv, miss, q = turned_crops(depth, uv, g["z"][rows], q, geom, intr, rng)
        else:
            crops, puv, miss = crop_grasps(depth, uv, g["jaw_angle"][rows], arch, geom, rng)
        if geom.align_jaw:  # the orientation seen by the camera turned with the crop
            q = canonical_quaternion(roll_quaternions(q, g["jaw_angle"][rows]))
        missing += float(miss.sum())
        dst = slice(fill, fill + len(rows))
        if ctx is not None:  # each window's context view, from the image filled once
            origins = vcrop.window_origin(uv - puv * geom.scale, geom)  # from the windows' centres
            out["context"][dst] = vcrop.context_crops(inpaint.fill_nearest(depth), origins, geom, ctx)
        out["images"][dst] = crops
        out["poses"][dst] = np.concatenate([puv, g["z"][rows, None], q], axis=1)
        out["labels"][dst] = g["quality"][rows] > thr
        out["quality"][dst] = g["quality"][rows]
        out["object_id"][dst] = sh.object_id
        out["camera_d"][dst] = im["camera_d"][img_i]
        out["camera_phi"][dst] = im["camera_phi"][img_i]
        out["beta"][dst] = g["beta"][rows]
        out["psi"][dst] = g["psi"][rows]
        out["placement"][dst] = place
        fill += len(rows)
    return {"object_id": sh.object_id, "rows": out, "missing": missing}


def make_crops(
    src: str | Path,
    out: str | Path,
    arch: str,
    kappa_px: float | None = None,
    seed: int = 0,
    log: Callable[[str], None] = print,
    progress: bool = False,
    sensor: str | sensor_model.SensorModel | dict | None = None,
    sensor_overrides: dict | None = None,
    splits: tuple[str, ...] = SPLITS,
    workers: int = 1,
    window: int = 96,
    align_jaw: bool = False,
    jaw_turns: int = 0,
    context_scale: int = 0,
) -> dict:
    """Crop every grasp of the grasp dataset ``src`` into the ``vgq-crops`` dataset ``out``.

    The split comes from ``src``'s manifest (``datagen sample``); a dataset without one is
    split object-wise here (80/10/10, by ``seed``). ``sensor``: the depth-sensor model (a
    preset name, a .json file, a dict or a SensorModel; default ``realistic``), with
    ``sensor_overrides`` (field -> value). ``splits``: the splits to crop (the others are
    written empty), e.g. ``("test",)`` for a second, differently corrupted copy of the test
    split. ``workers``: processes cropping objects in parallel (the result does not depend on
    it). ``window``: source px a side of each crop window (resized to 32 x 32). ``align_jaw``
    (vgqcnn): crops turned so each grasp's jaw axis is horizontal, poses with them
    (``vgq.crop.CropGeometry.align_jaw``). ``jaw_turns`` (fast_vgqcnn): windows cut from the image
    turned in that many steps towards each jaw axis (``vgq.turns``). ``context_scale`` (fast_vgqcnn,
    unturned): also each window's context view, ``context_scale`` windows wide (field ``context``,
    :func:`vgq.crop.context_crops`). Returns the written manifest."""
    geom = geometry_for(arch, kappa_px, window=window, align_jaw=align_jaw, jaw_turns=jaw_turns)
    if context_scale:
        vcrop.context_geometry(geom, context_scale)  # the scale checked
        if arch != "fast_vgqcnn" or geom.jaw_turns:
            raise ValueError(f"context views are cut for unturned fast_vgqcnn windows, not {arch} ({geom.turning()})")
    bad = sorted(set(splits) - set(SPLITS))
    if bad or not splits:
        raise ValueError(f"splits must be a non-empty subset of {SPLITS}, got {tuple(splits)}")
    sensor_name, sensor = sensor_model.resolve(sensor, sensor_overrides)
    out = Path(out)
    if (out / storage.MANIFEST).exists():
        raise FileExistsError(f"output folder {out} already holds a dataset; choose a new --out")
    ds = storage.open_dataset(src)
    m_src = ds.manifest
    if "splits" in m_src:
        split_of = {int(i): s for s in SPLITS for i in m_src["splits"].get(s, [])}
        split_note = "from the source dataset"
    else:
        population = split_population(m_src, ds.object_ids)  # a derived dataset: its source's objects
        split_of = split_objects(population, SamplingParams().split_fractions, seed)
        split_of = {i: split_of[i] for i in ds.object_ids}
        split_note = f"object-wise 80/10/10 computed by datagen crops (seed {seed})"
    missing = [e["object_id"] for e in ds.shard_entries if e["object_id"] not in split_of]
    if missing:
        raise storage.DatasetError(f"{ds.root / storage.MANIFEST}: objects {missing[:5]} have no split")
    n = {
        s: sum(e["num_grasps"] for e in ds.shard_entries if split_of[e["object_id"]] == s) if s in splits else 0
        for s in SPLITS
    }
    entries = [e for e in ds.shard_entries if split_of[e["object_id"]] in splits]
    intr_d = m_src.get("intrinsics") or m_src.get("config", {}).get("intrinsics")
    intr = Intrinsics.from_dict(intr_d) if intr_d else DEFAULT_INTRINSICS
    thr = ds.label_threshold
    job = {  # what the rows depend on: a stopped run resumes only into the same job
        "source_manifest_sha256": hashlib.sha256((ds.root / storage.MANIFEST).read_bytes()).hexdigest(),
        "arch": arch,
        "geometry": geom.to_dict(),
        "seed": int(seed),
        "sensor": sensor.to_dict(),
        "splits": list(splits),
        "rows": n,
        "label_threshold": thr,
        "intrinsics": intr.to_dict(),
        **({"context_scale": int(context_scale)} if context_scale else {}),
    }
    job = json.loads(json.dumps(job))  # as it reads back from the job file
    done = _resume_state(out, job, n, log)
    if not done:
        _clear_leftovers(out)
        atomic.write_json(out / JOB_FILE, job)
    extra = ("context",) if context_scale else ()
    writers = {s: storage.crop_writers(out, s, n[s], partial=True, resume=bool(done), extra=extra) for s in SPLITS}
    pos = {s: 0 for s in SPLITS}
    written = {s: 0 for s in SPLITS}
    missing_sum = {s: 0.0 for s in SPLITS}
    for r in done.values():
        pos[r["split"]] += r["positives"]
        written[r["split"]] += r["rows"]
        missing_sum[r["split"]] += r["missing"]
    # each object's rows start where the previous object's (in id order) of its split end
    start, fill = {}, {s: 0 for s in SPLITS}
    for e in entries:
        s = split_of[e["object_id"]]
        start[e["object_id"]] = fill[s]
        fill[s] += e["num_grasps"]
    pending: list[dict] = []
    last_save = [time.monotonic()]

    def save_progress() -> None:
        """Flush the memory maps, then record the objects whose rows they now hold."""
        for ws in writers.values():
            for wr in ws.values():
                wr.flush()
        if pending:
            with open(out / DONE_FILE, "a") as f:
                f.write("".join(json.dumps(r) + "\n" for r in pending))
                f.flush()
                os.fsync(f.fileno())
            pending.clear()
        last_save[0] = time.monotonic()

    def write(r: dict) -> None:
        s = split_of[r["object_id"]]
        rows = r["rows"]
        dst = slice(start[r["object_id"]], start[r["object_id"]] + len(rows["labels"]))
        for k, a in rows.items():
            writers[s][k].array[dst] = a
        npos = int(rows["labels"].sum())
        pos[s] += npos
        written[s] += len(rows["labels"])
        missing_sum[s] += r["missing"]
        pending.append(
            {
                "object_id": r["object_id"],
                "split": s,
                "rows": len(rows["labels"]),
                "positives": npos,
                "missing": r["missing"],
            }
        )
        if time.monotonic() - last_save[0] > SAVE_EVERY_S:
            save_progress()

    from .parallel import run_tasks

    _OPEN[str(ds.root)] = ds  # this run's manifest, not one cached from an earlier run on the same folder
    todo = [e for e in entries if e["object_id"] not in done]
    tasks = [(str(ds.root), e, arch, geom, sensor, seed, intr, thr, context_scale) for e in todo]
    try:
        run_tasks(crop_object, tasks, workers=workers, on_result=write, progress=progress, desc=f"crops {arch}")
    finally:  # an interrupted run keeps what it cropped: rerunning the same command resumes
        save_progress()
    for s in SPLITS:
        if written[s] != n[s]:
            raise storage.DatasetError(f"{src}: split {s} filled {written[s]} rows, manifest counts {n[s]}")
        for wr in writers[s].values():
            wr.close()
    counts = {
        s: crop_counts(
            n[s],
            pos[s],
            missing_fraction_mean=missing_sum[s] / n[s] if n[s] else 0.0,
            objects=sorted(i for i, v in split_of.items() if v == s and s in splits),
        )
        for s in SPLITS
    }
    cfg = m_src.get("config", {})
    native = m_src.get("sampling", {}).get("stats", {}).get("steps", {}).get("native")  # before sampling
    m = write_crop_manifest(
        out,
        arch,
        geom,
        counts,
        thr,
        source={
            "dataset": str(Path(src).resolve()),
            "seed": m_src.get("seed"),
            "config": cfg,
            "sampling": m_src.get("sampling", {}).get("params"),
            "split": split_note,
            "objects": [
                {"object_id": o["object_id"], "name": o.get("name"), "family": o.get("family")}
                for o in m_src["objects"]
            ],
            "splits": list(splits),
        },
        intrinsics=intr_d,
        native_counts=crop_counts(native["grasps"], native["positive"]) if native else None,
        seed=int(seed),
        sensor={"name": sensor_name, "params": sensor.to_dict()},
        inpaint={"method": "nearest valid pixel (OpenCV distance transform, 5x5 mask)", "margin_px": inpaint.MARGIN_PX},
        context_scale=context_scale,
        placement_grasp_depth=PLACEMENT_GRASP_DEPTH,
        versions=storage.library_versions(),
    )
    for f in (DONE_FILE, JOB_FILE):  # complete: nothing left to resume
        (out / f).unlink(missing_ok=True)
    for s in splits:
        log(
            f"{s}: {n[s]} crops, positivity {100 * counts[s]['positivity']:.1f}%, "
            f"missing pixels {100 * counts[s]['missing_fraction_mean']:.2f}% (sensor {sensor_name})"
        )
    return m


def _resume_state(out: Path, job: dict, n: dict, log: Callable[[str], None]) -> dict[int, dict]:
    """The finished objects (id -> progress record) of a stopped run of the same ``job`` in
    ``out``; empty when there is none to resume. A stopped run of a different job is an error."""
    try:
        old = json.loads((out / JOB_FILE).read_text())
    except FileNotFoundError:
        return {}
    except ValueError:
        old = None
    if old != job:
        raise storage.DatasetError(
            f"{out} holds an unfinished crop run with other inputs (source, architecture, seed, sensor or splits); "
            f"delete the folder or choose a new --out"
        )
    parts = [out / s / f".{k}.npy.partial" for s in SPLITS if n[s] for k in WRITTEN_CROP_FIELDS]
    if not all(p.is_file() for p in parts):
        log(f"{out}: the unfinished run's files are incomplete; starting over")
        return {}
    done = {}
    try:
        lines = (out / DONE_FILE).read_text().splitlines()
    except FileNotFoundError:
        lines = []
    for line in lines:
        try:
            r = json.loads(line)
        except ValueError:  # a line cut by the stop: that object is cropped again
            continue
        done[int(r["object_id"])] = r
    log(f"{out}: resuming an unfinished run, {len(done)} objects already cropped")
    return done


def _clear_leftovers(out: Path) -> None:
    """Remove the temporary files of earlier unfinished runs in ``out`` (they can be gigabytes)."""
    for s in SPLITS:
        for k in WRITTEN_CROP_FIELDS:
            for p in (out / s).glob(f".{k}.npy.*"):
                p.unlink()
    (out / DONE_FILE).unlink(missing_ok=True)
