"""Teacher scores for distillation: a trained run's P(success) for the rows of one crop split.

A student of another architecture learns from them (``training train --target teacher --teacher
DIR``) when its crops were cut from the same sampled grasps (``datagen crops`` of one ``datagen
sample`` output: the same rows in the same order; checked by the labels' and object ids' digest).

Rows are scored in chunks, in a seeded random order, and the scores are saved after each chunk
(atomically): an interrupted scoring resumes, and a part-scored file (NaN where not yet scored)
already serves a student, which falls back to the label on the rows without a score.

Folder layout: ``manifest.json`` (format ``vgq-teacher-scores``, the teacher checkpoint, the crops
scored, per split its row count, digest and rows scored) and ``<split>.npy`` (n,) float32.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from vgq import atomic

from .data import CropSplit, DatasetError
from .evaluate import open_trained_on
from .predict import predict_split

FORMAT = "vgq-teacher-scores"
FORMAT_VERSION = 1


def rows_digest(split: CropSplit) -> str:
    """sha256 of a split's labels and object ids: equal for two crop sets cut from one sampled set."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(split.labels, dtype=np.uint8).tobytes())
    h.update(np.ascontiguousarray(split.arrays["object_id"], dtype=np.int64).tobytes())
    return h.hexdigest()


def _read_manifest(out: Path) -> dict | None:
    p = out / "manifest.json"
    if not p.is_file():
        return None
    try:
        m = json.loads(p.read_text())
    except ValueError as e:
        raise DatasetError(f"{p}: not JSON ({e})") from e
    if m.get("format") != FORMAT:
        raise DatasetError(f"{p}: format {m.get('format')!r}, expected {FORMAT!r}")
    return m


def score_teacher(
    run: str | Path,
    data_dir: str | Path,
    out_dir: str | Path,
    split: str = "train",
    max_rows: int = 0,
    chunk_rows: int = 65536,
    batch_size: int = 256,
    bf16: bool = False,
    seed: int = 0,
    progress: bool = True,
) -> dict:
    """Score ``split`` of the crop dataset ``data_dir`` (crops the teacher was trained on) with the
    run folder's best checkpoint (or checkpoint file) ``run`` into ``out_dir``; resumes a part-scored
    folder of the same teacher and crops. ``max_rows`` > 0: stop after that many rows (the first of the
    seeded order). ``bf16``: the forward pass under CPU bf16 autocast. Returns the manifest."""
    if chunk_rows < 1 or batch_size < 1 or max_rows < 0:
        raise ValueError(
            f"need chunk_rows, batch_size >= 1 and max_rows >= 0, got {chunk_rows}, {batch_size}, {max_rows}"
        )
    net, meta, data, sp, _ = open_trained_on(run, data_dir, split)
    n, digest = len(sp), rows_digest(sp)
    out = Path(out_dir)
    teacher = {
        "checkpoint": meta["checkpoint"],
        "arch": meta["arch"],
        "samples_seen": meta["training"]["samples_seen"],
        "val_balanced_accuracy": meta["training"]["validation"].get("balanced_accuracy"),
        "class_balance": meta["training"]["config"].get("class_balance", "none"),
    }
    m = _read_manifest(out) or {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "teacher": teacher,
        "crops": str(data.path.resolve()),
        "source": (data.manifest.get("source") or {}).get("dataset"),
        "splits": {},
    }
    if (m["teacher"]["checkpoint"], m["teacher"]["samples_seen"]) != (teacher["checkpoint"], teacher["samples_seen"]):
        raise DatasetError(
            f"{out} holds the scores of {m['teacher']['checkpoint']} at {m['teacher']['samples_seen']} samples; "
            "choose another folder"
        )
    entry = m["splits"].get(split)
    path = out / f"{split}.npy"
    if entry is not None and path.is_file():
        if (entry["n"], entry["digest"]) != (n, digest):
            raise DatasetError(
                f"{out}: its {split!r} scores are of other rows than {data.path}'s; choose another folder"
            )
        scores = np.array(np.load(path), dtype=np.float32)
    else:
        scores = np.full(n, np.nan, dtype=np.float32)
    order = np.random.default_rng(seed).permutation(n)[: max_rows or n]
    net = net.to(memory_format=torch.channels_last)
    out.mkdir(parents=True, exist_ok=True)
    bar = tqdm(total=len(order), unit="row", unit_scale=True, desc=f"teacher {split}", disable=not progress)
    for c in range(0, len(order), chunk_rows):
        rows = np.sort(order[c : c + chunk_rows])
        todo = rows[np.isnan(scores[rows])]  # a chunk cut short by max_rows is finished, not redone
        if len(todo):
            scores[todo], _ = predict_split(net, sp, todo, batch_size=batch_size, bf16=bf16)
            atomic.save_npy(path, scores)  # the scores first: the manifest never counts rows not on disk
            m["splits"][split] = {"n": n, "digest": digest, "seed": seed, "scored": int(np.isfinite(scores).sum())}
            atomic.write_json(out / "manifest.json", m)
        bar.update(len(rows))
    bar.close()
    return m


def load_teacher_scores(teacher_dir: str | Path, split: CropSplit, weights=None) -> np.ndarray:
    """The teacher's posterior P(success) (n,) float32 (NaN: not scored) for the rows of ``split``,
    checked to be the same rows (count and digest); raises DatasetError naming the mismatch.

    A teacher trained with class-balanced loss weights scores p = w1 P / (w1 P + w0 (1 - P)), not P;
    its scores are turned back into P with ``weights`` (w0, w1), the class weights of these very rows
    (:func:`training.train._class_weights`), needed then."""
    d = Path(teacher_dir)
    m = _read_manifest(d)
    if m is None:
        raise DatasetError(f"{d} holds no teacher scores (no manifest.json; `python -m training teacher-scores`)")
    entry = m["splits"].get(split.name)
    if entry is None or not (d / f"{split.name}.npy").is_file():
        raise DatasetError(f"{d} has no scores of the {split.name!r} split")
    if entry["n"] != len(split) or entry["digest"] != rows_digest(split):
        raise DatasetError(
            f"{d}: the teacher scored other rows ({entry['n']} rows, cut from {m.get('source')}) than this "
            f"{split.name!r} split ({len(split)} rows): cut both crop sets from the same sampled grasps"
        )
    scores = np.load(d / f"{split.name}.npy", mmap_mode="r")
    if scores.shape != (len(split),) or scores.dtype != np.float32:
        raise DatasetError(f"{d}/{split.name}.npy: {scores.shape} {scores.dtype}, expected ({len(split)},) float32")
    if m["teacher"].get("class_balance", "none") == "none":
        return scores
    if weights is None:
        raise ValueError("a class-balanced teacher's scores need the class weights to become posteriors")
    w0, w1 = float(weights[0]), float(weights[1])
    p = np.asarray(scores, dtype=np.float64)
    return (w0 * p / (w0 * p + w1 * (1.0 - p))).astype(np.float32)
