"""Dataset sampling (SPEC section 3): psi filter, positivity equalisation over beta bins,
uniform undersampling over (phi, beta) bins, object-wise train / val / test split.

Pure numpy functions on per-grasp arrays (angles in radians, positivity rates in percent),
and :func:`sample_dataset`, which applies them to a ``vgq-grasps`` dataset and writes the
sampled dataset (same format, with the split recorded in its manifest).
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from vgq.schema import SPLITS

from . import storage
from .parallel import run_tasks


@dataclass(frozen=True)
class SamplingParams:
    """Sampling settings. Angles in radians, ``target_positivity`` in percent."""

    max_psi: float = math.pi / 2  # drop grasps with psi >= this (approach from behind the object)
    target_positivity: float = 19.0  # VG-dset: the rate of Dex-Net 2.0
    beta_bin: float = math.radians(5.0)  # bin width for positivity equalisation and uniform sampling
    phi_bin: float = math.radians(5.0)  # bin width over camera elevation for uniform sampling
    uniform: bool = True  # undersample to a uniform count over (phi, beta) bins
    uniform_quantile: float = 0.0  # per-bin cap = this quantile of non-empty bin counts (0: the smallest bin)
    split_fractions: tuple[float, float, float] = (0.8, 0.1, 0.1)  # train / val / test, object-wise per family
    holdout_families: tuple[str, ...] = ()  # families whose objects all go to test (leave-family-out)
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0 < self.max_psi <= math.pi:
            raise ValueError(f"max_psi must be in (0, pi] radians, got {self.max_psi}")
        if not 0 < self.target_positivity < 100:
            raise ValueError(f"target_positivity must be a percentage in (0, 100), got {self.target_positivity}")
        if not self.beta_bin > 0 or not self.phi_bin > 0:
            raise ValueError(f"beta_bin and phi_bin must be > 0 radians, got {self.beta_bin}, {self.phi_bin}")
        if not 0 <= self.uniform_quantile <= 1:
            raise ValueError(f"uniform_quantile must be in [0, 1], got {self.uniform_quantile}")
        f = tuple(self.split_fractions)
        if len(f) != 3 or any(x < 0 for x in f) or abs(sum(f) - 1) > 1e-6 or f[0] == 0:
            raise ValueError(f"split_fractions must be 3 non-negative numbers summing to 1 with train > 0, got {f}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        if not all(isinstance(f, str) and f for f in self.holdout_families):
            raise ValueError(f"holdout_families must be family names, got {self.holdout_families!r}")


# ----------------------------------------------------------------------------- pure functions


def angle_bins(angle: np.ndarray, width: float) -> np.ndarray:
    """Bin index floor(angle / width) (int64, >= 0) of angles in radians."""
    return np.maximum(np.floor(np.asarray(angle, dtype=np.float64) / width + 1e-9), 0).astype(np.int64)


def psi_mask(psi: np.ndarray, max_psi: float) -> np.ndarray:
    """Keep grasps with psi < max_psi (SPEC 3.1)."""
    return np.asarray(psi) < max_psi


def positivity_by_bin(labels: np.ndarray, bins: np.ndarray, n_bins: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per bin: (count, positives, positivity rate in percent; NaN for empty bins)."""
    labels = np.asarray(labels, dtype=bool)
    n = np.bincount(bins, minlength=n_bins)[:n_bins]
    pos = np.bincount(bins, weights=labels, minlength=n_bins)[:n_bins].astype(np.int64)
    with np.errstate(divide="ignore", invalid="ignore"):
        rate = np.where(n > 0, 100.0 * pos / np.maximum(n, 1), np.nan)
    return n, pos, rate


def sample_rates(pos_rate: np.ndarray, target: float) -> tuple[np.ndarray, np.ndarray]:
    """The paper's sampling rates for a bin of positivity ``pos_rate`` (percent), target ``target``:
    ``rate_neg = (100 / t * p - p) / (100 - p)``, ``rate_pos = 1 / rate_neg``, each capped at 1.

    A bin without positives gets rate_neg = 0 (the target cannot be reached by dropping
    negatives); an all-positive bin gets rate_pos = 0. Empty bins (NaN) get 1."""
    p = np.asarray(pos_rate, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        neg = np.where(p >= 100.0, np.inf, (100.0 / target * p - p) / (100.0 - p))
        pos = np.where(neg > 0, 1.0 / neg, np.inf)
    neg = np.where(np.isnan(p), 1.0, np.minimum(neg, 1.0))
    pos = np.where(np.isnan(p), 1.0, np.minimum(pos, 1.0))
    return neg, pos


def equalise_positivity(
    labels: np.ndarray, beta: np.ndarray, params: SamplingParams, rng: np.random.Generator
) -> np.ndarray:
    """Keep mask (SPEC 3.2): each grasp survives with its beta bin's rate for its label."""
    labels = np.asarray(labels, dtype=bool)
    bins = angle_bins(beta, params.beta_bin)
    n_bins = int(bins.max()) + 1 if len(bins) else 1
    _, _, rate = positivity_by_bin(labels, bins, n_bins)
    r_neg, r_pos = sample_rates(rate, params.target_positivity)
    keep_p = np.where(labels, r_pos[bins], r_neg[bins])
    return rng.random(len(labels)) < keep_p


def uniform_over_bins(
    phi: np.ndarray, beta: np.ndarray, params: SamplingParams, rng: np.random.Generator
) -> np.ndarray:
    """Keep mask (SPEC 3.3): at most ``cap`` random grasps per joint (phi, beta) bin, with
    ``cap`` the ``uniform_quantile`` of the non-empty bin counts (0 -> the smallest bin)."""
    n = len(phi)
    keep = np.zeros(n, dtype=bool)
    if n == 0:
        return keep
    pb = angle_bins(phi, params.phi_bin)
    bb = angle_bins(beta, params.beta_bin)
    key = pb * (int(bb.max()) + 1) + bb
    counts = np.bincount(key)
    cap = int(np.floor(np.quantile(counts[counts > 0], params.uniform_quantile)))
    perm = rng.permutation(n)
    k = key[perm]
    order = np.argsort(k, kind="stable")
    ks = k[order]
    starts = np.searchsorted(ks, ks, side="left")
    rank = np.arange(n) - starts
    keep[perm[order[rank < cap]]] = True
    return keep


def split_objects(object_ids, fractions=(0.8, 0.1, 0.1), seed: int = 0) -> dict[int, str]:
    """Object-wise split: object id -> "train" | "val" | "test", deterministic by ``seed``
    (a seeded permutation of the sorted ids). With 3 or more objects, every split whose
    fraction is > 0 gets at least one object."""
    ids = np.array(sorted(set(int(i) for i in object_ids)), dtype=np.int64)
    n = len(ids)
    perm = np.random.default_rng(seed).permutation(ids)
    n_val = int(round(fractions[1] * n))
    n_test = int(round(fractions[2] * n))
    if n >= 3:
        n_val = max(n_val, 1 if fractions[1] > 0 else 0)
        n_test = max(n_test, 1 if fractions[2] > 0 else 0)
    n_val = min(n_val, max(n - 1, 0))
    n_test = min(n_test, max(n - 1 - n_val, 0))
    n_train = n - n_val - n_test
    out = {}
    for i, oid in enumerate(perm):
        out[int(oid)] = "train" if i < n_train else ("val" if i < n_train + n_val else "test")
    return out


def split_by_family(
    object_ids, families: dict[int, str], fractions=(0.8, 0.1, 0.1), seed: int = 0, holdout: tuple[str, ...] = ()
) -> dict[int, str]:
    """Object-wise split within every family: object id -> "train" | "val" | "test".

    ``families``: object id -> family name (ids without one form one unnamed family).
    Each family is split by :func:`split_objects` with its own seed derived from (seed,
    family), so a family of 3 or more objects has objects in every split whose fraction is
    > 0; families in ``holdout`` go wholly to test. With a single family and no holdout this
    is exactly :func:`split_objects` (the behaviour before families). Raises ValueError for
    a holdout family that has no object."""
    groups: dict[str, list[int]] = {}
    for i in sorted(set(int(i) for i in object_ids)):
        groups.setdefault(families.get(i) or "", []).append(i)
    missing = sorted(set(holdout) - set(groups))
    if missing:
        raise ValueError(
            f"holdout family {missing[0]!r} has no object in the dataset (has: {', '.join(sorted(groups))})"
        )
    if len(groups) <= 1 and not holdout:
        return split_objects(object_ids, fractions, seed)
    out: dict[int, str] = {}
    for fam, ids in sorted(groups.items()):
        if fam in holdout:
            out.update({i: "test" for i in ids})
        else:
            out.update(split_objects(ids, fractions, _family_seed(seed, fam)))
    return out


def _family_seed(seed: int, family: str) -> int:
    return int.from_bytes(hashlib.sha256(f"vgq-split:{int(seed)}:{family}".encode()).digest()[:8], "little")


def split_population(manifest: dict, object_ids) -> list[int]:
    """The object ids an object-wise split is drawn over: the manifest's ``split_object_ids`` when
    it records them (a dataset derived from another one, e.g. by ``datagen planner-grasps``, whose
    objects must land in the splits they have in the source), else ``object_ids`` (the dataset's
    own shards). Raises ValueError when the dataset holds an object outside the recorded ones."""
    ids = [int(i) for i in object_ids]
    if "split_object_ids" not in manifest:
        return ids
    population = [int(i) for i in manifest["split_object_ids"]]
    extra = sorted(set(ids) - set(population))
    if extra:
        raise ValueError(f"objects {extra[:5]} have shards but are not among the manifest's split_object_ids")
    return population


def split_table(split: dict[int, str], families: dict[int, str]) -> dict[str, dict[str, int]]:
    """Objects per split within each family: {family: {split: count}}."""
    out: dict[str, dict[str, int]] = {}
    for i, sp in sorted(split.items()):
        row = out.setdefault(families.get(i) or "", {s: 0 for s in SPLITS})
        row[sp] += 1
    return out


# ----------------------------------------------------------------------------- dataset stage


@dataclass
class GraspTable:
    """Per-grasp columns of a whole grasp dataset (rows in shard order, then row order)."""

    object_id: np.ndarray
    row: np.ndarray  # row within its shard
    beta: np.ndarray
    psi: np.ndarray
    phi: np.ndarray  # camera elevation of the grasp's image
    label: np.ndarray


def _table_rows(path: str, sha256: str | None, object_id: int, label_threshold: float) -> tuple[int, dict]:
    """One shard's rows of the grasp table (a worker task: loads and checks the shard, its depth
    images left compressed)."""
    images, g = storage.read_shard(path, sha256, skip=("depth",))
    n = len(g["grasp_id"])
    return object_id, {
        "object_id": np.full(n, object_id, dtype=np.int64),
        "row": np.arange(n, dtype=np.int64),
        "beta": g["beta"].astype(np.float64),
        "psi": g["psi"].astype(np.float64),
        "phi": images["camera_phi"][g["image_index"]].astype(np.float64),
        "label": g["quality"] > label_threshold,
    }


def _shard_tasks(ds: storage.GraspDataset) -> list[tuple[str, str | None, int]]:
    return [
        (str(ds.root / e["file"]), e.get("sha256") if ds.verify else None, int(e["object_id"]))
        for e in ds.shard_entries
    ]


def grasp_table(ds: storage.GraspDataset, workers: int = 1, progress: bool = False) -> GraspTable:
    """Every grasp of ``ds`` as one row, in shard (object id) order whatever ``workers`` reads them."""
    parts: dict[int, dict] = {}
    tasks = [(*t, ds.label_threshold) for t in _shard_tasks(ds)]
    run_tasks(_table_rows, tasks, workers, on_result=lambda r: parts.__setitem__(*r), progress=progress, desc="read")
    cols: dict[str, list] = {k: [parts[i][k] for i in ds.object_ids] for k in GraspTable.__dataclass_fields__}
    return GraspTable(**{k: (np.concatenate(v) if v else np.zeros(0)) for k, v in cols.items()})


def _write_sampled(
    path: str, sha256: str | None, object_id: int, out: str, keep: np.ndarray, label_threshold: float
) -> tuple[int, dict | None]:
    """Write the ``keep`` rows of one shard (and only the images they use) into ``out`` (a worker
    task); (object id, its shard entry), or None for the entry when no row is kept."""
    if not keep.any():
        return object_id, None
    images, grasps = storage.read_shard(path, sha256)
    grasps = {k: v[keep] for k, v in grasps.items()}
    used, new_index = np.unique(grasps["image_index"], return_inverse=True)
    grasps["image_index"] = new_index.astype(np.int32).reshape(-1)
    images = {k: v[used] for k, v in images.items()}
    return object_id, storage.write_shard(out, object_id, images, grasps, label_threshold)


def _beta_table(label: np.ndarray, beta: np.ndarray, width: float, n_bins: int) -> dict:
    n, pos, rate = positivity_by_bin(label, angle_bins(beta, width), n_bins)
    return {
        "count": n.tolist(),
        "positive": pos.tolist(),
        "positivity": [None if np.isnan(r) else float(r) for r in rate],
    }


def sample_dataset(
    src: str | Path,
    out: str | Path,
    params: SamplingParams = SamplingParams(),
    log: Callable[[str], None] = print,
    plot: bool = True,
    split_over: list[int] | None = None,
    workers: int = 1,
    progress: bool = False,
) -> dict:
    """Sample the grasp dataset ``src`` into ``out`` (a ``vgq-grasps`` dataset holding only the
    kept grasps and their images, with ``split`` per object and ``sampling`` statistics in its
    manifest). Returns the statistics. ``split_over``: the object ids the object-wise split
    is drawn over, in place of the dataset's own (e.g. a partly generated run of a recipe split
    as the whole run was); it must hold every object that has grasps. ``workers`` processes read
    and write the shards (the same dataset for any number)."""
    out = Path(out)
    if (out / storage.MANIFEST).exists():
        raise FileExistsError(f"output folder {out} already holds a dataset; choose a new --out")
    ds = storage.open_dataset(src)
    t = grasp_table(ds, workers, progress)
    if len(t.label) and not t.label.any():
        raise ValueError(
            f"{src} has no positive grasp (quality > label threshold {ds.label_threshold}); positivity "
            "equalisation would drop every grasp"
        )
    rng = np.random.default_rng(params.seed)
    n_beta = max(
        int(math.ceil(math.pi / 2 / params.beta_bin)),
        int(angle_bins(t.beta, params.beta_bin).max()) + 1 if len(t.beta) else 1,
    )

    steps = {"native": np.ones(len(t.label), dtype=bool)}
    keep = psi_mask(t.psi, params.max_psi)
    steps["psi"] = keep.copy()
    idx = np.flatnonzero(keep)
    eq = equalise_positivity(t.label[idx], t.beta[idx], params, rng)
    keep[idx[~eq]] = False
    steps["positivity"] = keep.copy()
    if params.uniform:
        idx = np.flatnonzero(keep)
        un = uniform_over_bins(t.phi[idx], t.beta[idx], params, rng)
        keep[idx[~un]] = False
    steps["uniform"] = keep.copy()

    stats = {"steps": {}, "beta_bins_deg": [math.degrees(i * params.beta_bin) for i in range(n_beta + 1)]}
    for name, m in steps.items():
        stats["steps"][name] = {
            "grasps": int(m.sum()),
            "positive": int(t.label[m].sum()),
            "positivity": float(100.0 * t.label[m].mean()) if m.any() else 0.0,
            "by_beta": _beta_table(t.label[m], t.beta[m], params.beta_bin, n_beta),
        }
    families = {int(o["object_id"]): o.get("family") for o in ds.manifest["objects"]}
    manifest = ds.manifest if split_over is None else {**ds.manifest, "split_object_ids": list(split_over)}
    population = split_population(manifest, ds.object_ids)
    split = split_by_family(population, families, params.split_fractions, params.seed, params.holdout_families)
    split = {i: split[i] for i in ds.object_ids}  # a derived dataset's objects, split as in its source
    stats["families"] = split_table(split, families)
    _print_stats(stats, log)
    if len(stats["families"]) > 1:
        log(
            "objects per family (train / val / test): "
            + ", ".join(f"{f} {r['train']}/{r['val']}/{r['test']}" for f, r in stats["families"].items())
        )
        wanted = [sp for sp, fr in zip(SPLITS, params.split_fractions) if fr > 0]
        short = [
            f
            for f, r in stats["families"].items()
            if f not in params.holdout_families and any(r[sp] == 0 for sp in wanted)
        ]
        if short:
            log(f"warning: families with an empty split (fewer than 3 objects?): {', '.join(short)}")
    psi_tab = stats["steps"]["psi"]["by_beta"]
    empty = [i for i, (n, p) in enumerate(zip(psi_tab["count"], psi_tab["positive"])) if n > 0 and p == 0]
    if empty:
        log(
            f"warning: {len(empty)} beta bins without positives lose all their grasps (rate_neg = 0): "
            + ", ".join(f"[{stats['beta_bins_deg'][i]:.0f}, {stats['beta_bins_deg'][i + 1]:.0f})" for i in empty)
        )

    # write the sampled dataset
    src_m = ds.manifest
    objects = [{k: v for k, v in o.items() if k not in ("status", "shard", "reason")} for o in src_m["objects"]]
    m = storage.new_grasp_manifest(
        src_m["config"],
        src_m["seed"],
        objects,
        ds.label_threshold,
        source_dataset=str(Path(src).resolve()),
        **({"intrinsics": src_m["intrinsics"]} if src_m.get("intrinsics") else {}),
        sampling={"params": asdict(params), "stats": stats},
        **({} if split_over is None else {"split_object_ids": sorted(int(i) for i in population)}),
    )
    for o, so in zip(m["objects"], src_m["objects"]):
        if so.get("status") != "done":
            storage.record_skip(m, o["object_id"], so.get("reason", "not generated"))

    def record(result: tuple[int, dict | None]) -> None:
        oid, entry = result
        if entry is None:
            storage.record_skip(m, oid, "no grasps left after sampling", split=split[oid])
        else:
            storage.record_shard(m, entry, split=split[oid])  # kept in object id order
        storage.write_manifest(out, m)

    tasks = [(*task, str(out), keep[t.object_id == task[2]], ds.label_threshold) for task in _shard_tasks(ds)]
    run_tasks(_write_sampled, tasks, workers, on_result=record, progress=progress, desc="write")
    m["splits"] = {s: sorted(i for i, v in split.items() if v == s) for s in SPLITS}
    kept_ids = t.object_id[keep]
    stats["splits"] = {s: int(np.isin(kept_ids, m["splits"][s]).sum()) for s in SPLITS}
    m["sampling"]["stats"] = stats
    m["complete"] = True
    storage.write_manifest(out, m)
    log("grasps per split: " + ", ".join(f"{s} {stats['splits'][s]} ({len(m['splits'][s])} objects)" for s in SPLITS))
    if plot and len(t.label):
        from . import plots

        files = plots.sampling_plots(out / "plots", stats, t, steps, params)
        log("plots: " + ", ".join(str(f) for f in files))
    return stats


def _print_stats(stats: dict, log: Callable[[str], None]) -> None:
    log("step         grasps   positive  positivity")
    for name, s in stats["steps"].items():
        log(f"{name:<10} {s['grasps']:>8} {s['positive']:>10} {s['positivity']:>10.1f}%")
    edges = stats["beta_bins_deg"]
    before, after = stats["steps"]["psi"]["by_beta"], stats["steps"]["positivity"]["by_beta"]
    final = stats["steps"]["uniform"]["by_beta"]
    log("beta bin (deg)   n before  pos% before   n after  pos% after   n final")

    def pct(x):
        return "      -" if x is None else f"{x:7.1f}"

    for i in range(len(edges) - 1):
        if before["count"][i] == 0:
            continue
        log(
            f"[{edges[i]:4.0f}, {edges[i + 1]:4.0f})   {before['count'][i]:>8}  {pct(before['positivity'][i]):>11}"
            f"  {after['count'][i]:>8}  {pct(after['positivity'][i]):>10}  {final['count'][i]:>8}"
        )
