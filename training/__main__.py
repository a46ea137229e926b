"""Command line: ``python -m training {train,evaluate,baseline,ablation,label-noise,centroid-probe,stacker,placement-drift,bench} ...``.

Training options are generated from ``TrainConfig`` (``--batch-size``, ``--base-lr``, ...)
by the shared bridge ``vgq.cli_config``, so the dataclass stays the one place where they
are defined. Bad input (missing folder, wrong format, architecture unsuited to the
dataset, bad option value) exits with status 2 and a message naming the problem. Under ``torchrun`` ``train`` and ``ablation`` run DDP.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from vgq.cli_config import add_options, build

from .baseline import BaselineConfig
from .config import TrainConfig


def _add_dataclass_options(p: argparse.ArgumentParser, cls) -> None:
    add_options(p, cls)  # choices from the fields' metadata


def _config_from(args, cls):
    return build(cls, args)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="python -m training",
        description="Train, evaluate and compare VGQ-CNN / Fast-VGQ-CNN / GQ-CNN on crop datasets.",
    )
    sub = ap.add_subparsers(dest="command", required=True)

    t = sub.add_parser("train", help="train a network on a crop dataset")
    t.add_argument("--data", required=True, help="crop dataset folder (vgq-crops)")
    t.add_argument("--out", required=True, help="run folder (checkpoints, metrics.jsonl, run.json)")
    t.add_argument("--resume", action="store_true", help="continue from OUT/checkpoints/last.pt")
    t.add_argument("--no-progress", action="store_true")
    _add_dataclass_options(t, TrainConfig)

    e = sub.add_parser("evaluate", help="metrics, camera-grid heat maps and curves of a run")
    e.add_argument("--run", required=True, help="run folder (uses checkpoints/best.pt) or a checkpoint file")
    e.add_argument("--data", required=True, help="crop dataset folder")
    e.add_argument("--split", default="test", choices=("train", "val", "test"))
    e.add_argument("--out", default=None, help="output folder (default RUN/eval)")
    e.add_argument(
        "--name",
        default=None,
        help="name of the result (metrics_NAME.json; default the split), e.g. test_clean for a clean-sensor "
        "copy of the test split (`datagen crops --splits test --sensor clean`)",
    )
    e.add_argument("--threshold", type=float, default=0.5)
    e.add_argument("--batch-size", type=int, default=64)
    e.add_argument(
        "--max-n",
        type=int,
        default=0,
        help="evaluate this many rows drawn at random (--seed) from the split (default 0: all; a clean copy "
        "of the split gets the same rows)",
    )
    e.add_argument("--seed", type=int, default=0)
    e.add_argument("--no-progress", action="store_true")

    k = sub.add_parser(
        "teacher-scores", help="a trained run's scores of a crop split's rows, for a student (--target teacher)"
    )
    k.add_argument("--run", required=True, help="the teacher: run folder (its best.pt) or a checkpoint file")
    k.add_argument("--data", required=True, help="crop dataset the teacher was trained on (its crops of the rows)")
    k.add_argument("--out", required=True, help="scores folder (resumes a part-scored one)")
    k.add_argument("--split", default="train", choices=("train", "val", "test"))
    k.add_argument("--max-rows", type=int, default=0, help="stop after this many rows of the seeded order (0: all)")
    k.add_argument("--batch-size", type=int, default=256)
    k.add_argument(
        "--precision", default="auto", choices=("fp32", "bf16", "auto"), help="'auto': bf16 on a CPU with native bf16"
    )
    k.add_argument("--seed", type=int, default=0)
    k.add_argument("--no-progress", action="store_true")

    b = sub.add_parser("baseline", help="pose-only baseline (no image)")
    b.add_argument("--data", required=True, help="crop dataset folder")
    b.add_argument("--out", default=None, help="folder for baseline_<model>.json and its heat map")
    b.add_argument("--no-progress", action="store_true")
    _add_dataclass_options(b, BaselineConfig)

    a = sub.add_parser("ablation", help="train + evaluate on crop datasets of several kappa values")
    a.add_argument("--data", required=True, nargs="+", help="crop dataset folders, one per kappa")
    a.add_argument("--out", required=True, help="ablation folder (one run folder per kappa)")
    a.add_argument("--no-progress", action="store_true")
    _add_dataclass_options(a, TrainConfig)

    n = sub.add_parser("label-noise", help="the balanced accuracy / AUC ceiling the physics label's trial noise sets")
    n.add_argument("--data", required=True, help="crop dataset folder (physics label)")
    n.add_argument("--split", default="test", choices=("train", "val", "test"))

    c = sub.add_parser(
        "centroid-probe", help="what a grasp's offset from the object's visible centroid adds to a model's score"
    )
    c.add_argument("--sampled", required=True, help="sampled dataset folder (datagen sample) the crops were cut from")
    c.add_argument("--crops", required=True, help="its crop dataset folder (the test split is probed)")
    c.add_argument("--model-dir", required=True, help="exported Fast-VGQ-CNN folder")
    c.add_argument("--per-object", type=int, default=1500, help="grasps drawn per object (default 1500)")
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--json", help="also write the result here")

    from .stacker import BALANCES

    st = sub.add_parser(
        "stacker", help="fit a placement stacker on a model's scores and write the stacked model folder"
    )
    st.add_argument("--model-dir", required=True, help="exported Fast-VGQ-CNN folder (its head reads no placement)")
    st.add_argument("--fit", nargs="+", required=True, help="crop dataset(s) of objects the model never saw, to fit on")
    st.add_argument("--judge", nargs="+", required=True, help="crop dataset(s) of other such objects, to judge on")
    st.add_argument("--out", required=True, help="the stacked model folder to write")
    st.add_argument("--split", default="test", choices=("train", "val", "test"))
    st.add_argument("--per-object", type=int, default=1500, help="rows drawn per object (default 1500)")
    st.add_argument("--hidden", type=int, default=32, help="units of each of the MLP's two hidden layers")
    st.add_argument("--epochs", type=int, default=8)
    st.add_argument(
        "--balance",
        default="family",
        choices=BALANCES,
        help="loss weights: each family's positives and negatives alike (default), or all positives against all negatives",
    )
    st.add_argument("--seed", type=int, default=0)
    st.add_argument(
        "--test",
        help="crop dataset whose test split the stacked graphs are measured on, as the card's metrics.test "
        "(the unstacked model's move to metrics.before_stacker), e.g. the recipe's crops",
    )
    st.add_argument("--test-clean", help="the same grasps without the sensor model: the card's metrics.test_clean")
    st.add_argument("--test-max-n", type=int, default=50_000, help="test rows drawn at random (default 50000)")

    d = sub.add_parser(
        "placement-drift", help="how far the sensor model moves the placement rows (clean vs sensor crops)"
    )
    d.add_argument(
        "--clean", required=True, help="crop dataset cut on clean renders (e.g. the recipe's crops_clean_test)"
    )
    d.add_argument("--sensor", required=True, help="crop dataset of the same sampled grasps with the sensor model")
    d.add_argument("--split", default="test", choices=("train", "val", "test"))
    d.add_argument("--max-n", type=int, default=200_000, help="rows drawn at random (0: all; default 200000)")
    d.add_argument("--seed", type=int, default=0)

    s = sub.add_parser("bench", help="training throughput (samples/s) of full SGD steps on this CPU")
    s.add_argument("--arch", default="fast_vgqcnn", choices=("fast_vgqcnn", "vgqcnn", "gqcnn"))
    s.add_argument("--batch-size", type=int, default=64)
    s.add_argument("--steps", type=int, default=20)
    s.add_argument("--warmup", type=int, default=3)
    s.add_argument("--threads", type=int, default=0, help="torch threads; 0: torch default")
    s.add_argument(
        "--precision",
        nargs="+",
        default=["fp32"],
        choices=("fp32", "bf16"),
        help="measure these side by side (e.g. --precision fp32 bf16)",
    )
    s.add_argument("--optimizer", default="adamw", choices=("sgd", "adamw"))
    s.add_argument(
        "--predict-rows",
        type=int,
        default=0,
        help="also time the forward-only pass of validation / evaluation over this many rows (0: skip)",
    )
    s.add_argument("--predict-batch-sizes", type=int, nargs="+", default=[64, 1024])
    s.add_argument("--no-progress", action="store_true")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    progress = not getattr(args, "no_progress", False)
    try:
        if args.command == "train":
            from .train import train

            r = train(_config_from(args, TrainConfig), args.data, args.out, resume=args.resume, progress=progress)
            print(
                json.dumps(
                    {
                        "run": str(r.run_dir),
                        "steps": r.steps,
                        "samples_seen": r.samples_seen,
                        "best_val_balanced_accuracy": None
                        if r.best_val_balanced_accuracy != r.best_val_balanced_accuracy
                        else r.best_val_balanced_accuracy,
                        "wall_time_s": round(r.wall_time_s, 1),
                    }
                )
            )
        elif args.command == "evaluate":
            from .evaluate import evaluate

            rec = evaluate(
                args.run,
                args.data,
                args.split,
                args.out,
                threshold=args.threshold,
                batch_size=args.batch_size,
                progress=progress,
                name=args.name,
                max_n=args.max_n,
                seed=args.seed,
            )
            print(json.dumps({"split": rec["split"], "name": rec["name"], "sensor": rec["sensor"], **rec["overall"]}))
            for fam, m in rec["by_family"].items():
                print(json.dumps({"family": fam, **m}))
            for key, what in (
                ("by_camera_distance_m", "camera_d_m"),
                ("by_camera_elevation_deg", "camera_phi_deg"),
                ("by_approach_psi_deg", "approach_psi_deg"),
                ("by_approach_beta_deg", "approach_beta_deg"),
                ("by_window_offset_px", "window_offset_px"),
            ):
                for b, m in rec[key].items():
                    print(json.dumps({what: b, **m}))
        elif args.command == "teacher-scores":
            from .teacher import score_teacher
            from .train import resolve_precision

            m = score_teacher(
                args.run,
                args.data,
                args.out,
                args.split,
                max_rows=args.max_rows,
                batch_size=args.batch_size,
                bf16=resolve_precision(args.precision) == "bf16",
                seed=args.seed,
                progress=progress,
            )
            print(json.dumps({"out": args.out, **m["splits"][args.split]}))
        elif args.command == "baseline":
            from .baseline import run_baseline

            rec = run_baseline(args.data, _config_from(args, BaselineConfig), args.out, progress=progress)
            print(json.dumps({k: rec[k] for k in ("config", "val", "test") if k in rec}))
        elif args.command == "ablation":
            from .ablation import run_ablation

            rec = run_ablation(args.data, args.out, _config_from(args, TrainConfig), progress=progress)
            print(json.dumps(rec["results"]))
        elif args.command == "label-noise":
            from dataclasses import asdict

            from .label_noise import dataset_ceiling

            c = dataset_ceiling(args.data, args.split)
            print(json.dumps({"split": args.split, **asdict(c)}))
        elif args.command == "centroid-probe":
            from .centroid_probe import probe, table

            if args.per_object < 1:
                raise ValueError(f"--per-object must be >= 1, got {args.per_object}")
            rec = probe(args.sampled, args.crops, args.model_dir, args.per_object, args.seed)
            print(table(rec))
            if args.json:
                from vgq import atomic

                atomic.write_json(args.json, rec)
        elif args.command == "stacker":
            from datagen import storage

            from .stacker import measure, run
            from .stacker import table as stacker_table

            opts = ("split", "per_object", "hidden", "epochs", "seed", "balance")
            if args.test_max_n < 1:
                raise ValueError(f"--test-max-n must be >= 1, got {args.test_max_n}")
            for c in (args.test, args.test_clean):
                if c is not None and not (Path(c) / storage.MANIFEST).is_file():
                    raise ValueError(f"{c}: not a crop dataset (no manifest.json)")
            rec = run(args.model_dir, args.fit, args.judge, args.out, **{k: getattr(args, k) for k in opts})
            print(stacker_table(rec))
            for key, c in (("test", args.test), ("test_clean", args.test_clean)):
                if c is not None:
                    m = measure(args.out, c, key, args.test_max_n)
                    print(
                        f"{key} ({c}, {m['n']} rows, stacked graphs): balanced accuracy "
                        f"{100 * m['balanced_accuracy']:.1f}%, TPR {100 * m['tpr']:.1f}%, TNR {100 * m['tnr']:.1f}%"
                    )
            print(f"-> {args.out}")
        elif args.command == "placement-drift":
            from .placement_drift import compare
            from .placement_drift import table as drift_table

            if args.max_n < 0:
                raise ValueError(f"--max-n must be >= 0, got {args.max_n}")
            print(drift_table(compare(args.clean, args.sensor, args.split, args.max_n, args.seed)))
        elif args.command == "bench":
            from .bench import measure_predict_throughput, measure_train_throughput

            rec = measure_train_throughput(
                args.arch, args.batch_size, args.steps, args.warmup, args.threads, tuple(args.precision), args.optimizer
            )
            if args.predict_rows:
                rec["predict_rows_per_s"] = measure_predict_throughput(
                    args.arch, args.predict_rows, tuple(args.predict_batch_sizes), tuple(args.precision), args.threads
                )
            print(json.dumps(rec))
    except (ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
