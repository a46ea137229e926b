"""Add a checked int8 encoder (``encoder_int8.onnx``) to an exported Fast-VGQ-CNN model folder.

    python -m export.int8_encoder --model-dir models/fast-vgqcnn-default \\
        --calibration data/calib/crops --check data/calib/crops

Calibration crops: the ``train`` split of a crop dataset (``datagen crops --arch fast_vgqcnn``).
Check crops: the ``val`` and ``test`` splits of a crop dataset (objects the calibration did
not see), or a .npz with ``images`` (n, 1, S, S), ``poses`` (n, 7) and ``labels`` (n,). The
variant is written and recorded in the model card (``files.encoder_int8``,
``export.int8_encoder``) only if it passes ``export.quantize.check_encoder_variant``; the
service then measures it against fp32 at start-up (``encoder_precision auto``).
"""

from __future__ import annotations

import argparse
import hashlib
import logging
import sys
import tempfile
from pathlib import Path

import numpy as np

from vgq import atomic
from vgq.model_card import ModelCard

from .quantize import EncoderCheck, QuantizationError, check_encoder_variant, quantize_encoder

INT8_ENCODER_FILE = "encoder_int8.onnx"


def crop_split(path: str | Path, splits: tuple[str, ...], n: int | None = None, seed: int = 0, placement: bool = False):
    """(crops (n, 1, S, S), poses (n, 7), labels (n,)) as numpy: up to ``n`` random rows of the
    named splits of a Fast-VGQ-CNN crop dataset, or all rows of a .npz (images, poses, labels);
    ``placement`` (a dataset): each pose row followed by its placement row (a placement head's input)."""
    path = Path(path)
    if path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:
            try:
                return z["images"].astype(np.float32), z["poses"].astype(np.float32), z["labels"].astype(np.uint8)
            except KeyError as e:
                raise ValueError(f"{path}: no {e} array (expected images, poses, labels)") from None
    from training.data import open_crop_dataset

    ds = open_crop_dataset(path)
    present = [ds.splits[name] for name in splits if ds.splits.get(name) is not None and len(ds.splits[name])]
    if not present:
        raise ValueError(f"{path}: none of the splits {splits} holds crops")
    sizes = np.array([len(sp) for sp in present])
    rows = np.arange(sizes.sum())
    if n is not None and len(rows) > n:  # choose the rows first: only those are read (a split may be GBs)
        rows = np.sort(np.random.default_rng(seed).choice(len(rows), n, replace=False))
    starts = np.concatenate([[0], np.cumsum(sizes)])
    parts = [
        [t.numpy() for t in sp.batch(rows[(rows >= lo) & (rows < hi)] - lo, "fast_vgqcnn", placement=placement)]
        for sp, lo, hi in zip(present, starts[:-1], starts[1:])
        if np.any((rows >= lo) & (rows < hi))
    ]
    crops, poses, labels = (np.concatenate([p[i] for p in parts]) for i in range(3))
    return crops.astype(np.float32), poses.astype(np.float32), labels


def variant_parser(prog: str, doc: str, model_help: str, calibration_help: str, calibration_n: int):
    """The shared command line of the tools that rebuild a folder's graph from calibration and
    check crops (export.int8_encoder, export.prune_head, export.prune_encoder)."""
    p = argparse.ArgumentParser(prog=prog, description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model-dir", required=True, help=model_help)
    p.add_argument("--calibration", required=True, help=f"crop dataset (its train split) or .npz: {calibration_help}")
    p.add_argument("--check", required=True, help="crop dataset (its val + test splits) or .npz of labelled crops")
    p.add_argument(
        "--calibration-n", type=int, default=calibration_n, help=f"calibration crops (default {calibration_n})"
    )
    p.add_argument(
        "--check-n",
        type=int,
        default=0,
        help="check crops of a dataset: that many random val + test rows (seed 0); 0 = all (default)",
    )
    return p


def parse_variant_args(p: argparse.ArgumentParser, argv, log_name: str) -> argparse.Namespace:
    """Parse and check ``variant_parser``'s arguments (exit 2 naming the problem); logging on."""
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format=f"[{log_name}] %(message)s")
    if a.calibration_n < 16:
        p.error("--calibration-n must be >= 16")
    if a.check_n < 0:
        p.error("--check-n must be >= 0")
    if not (Path(a.model_dir) / "model_card.json").is_file():
        p.error(f"--model-dir {a.model_dir!r} holds no model_card.json")
    if Path(a.check).resolve() == Path(a.calibration).resolve() and Path(a.check).suffix == ".npz":
        p.error("--check must not be the calibration crops")
    return a


#: the most check rows a whole dataset may hand these tools without --check-n (their crops and
#: encodings are held in memory: a jaw-grid encoding is 17,408 floats)
MAX_CHECK_ROWS = 50_000


def check_crops(path: str, model_dir: str | Path, n: int = 0) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], str]:
    """The labelled check crops of ``path`` (a dataset's val + test splits, ``n`` > 0: that many random
    rows of them, seed 0; or a .npz) and their label, with placement rows where ``model_dir``'s head
    reads them."""
    place = bool(ModelCard.load(model_dir).placement_columns)
    if not Path(path).is_dir():
        return crop_split(path, ("val", "test"), placement=place), path
    if not n:
        from training.data import open_crop_dataset

        total = sum(len(sp) for name, sp in open_crop_dataset(path).splits.items() if name in ("val", "test") and sp)
        if total > MAX_CHECK_ROWS:
            raise ValueError(
                f"--check {path} holds {total:,} val + test rows, more than {MAX_CHECK_ROWS:,} to score at once; "
                "pass --check-n (e.g. 4096) to check on a random sample of them"
            )
    rows = f"{n} random val + test rows, seed 0" if n else "val + test"
    return crop_split(path, ("val", "test"), n or None, placement=place), f"{path} ({rows})"


def add_int8_encoder(
    model_dir: str | Path,
    calibration_crops: np.ndarray,
    check: tuple[np.ndarray, np.ndarray, np.ndarray],
    check_data: str = "",
    calibration: str = "",
    prune: bool = True,
    prune_crops: np.ndarray | None = None,
) -> EncoderCheck:
    """Quantise the folder's encoder, check it, and only then move ``encoder_int8.onnx`` into the
    folder and record it in the card (both writes atomic). Raises QuantizationError when refused.

    ``prune``: the quantised encoder loses its dead channels (``export.prune_encoder``, measured on
    ``prune_crops``, default the calibration crops); the pruned graph must score like the whole
    int8 graph on ``check`` within the tighter PRUNE_* bounds, then like fp32 as usual."""
    from .prune_encoder import prune_encoder

    model_dir = Path(model_dir)
    card = ModelCard.load(model_dir)
    if card.architecture != "fast_vgqcnn":
        raise QuantizationError(f"{model_dir}: an int8 encoder exists for fast_vgqcnn only, not {card.architecture}")
    encoder, head = model_dir / card.files["encoder"], model_dir / card.files["head"]
    pruning = None
    with atomic.staged(model_dir / INT8_ENCODER_FILE) as tmp:
        with tempfile.TemporaryDirectory(prefix=".prune-", dir=model_dir) as work:
            if prune:  # quantise the whole encoder, then drop the channels dead in the int8 graph
                whole = Path(work) / "encoder_int8_whole.onnx"
                nodes = quantize_encoder(encoder, whole, calibration_crops)
                crops = calibration_crops if prune_crops is None else prune_crops
                pruning = prune_encoder(whole, tmp, head, crops, check, check_data)
                logging.info("dead channels removed (kept / total per ReLU): %s", pruning["kept"])
            else:
                nodes = quantize_encoder(encoder, tmp, calibration_crops)
        result = check_encoder_variant(
            encoder,
            tmp,
            head,
            *check,
            precision="int8",
            quantized_nodes=nodes,
            check_data=check_data,
            calibration=calibration,
        )
        digest = hashlib.sha256(tmp.read_bytes()).hexdigest()
    import onnxruntime as ort

    card.files["encoder_int8"] = INT8_ENCODER_FILE
    card.export["int8_encoder"] = {
        **result.to_dict(),
        "sha256": digest,
        "onnxruntime": ort.__version__,
        "n_calibration": int(len(calibration_crops)),
        **({"pruning": pruning} if pruning else {}),
    }
    card.save(model_dir)
    return result


def main(argv=None) -> EncoderCheck:
    p = variant_parser(
        "python -m export.int8_encoder",
        __doc__,
        "exported Fast-VGQ-CNN model folder (updated in place)",
        "calibrates the activation ranges",
        2048,
    )
    p.add_argument(
        "--prune-n",
        type=int,
        default=50000,
        help="train crops that find the dead channels (default 50000); the encoder is quantised with them removed",
    )
    p.add_argument("--no-prune", action="store_true", help="quantise every channel (export.prune_encoder not applied)")
    p.add_argument("--seed", type=int, default=0)
    a = parse_variant_args(p, argv, "int8-encoder")
    if a.prune_n < 16:
        p.error("--prune-n must be >= 16")
    try:
        prune_crops = None if a.no_prune else crop_split(a.calibration, ("train",), a.prune_n, a.seed)[0]
        calib = crop_split(a.calibration, ("train",), a.calibration_n, a.seed)[0]
        check, check_data = check_crops(a.check, a.model_dir, a.check_n)
        logging.info(
            "calibrating on %d crops of %s, checking on %d crops of %s",
            len(calib),
            a.calibration,
            len(check[0]),
            a.check,
        )
        result = add_int8_encoder(
            a.model_dir,
            calib,
            check,
            check_data=check_data,
            calibration=f"{a.calibration} (train, {len(calib)} crops)",
            prune=not a.no_prune,
            prune_crops=prune_crops,
        )
    except (QuantizationError, ValueError, FileNotFoundError) as e:
        print(f"int8-encoder: {e}", file=sys.stderr)
        sys.exit(2)
    logging.info(
        "int8 encoder kept: balanced accuracy %.4f (fp32 %.4f), mean |dp| %.4f, max %.4f, %d of %d decisions changed",
        result.balanced_accuracy_variant,
        result.balanced_accuracy_fp32,
        result.mean_abs_diff_probability,
        result.max_abs_diff_probability,
        result.decisions_changed,
        result.n,
    )
    return result


if __name__ == "__main__":
    main()
