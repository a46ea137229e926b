"""Score exported model folders on a crop dataset's split through their ONNX graphs (what the
service runs), overall and per object family: to compare two models on the same grasps, e.g.
the bundled model on a new dataset or v1 against v2 on v2's test split.

    python -m export.evaluate --model-dir models/fast-vgqcnn-default /work/data/v2-model \\
        --data data/v2/crops --split test --max-n 20000

Metrics: balanced accuracy, TPR, TNR at raw score 0.5 (the training threshold) and ROC AUC, on
``--max-n`` rows drawn at random (seed 0) from the split, the same rows for every model; fp32
head and encoder (exact scores). Fast-VGQ-CNN folders only (crops are its 32 x 32 windows).

``--mirror``: also each crop's left-right mirror image (crop flipped, pose by
``vgq.pose.mirror_poses``), scored alone and as the mean of the two scores (test-time mirroring),
with the correlation of the two scores.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

import numpy as np

from datagen import storage
from training import metrics as M
from vgq.model_card import ModelCard
from vgq.schema import SPLITS, placement_rows_as_seen


def object_families(data: str | Path, default: str = "") -> dict[int, str]:
    """Object id -> family name of a crop dataset's objects (from its source manifest), ``default``
    for an object recorded without one."""
    m = json.loads((Path(data) / storage.MANIFEST).read_text())
    return {int(o["object_id"]): o.get("family") or default for o in m.get("source", {}).get("objects", [])}


def crop_rows(data: str | Path, split: str, max_n: int, seed: int = 0) -> dict[str, np.ndarray]:
    """``images``, ``poses``, ``labels``, ``family``, ``object_id`` and ``beta`` (radians, the
    approach to the downward table normal; None when the dataset has none) of at most ``max_n``
    random rows (sorted)."""
    arrays = storage.open_crops(data, split)
    n = len(arrays["labels"])
    if n == 0:
        raise ValueError(f"{data}: split {split!r} has no crops")
    idx = M.sample_rows(n, max_n, seed)  # the rows training evaluate --max-n scores
    fam = object_families(data)
    oid = np.asarray(arrays["object_id"][idx])
    rows_ok = placement_rows_as_seen(json.loads((Path(data) / storage.MANIFEST).read_text()))
    return {
        "images": np.asarray(arrays["images"][idx], np.float32),
        "poses": np.asarray(arrays["poses"][idx], np.float32),
        "labels": np.asarray(arrays["labels"][idx]).astype(bool),
        "family": np.array([fam.get(int(i), "") for i in oid]),
        "object_id": oid,
        "beta": np.asarray(arrays["beta"][idx], np.float64) if "beta" in arrays else None,
        # rows as the service makes them, or none (a placement head then refuses the crops)
        "placement": np.asarray(arrays["placement"][idx], np.float32) if "placement" in arrays and rows_ok else None,
    }


def check_geometry(model_dirs, data: str | Path) -> None:
    """ValueError naming the first model whose card's crop geometry is not the dataset's (its windows,
    kappa and turning): such a model would be scored on inputs it was never trained for."""
    from vgq.crop import CropGeometry
    from vgq.model_card import ModelCard

    m = json.loads((Path(data) / storage.MANIFEST).read_text())
    geom = CropGeometry.from_dict(m["geometry"])
    for d in model_dirs:
        card = ModelCard.load(d)
        if card.geometry != geom:
            raise ValueError(
                f"{d} was trained on crops {card.geometry.to_dict()} ({card.geometry.turning()}); {data} has "
                f"{geom.to_dict()} ({geom.turning()}); pass --other-crops to score it there all the same"
            )


def raw_scores(
    model_dir: str | Path, images: np.ndarray, poses: np.ndarray, batch: int = 256, placement: np.ndarray | None = None
) -> np.ndarray:
    """(n,) raw scores of the folder's fp32 graphs for crops (n, 32, 32) and pose rows (n, 7); a
    placement head (its card's ``placement_columns``) also reads ``placement`` (n, 7), the crops'
    placement rows (ValueError without them)."""
    from service.runtime import FastModel

    model = FastModel(model_dir, threads=0, head_precision="fp32", encoder_precision="fp32")
    if model.card.placement_columns:
        if placement is None:
            raise ValueError(
                f"{model_dir} reads placement rows; the crops have none made as the service makes them "
                "(cut them again with this datagen)"
            )
        poses = np.concatenate([poses, placement], axis=1).astype(np.float32)
    out = np.empty(len(images), np.float32)
    for s in range(0, len(images), batch):
        terms = model.encode(images[s : s + batch])
        out[s : s + batch] = model.score(terms, poses[s : s + batch])
    return out


def export_writes(key: str) -> bool:
    """Whether the export writes the card's ``metrics[key]`` itself (``python -m export``: test,
    test_clean, baseline_<model>; ``export.leave_family_out``): not for ``--card-key`` to replace."""
    return key in ("test", "test_clean", "leave_family_out") or key.startswith("baseline_")


def record_in_card(model_dir: str | Path, key: str, value: dict) -> None:
    """Set ``metrics[key]`` of the model card in ``model_dir`` to ``value``, every other key as it was
    (the card rewritten atomically)."""
    from vgq import atomic
    from vgq.model_card import CARD_NAME

    path = Path(model_dir) / CARD_NAME
    d = json.loads(path.read_text())
    d.setdefault("metrics", {})[key] = value
    atomic.write_json(path, d)


def mirrored(images: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Crops (n, [1,] S, S) flipped left to right and their Fast-VGQ-CNN pose rows (n, 7) mirrored
    to match (``vgq.pose.mirror_poses``: the same grasps in the mirrored scene)."""
    from vgq.pose import POSE_COLUMNS, mirror_poses

    flipped = np.ascontiguousarray(images[..., ::-1])
    return flipped, mirror_poses(poses, POSE_COLUMNS["fast_vgqcnn"]).astype(np.float32)


def evaluate(
    labels: np.ndarray,
    scores: np.ndarray,
    family: np.ndarray,
    object_id: np.ndarray | None = None,
    beta: np.ndarray | None = None,
) -> dict:
    """Overall and per-family metrics at raw score 0.5, with ROC AUC; with ``object_id`` also the
    balanced accuracy's 95% interval over the objects (``balanced_accuracy_ci95``); with
    ``beta`` (radians) by the grasp's approach to the downward table normal, in 15 deg bins."""
    by_family = M.metrics_by_group(labels[family != ""], scores[family != ""], family[family != ""])
    out = {
        "all": M.nan_to_none(M.binary_metrics(labels, scores)),
        "by_family": {f: M.nan_to_none(m) for f, m in by_family.items()},
    }
    if beta is not None:
        out["by_approach_beta_deg"] = {
            k: M.nan_to_none(m) for k, m in M.metrics_by_bin(labels, scores, np.degrees(beta), 15.0).items()
        }
    if object_id is not None:
        out["all"]["balanced_accuracy_ci95"] = M.object_bootstrap_ci(labels, scores, object_id)
        for f, m in out["by_family"].items():
            rows = family == f
            m["balanced_accuracy_ci95"] = M.object_bootstrap_ci(labels[rows], scores[rows], object_id[rows])
    return out


def _ci(m: dict) -> str:
    lo, hi = m.get("balanced_accuracy_ci95") or (None, None)
    return "n/a" if lo is None else f"{100 * lo:.1f}-{100 * hi:.1f}"


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(
        prog="python -m export.evaluate", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--model-dir", nargs="+", required=True, help="exported Fast-VGQ-CNN folders")
    p.add_argument("--data", required=True, help="a vgq-crops dataset (fast_vgqcnn crops)")
    p.add_argument("--split", default="test", choices=SPLITS)
    p.add_argument("--max-n", type=int, default=20_000, help="rows drawn at random from the split (default 20000)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", help="also write the results here")
    p.add_argument(
        "--mirror",
        action="store_true",
        help="also score each crop's left-right mirror image, alone and averaged with the original (test-time mirroring)",
    )
    p.add_argument(
        "--blank-placement",
        action="store_true",
        help="also score each placement model (card placement_columns) with every placement row made unknown "
        "(all 0): what the rows add",
    )
    p.add_argument(
        "--other-crops",
        action="store_true",
        help="score a model on crops cut for another geometry (e.g. an unturned model on windows turned "
        "towards the jaw: the start of a fine-tune into them); refused otherwise",
    )
    p.add_argument(
        "--card-key",
        metavar="KEY",
        help="also record each model's result in its model card as metrics.KEY (with the data folder, split, "
        "rows and seed), e.g. test_more_objects; the card is rewritten atomically, its other keys kept",
    )
    a = p.parse_args(argv)
    if a.card_key is not None and (export_writes(a.card_key) or not re.fullmatch(r"[a-z][a-z0-9_]*", a.card_key)):
        p.error(
            f"--card-key {a.card_key!r}: use lower-case letters, digits and _, and none of the export's own keys "
            "(test, test_clean, leave_family_out, baseline_*)"
        )
    if a.max_n < 1:
        p.error("--max-n must be >= 1")
    for d in a.model_dir:
        if not (Path(d) / "model_card.json").is_file():
            p.error(f"--model-dir {d}: no model_card.json there")
    try:
        if not a.other_crops:
            check_geometry(a.model_dir, a.data)
        rows = crop_rows(a.data, a.split, a.max_n, a.seed)
        for d in a.model_dir:
            if ModelCard.load(d).placement_columns and rows["placement"] is None:
                raise ValueError(
                    f"{d} reads placement rows; {a.data} has none made as the service makes them "
                    "(placement_grasp_depth: crop it again with this datagen)"
                )
    except (OSError, ValueError) as e:
        print(f"export.evaluate: {e}", file=sys.stderr)
        sys.exit(2)
    results = {}
    for d in a.model_dir:
        scores = raw_scores(d, rows["images"], rows["poses"], placement=rows["placement"])
        variants = {d: scores}
        if a.mirror:  # a placement row is the same in the mirror image
            m_scores = raw_scores(d, *mirrored(rows["images"], rows["poses"]), placement=rows["placement"])
            variants[f"{d} (mirrored)"] = m_scores
            variants[f"{d} (mean of it and its mirror)"] = 0.5 * (scores + m_scores)
        if a.blank_placement and rows["placement"] is not None and ModelCard.load(d).placement_columns:
            blank = np.zeros_like(rows["placement"])
            variants[f"{d} (placement rows unknown)"] = raw_scores(d, rows["images"], rows["poses"], placement=blank)
        for name, sc in variants.items():
            results[name] = _report(name, sc, rows, a)
        if a.card_key:
            where = {"data": str(a.data), "split": a.split, "max_n": a.max_n, "seed": a.seed}
            record_in_card(d, a.card_key, {**results[d], **where})
            print(f"{d}: model card metrics.{a.card_key} written")
        if a.mirror:
            corr = float(np.corrcoef(scores, m_scores)[0, 1])
            results[f"{d} (mirrored)"]["score_correlation_with_original"] = corr
            print(f"\ncorrelation of the scores of the crops and of their mirror images: {corr:.3f}")
    if a.json:
        from vgq import atomic

        atomic.write_json(a.json, {"data": str(a.data), "split": a.split, "max_n": a.max_n, "results": results})
    return results


def _report(d: str, scores: np.ndarray, rows: dict, a: argparse.Namespace) -> dict:
    """:func:`evaluate` of ``scores`` (n,) on ``rows`` (:func:`crop_rows`), printed as tables under ``d``."""
    r = evaluate(rows["labels"], scores, rows["family"], rows["object_id"], rows["beta"])
    print(f"\n{d} on {a.data} {a.split} ({len(rows['labels'])} crops):")
    print(
        "| family | n | balanced accuracy | 95% interval (objects resampled) | TPR | TNR | AUC |\n"
        "|---|---:|---:|---:|---:|---:|---:|"
    )
    for name, m in [("all", r["all"]), *r["by_family"].items()]:
        auc = "n/a" if m["auc"] is None else f"{m['auc']:.3f}"
        print(
            f"| {name} | {m['n']} | {M.pct(m['balanced_accuracy'])} | {_ci(m)} | {M.pct(m['tpr'])} | "
            f"{M.pct(m['tnr'])} | {auc} |"
        )
    if "by_approach_beta_deg" in r:
        bins = r["by_approach_beta_deg"]
        print("\n| approach to straight down, beta (deg) | " + " | ".join(bins) + " |")
        print("|---|" + "---:|" * len(bins))
        print("| balanced accuracy | " + " | ".join(M.pct(m["balanced_accuracy"]) for m in bins.values()) + " |")
        print("| grasps | " + " | ".join(f"{m['n']:,}" for m in bins.values()) + " |")
    return r


if __name__ == "__main__":
    main()
