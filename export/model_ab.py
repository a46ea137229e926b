"""Two model folders' served graphs side by side: speed and agreement, in one interleaved run.

    python -m export.model_ab BEFORE_DIR AFTER_DIR [--k 128] [--rounds 40] [--calls 20] [--encoder-precision int8]

Each folder is opened as the service opens it (``service.runtime.FastModel``: head precision
``auto``, the given encoder precision, one onnxruntime thread); its encoder (one crop) and head
(one image term, k grasps of the held-out crops) are timed, the folders taking turns every
``--calls`` calls (load from other processes hits both alike). Agreement: the held-out crops
(examples/heldout_test_crops.npz) through each folder's own encoder and head, each grasp scored
alone: max |dp| and decisions changed (a placement head's rows "not known": the crops carry
none). Used to measure rebuilt graphs (``export.prune_head``, ``export.prune_encoder``, a new
``export.graphs`` layout) against the ones they replace.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from vgq.placement import unknown_rows

HELDOUT = Path(__file__).resolve().parent.parent / "examples" / "heldout_test_crops.npz"


def compare(
    a_dir, b_dir, k: int = 128, rounds: int = 40, calls: int = 20, encoder_precision: str = "auto", heldout=HELDOUT
) -> dict:
    """Median encoder and head ms of each folder (interleaved) and their agreement on ``heldout``."""
    from service.runtime import FastModel

    models = {n: FastModel(d, threads=1, encoder_precision=encoder_precision) for n, d in (("a", a_dir), ("b", b_dir))}
    with np.load(heldout) as z:
        crops, poses = z["images"][:, 0], z["poses"].astype(np.float32)
    # a placement head reads a placement row after the pose columns: the held-out crops carry none, so
    # each grasp gets "not known" (all 0, vgq.placement.unknown_rows), what the service sends without a table
    rows = {n: np.c_[poses, unknown_rows(len(poses))[:, : m.n_pose - poses.shape[1]]] for n, m in models.items()}
    p = {}
    for n, m in models.items():
        terms = m.encode(crops)
        p[n] = np.concatenate([m.score(terms[i : i + 1], rows[n][i : i + 1]) for i in range(len(poses))])
    grasps = {n: np.resize(r, (k, r.shape[1])) for n, r in rows.items()}  # k grasps: repeated if fewer
    times = {(n, part): [] for n in models for part in ("encoder", "head")}
    for _ in range(rounds):
        for n, m in models.items():
            term = m.encode(crops[0])
            for part, fn, args in (("encoder", m.encode, (crops[0],)), ("head", m.score, (term, grasps[n]))):
                for _ in range(calls):
                    t = time.perf_counter()
                    fn(*args)
                    times[n, part].append(time.perf_counter() - t)
    med = {key: float(np.median(t)) * 1e3 for key, t in times.items()}
    out = {
        n: {
            "model_dir": str(d),
            "head_precision": models[n].head_precision,
            "encoder_precision": models[n].encoder_precision,
            "encoder_ms": med[n, "encoder"],
            "head_ms": med[n, "head"],
        }
        for n, d in (("a", a_dir), ("b", b_dir))
    }
    return {
        **out,
        "encoder_a_over_b": med["a", "encoder"] / med["b", "encoder"],
        "head_a_over_b": med["a", "head"] / med["b", "head"],
        "k": k,
        "n_heldout": len(poses),
        "max_abs_diff": float(np.abs(p["a"] - p["b"]).max()),
        "decisions_changed": int(((p["a"] > 0.5) != (p["b"] > 0.5)).sum()),
    }


def main(argv=None) -> dict:
    from service.config import ENCODER_PRECISIONS

    p = argparse.ArgumentParser(
        prog="python -m export.model_ab", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("a", help="model folder A (e.g. before)")
    p.add_argument("b", help="model folder B (e.g. after)")
    p.add_argument("--k", type=int, default=128)
    p.add_argument("--rounds", type=int, default=40)
    p.add_argument("--calls", type=int, default=20)
    p.add_argument("--encoder-precision", choices=ENCODER_PRECISIONS, default="auto")
    args = p.parse_args(argv)
    if min(args.k, args.rounds, args.calls) < 1:
        p.error("--k, --rounds and --calls must be >= 1")
    for d in (args.a, args.b):
        if not (Path(d) / "model_card.json").is_file():
            p.error(f"{d!r} holds no model_card.json")
    r = compare(args.a, args.b, args.k, args.rounds, args.calls, args.encoder_precision)
    for part in ("encoder", "head"):
        prec, k = f"{part}_precision", f", k = {r['k']}" if part == "head" else ""
        print(
            f"{part}{k}, 1 thread, median of {args.rounds} x "
            f"{args.calls} interleaved calls each: A {r['a'][part + '_ms']:.3f} ms ({r['a'][prec]}), "
            f"B {r['b'][part + '_ms']:.3f} ms ({r['b'][prec]}): A / B = {r[part + '_a_over_b']:.2f}x"
        )
    print(
        f"{r['n_heldout']} held-out crops through each folder's encoder and head, each grasp scored alone: "
        f"max |p_A - p_B| {r['max_abs_diff']:.2e}, {r['decisions_changed']} decisions changed"
    )
    return r


if __name__ == "__main__":
    main()
