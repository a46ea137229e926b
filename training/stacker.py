"""A placement stacker: the served head's logit corrected by where each grasp lies on its object.

The window shows the grasp's surroundings, not the whole object: a bottle held by its neck 8 cm
from its centre of mass falls, held 1 cm from it holds, and the 96 px window often cannot tell the
two apart (docs/training.md, "What the window misses"). Each grasp's placement row
(``vgq.placement``: the offset of the grasp from its object's centre-of-mass guess, in the table
plane and in the gripper frame, its height and the object's top, computed from the depth image
alone by ``planning.placement``) carries that. A fine-tune of the whole network through pc1 did
not learn to read the row. This module fits the correction on its own, on top of a trained
model's scores:

    logit' = logit + known * mlp((logit, offset, along, across, depth, height, top))

a small MLP (metres in, standardised) whose last layer starts at zero, trained with
cross-entropy on grasps of objects the model never saw, each family's positives and negatives
weighted alike (the target is every family's balanced accuracy); ``known`` = 0 (no table or
no object region found) leaves the model's logit as it was. ``export.stack_head`` appends it to a
model folder's head graphs, so the service serves it as any placement head (it analyses each
upload once and appends each grasp's row).

``python -m training stacker --model-dir M --fit CROPS ... --judge CROPS ... --out M2``
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vgq.calibration import logit, sigmoid
from vgq.placement import PLACEMENT_COLUMNS
from vgq.schema import check_placement_rows

#: what the MLP reads: the model's logit, then the placement row without its ``known`` flag
INPUTS = ("logit", *PLACEMENT_COLUMNS[1:])


@dataclass(frozen=True)
class Stacker:
    """The fitted correction: input standardisation (``mean``, ``std``: (7,), ``INPUTS`` order)
    and the MLP's layers, each (W (out, in), b (out,)) float32, ReLU between them."""

    mean: np.ndarray
    std: np.ndarray
    layers: tuple[tuple[np.ndarray, np.ndarray], ...]

    def delta(self, logit: np.ndarray, placement: np.ndarray) -> np.ndarray:
        """(n,) the MLP's correction for logits (n,) and placement rows (n, 7)."""
        x = (np.c_[logit, placement[:, 1:]] - self.mean) / self.std
        for i, (w, b) in enumerate(self.layers):
            x = x @ w.T + b
            if i < len(self.layers) - 1:
                x = np.maximum(x, 0.0)
        return x[:, 0]

    def apply(self, logit: np.ndarray, placement: np.ndarray) -> np.ndarray:
        """(n,) corrected logits; a row whose ``known`` is 0 keeps its logit."""
        return logit + placement[:, 0] * self.delta(logit, placement)

    def to_dict(self) -> dict:
        return {
            "inputs": list(INPUTS),
            "mean": self.mean.tolist(),
            "std": self.std.tolist(),
            "layers": [{"weight": w.tolist(), "bias": b.tolist()} for w, b in self.layers],
        }

    @classmethod
    def from_dict(cls, d: dict) -> Stacker:
        if list(d["inputs"]) != list(INPUTS):
            raise ValueError(f"a stacker of inputs {d['inputs']}; this code reads {list(INPUTS)}")
        layers = tuple((np.asarray(x["weight"], np.float32), np.asarray(x["bias"], np.float32)) for x in d["layers"])
        return cls(np.asarray(d["mean"], np.float32), np.asarray(d["std"], np.float32), layers)


def stack_rows(model_dir: str | Path, crops: list[str | Path], split: str, per_object: int, seed: int = 0) -> dict:
    """Up to ``per_object`` random rows of each object of the ``split`` split of each crop dataset
    in ``crops`` (cut with placement rows): ``logit`` (n,) of the model's fp32 graphs,
    ``placement`` (n, 7), ``labels`` (n,) bool, ``object`` (n,) str (dataset folder name:object id)
    and ``family`` (n,) str. ValueError naming crops without placement rows."""
    from datagen import storage
    from export.evaluate import object_families, raw_scores

    rng = np.random.default_rng(seed)
    parts = []
    for c in map(Path, crops):
        arr = storage.open_crops(c, split)
        if "placement" not in arr:
            raise ValueError(f"{c}: its {split} crops have no placement rows (cut them again with datagen crops)")
        check_placement_rows(json.loads((c / storage.MANIFEST).read_text()), str(c))
        fam = object_families(c, default="random_urdfs")
        oid = np.asarray(arr["object_id"])
        take = np.sort(
            np.concatenate(
                [rng.permutation(np.flatnonzero(oid == o))[:per_object] for o in np.unique(oid)]
                or [np.zeros(0, np.int64)]
            )
        )
        images, poses = np.asarray(arr["images"][take], np.float32), np.asarray(arr["poses"][take], np.float32)
        parts.append(
            {
                "logit": logit(raw_scores(model_dir, images, poses)),
                "placement": np.asarray(arr["placement"][take], np.float32),
                "labels": np.asarray(arr["labels"][take]).astype(bool),
                "object": np.array([f"{c.name}:{o}" for o in oid[take]]),
                "family": np.array([fam.get(int(o), "unknown") for o in oid[take]]),
            }
        )
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


#: how :func:`fit` weighs its rows: "family" (each family's positives and negatives alike: the
#: balanced accuracy of every family is the target) or "class" (all positives against all negatives)
BALANCES = ("family", "class")


def row_weights(labels: np.ndarray, family: np.ndarray, balance: str = "family") -> np.ndarray:
    """(n,) loss weights, mean 1: 1 / (rows of the row's class) overall ("class") or within the
    row's family ("family"; a family with one class only weighs as the others' rows of that class)."""
    if balance not in BALANCES:
        raise ValueError(f"balance must be one of {BALANCES}, got {balance!r}")
    y = np.asarray(labels, bool)
    groups = [np.ones(len(y), bool)] if balance == "class" else [family == f for f in np.unique(family)]
    w = np.zeros(len(y))
    for g in groups:
        for c in (False, True):
            r = g & (y == c)
            if r.any():
                w[r] = 1.0 / r.sum()
    return w * len(y) / w.sum()


def fit(
    rows: dict, hidden: int = 32, epochs: int = 8, lr: float = 1e-3, seed: int = 0, balance: str = "family"
) -> Stacker:
    """The stacker fitted to ``rows`` (:func:`stack_rows`): Adam, batches of 512, binary
    cross-entropy weighted by :func:`row_weights` (``balance``), weight decay 1e-4."""
    import torch

    torch.manual_seed(seed)
    y = rows["labels"].astype(np.float32)
    if len(y) == 0 or y.min() == y.max():
        raise ValueError(f"need positive and negative rows to fit a stacker, got {int(y.sum())} of {len(y)} positive")
    wt = torch.tensor(row_weights(rows["labels"], rows["family"], balance), dtype=torch.float32)
    x = np.c_[rows["logit"], rows["placement"][:, 1:]].astype(np.float64)
    mean, std = x.mean(0), x.std(0) + 1e-6
    net = torch.nn.Sequential(
        torch.nn.Linear(len(INPUTS), hidden),
        torch.nn.ReLU(),
        torch.nn.Linear(hidden, hidden),
        torch.nn.ReLU(),
        torch.nn.Linear(hidden, 1),
    )
    torch.nn.init.zeros_(net[-1].weight)  # starts as the model itself
    torch.nn.init.zeros_(net[-1].bias)
    opt = torch.optim.Adam(net.parameters(), lr, weight_decay=1e-4)
    xt = torch.tensor((x - mean) / std, dtype=torch.float32)
    lt = torch.tensor(rows["logit"], dtype=torch.float32)
    kt = torch.tensor(rows["placement"][:, 0], dtype=torch.float32)
    yt = torch.tensor(y)
    for _ in range(epochs):
        for b in torch.randperm(len(yt)).split(512):
            out = lt[b] + kt[b] * net(xt[b]).squeeze(1)
            loss = (torch.nn.functional.binary_cross_entropy_with_logits(out, yt[b], reduction="none") * wt[b]).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
    layers = tuple(
        (m.weight.detach().numpy().astype(np.float32), m.bias.detach().numpy().astype(np.float32))
        for m in net
        if isinstance(m, torch.nn.Linear)
    )
    return Stacker(mean.astype(np.float32), std.astype(np.float32), layers)


def by_family(rows: dict, logits: np.ndarray) -> dict:
    """``training.metrics.binary_metrics`` (balanced accuracy at P 0.5, TPR, TNR, AUC, row counts)
    of ``logits`` on ``rows``, over all (``"all"``) and per family."""
    from .metrics import binary_metrics, metrics_by_group

    p = sigmoid(logits)
    return {"all": binary_metrics(rows["labels"], p), **metrics_by_group(rows["labels"], p, rows["family"])}


def run(
    model_dir: str | Path,
    fit_crops: list[str | Path],
    judge_crops: list[str | Path],
    out: str | Path,
    split: str = "test",
    per_object: int = 1500,
    hidden: int = 32,
    epochs: int = 8,
    seed: int = 0,
    balance: str = "family",
) -> dict:
    """Fit a stacker on the ``split`` rows of ``fit_crops`` (objects ``model_dir``'s model never
    saw), judge it on those of ``judge_crops`` (other such objects), refit the card's calibration
    on the stacked scores (fit rows; measured on the judge rows; the card's target positivity),
    and write the stacked model folder ``out``. Returns the record kept in its card."""
    from export.calibrate import calibration_report, plot_reliability
    from export.stack_head import write_stacked
    from vgq.model_card import ModelCard

    if per_object < 1 or hidden < 1 or epochs < 1:
        raise ValueError(f"--per-object, --hidden and --epochs must be >= 1, got {per_object}, {hidden}, {epochs}")
    card = ModelCard.load(model_dir)
    rows = stack_rows(model_dir, fit_crops, split, per_object, seed)
    judge = stack_rows(model_dir, judge_crops, split, per_object, seed + 1)
    stacker = fit(rows, hidden, epochs, seed=seed, balance=balance)
    record = {
        "fit_on": [str(c) for c in fit_crops],
        "judged_on": [str(c) for c in judge_crops],
        "split": split,
        "per_object": per_object,
        "hidden": hidden,
        "epochs": epochs,
        "seed": seed,
        "balance": balance,
        "fit_rows": int(len(rows["labels"])),
        "fit_objects": int(len(np.unique(rows["object"]))),
        "judge_rows": int(len(judge["labels"])),
        "judge_objects": int(len(np.unique(judge["object"]))),
        "judged": {
            "model": by_family(judge, judge["logit"]),
            "stacked": by_family(judge, stacker.apply(judge["logit"], judge["placement"])),
        },
    }
    calibration = None
    if card.calibration:
        report = calibration_report(
            sigmoid(stacker.apply(rows["logit"], rows["placement"])),
            rows["labels"],
            sigmoid(stacker.apply(judge["logit"], judge["placement"])),
            judge["labels"],
            float(card.calibration["target_positivity"]),
            str(card.calibration.get("target_positivity_source", "the model's card")),
            splits=("stacker fit rows", "stacker judge rows"),
        )
        calibration = report.to_dict()
    path = write_stacked(model_dir, stacker, out, record, calibration)
    if calibration is not None:
        plot_reliability(report, path / calibration["reliability_diagram"])
    return record


def measure(model_dir: str | Path, crops: str | Path, key: str, max_n: int = 50_000, seed: int = 0) -> dict:
    """Score the folder's fp32 graphs (a stacked folder: with each crop's placement row) on ``max_n``
    random test rows of ``crops`` (the rows ``training evaluate --max-n`` and ``export.evaluate``
    draw) and record the result as the card's ``metrics[key]``, in the shape the export writes
    (the overall numbers, ``by_family``, the 95% interval over objects) with where it was measured."""
    from export.evaluate import crop_rows, evaluate, raw_scores, record_in_card

    rows = crop_rows(crops, "test", max_n, seed)
    scores = raw_scores(model_dir, rows["images"], rows["poses"], placement=rows["placement"])
    r = evaluate(rows["labels"], scores, rows["family"], rows["object_id"])
    value = {
        **r["all"],
        "by_family": r["by_family"],
        "data": str(crops),
        "split": "test",
        "max_n": max_n,
        "seed": seed,
        "measured_by": "training.stacker.measure: the folder's fp32 graphs (export.evaluate)",
    }
    record_in_card(model_dir, key, value)
    return value


def table(record: dict) -> str:
    """The judged balanced accuracies, model against stacked, as a Markdown table."""
    model, stacked = record["judged"]["model"], record["judged"]["stacked"]
    lines = ["| family | rows | model | stacked |", "|---|---:|---:|---:|"]
    for f in model:
        lines.append(
            f"| {f} | {model[f]['n']} | {100 * model[f]['balanced_accuracy']:.1f}% | "
            f"{100 * stacked[f]['balanced_accuracy']:.1f}% |"
        )
    return "\n".join(lines)
