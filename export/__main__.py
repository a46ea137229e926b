"""``vgq-export`` / ``python -m export``: trained run -> verified ONNX model folder.

    python -m export --run runs/fast --data data/crops_fast --out models/fast-vgqcnn-default

Verification inputs are real crops and poses from the dataset's test split (else val, else
train). Nothing is written unless onnxruntime matches torch within the tolerance.
The card also records a calibration of the probabilities (``export.calibrate``): fitted on
the val split for the dataset's positivity before sampling, its ECE measured on the test split.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

from export.leave_family_out import leave_family_out_metrics
from vgq import atomic
from vgq.camera import Intrinsics
from vgq.crop import CropGeometry


def _baselines(files: list[str], data_path) -> dict:
    """``{"baseline_<model>": {"test": metrics, "columns": [...]}}`` from baseline result files,
    refusing one computed on another dataset (its test split would not be ours)."""
    out = {}
    for f in files:
        try:
            r = json.loads(Path(f).read_text())
            model, test, data = r["config"]["model"], r["test"], r["data"]
        except (OSError, json.JSONDecodeError, KeyError, TypeError) as e:
            raise ValueError(f"--baseline {f}: not a baseline result ({e})") from None
        if Path(data).resolve() != Path(data_path).resolve():
            raise ValueError(f"--baseline {f}: computed on {data}, not on {data_path}")
        out[f"baseline_{model}"] = {"test": test, "columns": r.get("columns")}
    return out


def _copy_baseline_models(files: list[str], out: str) -> None:
    """Copy each baseline result's model file (``baseline_<model>.npz`` beside its json,
    :mod:`vgq.pose_only`) into the model folder, where planning's benchmark ranks grasps
    with it; a result without one (made before the file existed) is skipped with a log line."""
    from vgq.pose_only import PoseOnlyError, PoseOnlyModel

    for f in files:
        npz = Path(f).with_suffix(".npz")
        if not npz.exists():
            logging.info(
                "--baseline %s: no model file %s beside it (rerun `training baseline` to get one)", f, npz.name
            )
            continue
        try:
            PoseOnlyModel.load(npz)
        except PoseOnlyError as e:
            raise ValueError(f"--baseline {f}: {e}") from None
        atomic.write_bytes(Path(out) / npz.name, npz.read_bytes())


def _leave_family_out(path: str | None) -> dict:
    """``{"leave_family_out": metrics}`` from a `training evaluate` result of a leave-family-out run
    (``export.leave_family_out``: its held-out families' rows together, and each of them)."""
    if path is None:
        return {}
    try:
        return {"leave_family_out": leave_family_out_metrics(path)}
    except ValueError as e:
        raise ValueError(f"--leave-family-out {e}") from None


def _sample(ds, order: tuple[str, ...], n: int, seed: int, arch: str, placement: bool = False):
    """(split, crops, poses, labels) as numpy: ``n`` random rows of the first non-empty split in ``order``
    (``placement``: each pose row followed by its placement row, as a placement head reads them)."""
    from training.data import DatasetError

    split = next((ds.splits[s] for s in order if s in ds.splits and len(ds.splits[s])), None)
    if split is None:
        raise DatasetError(f"{ds.path}: no non-empty split among {order}")
    idx = np.sort(np.random.default_rng(seed).choice(len(split), min(n, len(split)), replace=False))
    return (split, *(t.numpy() for t in split.batch(idx, arch, placement=placement)))


def _add_int8_encoder(out: str, ds, arch: str, n_check: int, seed: int, prune_crops, placement: bool = False) -> None:
    """Calibrate an int8 encoder on train crops, check it on val (else test) crops, add it to
    ``out`` when it passes (``export.int8_encoder``); a refusal is logged, not an error.
    ``prune_crops``: train crops that find the dead channels removed first (None: no pruning)."""
    from .int8_encoder import add_int8_encoder
    from .quantize import QuantizationError

    calib = _sample(ds, ("train",), 2048, seed, arch, placement)
    chk, *labelled = _sample(ds, ("val", "test"), n_check, seed, arch, placement)
    logging.info(
        "int8 encoder: calibrating on %d %s crops, checking on %d %s crops",
        len(calib[1]),
        calib[0].name,
        len(labelled[0]),
        chk.name,
    )
    try:
        r = add_int8_encoder(
            out,
            calib[1],
            tuple(labelled),
            check_data=f"{ds.path} ({chk.name}, {len(labelled[0])} crops)",
            calibration=f"{ds.path} ({calib[0].name}, {len(calib[1])} crops)",
            prune=prune_crops is not None,
            prune_crops=prune_crops,
        )
    except QuantizationError as e:
        logging.warning("int8 encoder refused, not written: %s", e)
        return
    logging.info(
        "int8 encoder: balanced accuracy %.4f (fp32 %.4f), mean |dp| %.4f, %d of %d decisions changed",
        r.balanced_accuracy_variant,
        r.balanced_accuracy_fp32,
        r.mean_abs_diff_probability,
        r.decisions_changed,
        r.n,
    )


def main(argv=None) -> None:
    p = argparse.ArgumentParser(
        prog="vgq-export", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--run", required=True, help="training run folder (or a checkpoint file)")
    p.add_argument("--data", required=True, help="crop dataset the run was trained on (verification inputs)")
    p.add_argument("--out", required=True, help="model folder to write (replaced atomically)")
    p.add_argument("--verify-n", type=int, default=64, help="number of real inputs to verify on (default 64)")
    p.add_argument("--tolerance", type=float, default=1e-4, help="max abs probability difference (default 1e-4)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--recipe", help="how the dataset was built (a command line), recorded in the model card")
    p.add_argument(
        "--baseline",
        action="append",
        default=[],
        metavar="JSON",
        help="a `python -m training baseline` result on the same data; its test metrics go into "
        "the card's metrics as baseline_<model>, and its model file (baseline_<model>.npz beside it) is copied "
        "into the model folder (repeatable)",
    )
    p.add_argument(
        "--leave-family-out",
        metavar="JSON",
        help="a `python -m training evaluate` result (metrics_test.json) of the leave-family-out run; its "
        "held-out families' metrics go into the card's metrics as leave_family_out",
    )
    p.add_argument(
        "--int8-head",
        action="store_true",
        help="also write head_int8.onnx (fc5 in int8, ~2x faster) if it scores like the fp32 head on "
        "labelled validation crops",
    )
    p.add_argument("--int8-check-n", type=int, default=4096, help="labelled crops for the int8 check (default 4096)")
    p.add_argument(
        "--no-prune",
        action="store_true",
        help="quantise the whole head and encoder; by default their dead ReLU units and channels (never active "
        "on --prune-calibration-n train crops) are removed first, and each pruned graph is checked against the "
        "unpruned one (export.prune_head, export.prune_encoder)",
    )
    p.add_argument(
        "--prune-calibration-n",
        type=int,
        default=50000,
        help="train crops that find the dead units and channels (default 50000)",
    )
    p.add_argument(
        "--int8-encoder",
        action="store_true",
        help="also write encoder_int8.onnx (static int8, calibrated on up to 2048 train crops) if it scores "
        "like the fp32 encoder on the val (else test) crops; a refused one is reported and left out "
        "(the fp32 export stands). Existing folders: python -m export.int8_encoder",
    )
    c = p.add_argument_group("calibration (fitted on the val split, ECE measured on the test split)")
    c.add_argument("--no-calibration", action="store_true", help="export without a calibration")
    c.add_argument("--calibration-method", choices=("platt", "temperature"), default="platt")
    c.add_argument(
        "--native-positivity",
        type=float,
        metavar="FRACTION",
        help="positivity to calibrate for (default: the dataset's before sampling, from its manifests)",
    )
    c.add_argument("--calibration-n", type=int, default=10000, help="max rows of each split (default 10000; 0: all)")
    c.add_argument(
        "--reliability-png",
        metavar="PATH",
        help="also copy the reliability diagram here (e.g. docs/img/reliability_diagram.png)",
    )
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[export] %(message)s")
    if a.verify_n < 1:
        p.error("--verify-n must be >= 1")
    if a.int8_check_n < 100:
        p.error("--int8-check-n must be >= 100")
    if a.prune_calibration_n < 16:
        p.error("--prune-calibration-n must be >= 16")
    if a.native_positivity is not None and not 0 < a.native_positivity < 1:
        p.error("--native-positivity must be a fraction in (0, 1)")
    if a.calibration_n < 0:
        p.error("--calibration-n must be >= 0")

    from training.checkpoint import CheckpointError, load_trained
    from training.data import DatasetError, open_crop_dataset

    from .calibrate import DIAGRAM, CalibrationError, calibrate_on_dataset
    from .onnx_export import ExportError, export_model

    t0 = time.perf_counter()
    try:
        logging.info("loading %s", a.run)
        net, meta = load_trained(a.run)
        ds = open_crop_dataset(a.data)
        place = bool(net.n_place)
        split, crops, poses, _ = _sample(ds, ("test", "val", "train"), a.verify_n, a.seed, meta["arch"], place)
        int8 = prune_calibration = None
        if not a.no_prune and (a.int8_head or a.int8_encoder):  # (crops, poses) that find the dead units, once
            prune_calibration = tuple(_sample(ds, ("train",), a.prune_calibration_n, a.seed, meta["arch"], place)[1:3])
        if a.int8_head:
            chk, *labelled = _sample(ds, ("val", "test", "train"), a.int8_check_n, a.seed, meta["arch"], place)
            int8 = tuple(labelled)
            logging.info("int8 head check on %d %s crops", len(labelled[0]), chk.name)
        if a.recipe:
            meta["dataset"]["recipe"] = a.recipe
        meta["metrics"].update(_baselines(a.baseline, ds.path))
        meta["metrics"].update(_leave_family_out(a.leave_family_out))
        calibration = None
        if not a.no_calibration:
            calibration = calibrate_on_dataset(
                net, ds, meta, a.calibration_method, a.native_positivity, a.calibration_n, a.seed
            )
        logging.info("exporting %s, verifying on %d %s crops", meta["arch"], len(crops), split.name)
        card = export_model(
            net,
            a.out,
            crops,
            poses,
            geometry=CropGeometry.from_dict(meta["geometry"]),
            intrinsics=Intrinsics.from_dict(meta["intrinsics"]),
            dataset=meta["dataset"],
            training=meta["training"],
            metrics=meta["metrics"],
            label_threshold=float(meta.get("label_threshold", 0.002)),
            tolerance=a.tolerance,
            int8_check=int8,
            calibration=calibration,
            prune_calibration=prune_calibration if a.int8_head else None,
        )
        _copy_baseline_models(a.baseline, a.out)
        if a.int8_encoder:
            prune_crops = None if prune_calibration is None else prune_calibration[0]
            _add_int8_encoder(a.out, ds, meta["arch"], a.int8_check_n, a.seed, prune_crops, place)
        if calibration is not None and a.reliability_png:
            atomic.write_bytes(a.reliability_png, (Path(a.out) / DIAGRAM).read_bytes())
    except CalibrationError as e:
        print(f"vgq-export: calibration: {e} (--no-calibration exports without one)", file=sys.stderr)
        sys.exit(2)
    except (CheckpointError, DatasetError, ExportError, FileNotFoundError, ValueError) as e:
        print(f"vgq-export: {e}", file=sys.stderr)
        sys.exit(2)
    v = card.export["verification"]
    logging.info(
        "wrote %s (%s) in %.1f s; max |p_onnx - p_torch| = %.2e",
        a.out,
        card.model_version,
        time.perf_counter() - t0,
        v["max_abs_diff_probability"],
    )
    if "int8_head" in card.export:
        q = card.export["int8_head"]
        logging.info(
            "int8 head: balanced accuracy %.4f (fp32 %.4f), max |p_int8 - p_fp32| = %.4f, %d of %d decisions changed",
            q["balanced_accuracy_int8"],
            q["balanced_accuracy_fp32"],
            q["max_abs_diff_probability"],
            q["decisions_changed"],
            q["n"],
        )
        if "pruning" in q:
            pr = q["pruning"]
            logging.info(
                "int8 head pruned: fc4 keeps %d, fc5 keeps %d of %d units; max |p_pruned - p_full| = %.2e on %d pairs",
                pr["units"]["fc4_units_kept"],
                pr["units"]["fc5_units_kept"],
                pr["units"]["units"],
                pr["max_abs_diff_probability"],
                pr["n_pairs"],
            )
    if card.calibration:
        k = card.calibration
        logging.info(
            "calibration (%s, for positivity %.4f: %s): ECE on %s %.4f raw -> %.4f calibrated",
            k["method"],
            k["target_positivity"],
            k["target_positivity_source"],
            k["test"]["split"],
            k["test"]["ece_raw"],
            k["test"]["ece_calibrated"],
        )


if __name__ == "__main__":
    main()
