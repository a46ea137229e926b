"""Two model folders' served heads side by side: time and agreement, in one interleaved run.

    python -m export.head_ab BEFORE_DIR AFTER_DIR [--k 128] [--rounds 40] [--calls 20]

Each folder is opened as the service opens it (``service.runtime.FastModel``, its head precision
``auto``, one onnxruntime thread); the head is timed on one image term and k grasps of the
held-out crops, the folders taking turns every ``--calls`` calls (load from other processes
hits both alike). Agreement: the held-out crops (examples/heldout_test_crops.npz) through
folder A's encoder, each grasp scored alone by both heads: max |dp| and decisions changed.
Used to measure a rebuilt head (``export.prune_head``) against the one it replaces.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

HELDOUT = Path(__file__).resolve().parent.parent / "examples" / "heldout_test_crops.npz"


def compare(a_dir, b_dir, k: int = 128, rounds: int = 40, calls: int = 20, heldout=HELDOUT) -> dict:
    """Median head ms of each folder (k grasps, interleaved) and their agreement on ``heldout``."""
    from service.runtime import FastModel

    a, b = (FastModel(d, threads=1, encoder_precision="fp32") for d in (a_dir, b_dir))
    with np.load(heldout) as z:
        crops, poses = z["images"][:, 0], z["poses"].astype(np.float32)
    terms = a.encode(crops)
    pa, pb = (np.concatenate([m.score(terms[i : i + 1], poses[i : i + 1]) for i in range(len(poses))]) for m in (a, b))
    grasps = np.resize(poses, (k, poses.shape[1]))  # k grasps: the held-out poses, repeated if fewer
    times: dict[str, list[float]] = {"a": [], "b": []}
    for _ in range(rounds):
        for name, m in (("a", a), ("b", b)):
            for _ in range(calls):
                t = time.perf_counter()
                m.score(terms[:1], grasps)
                times[name].append(time.perf_counter() - t)
    med = {n: float(np.median(t)) * 1e3 for n, t in times.items()}
    return {
        "a": {"model_dir": str(a_dir), "head_precision": a.head_precision, "head_ms": med["a"]},
        "b": {"model_dir": str(b_dir), "head_precision": b.head_precision, "head_ms": med["b"]},
        "a_over_b": med["a"] / med["b"],
        "k": k,
        "n_heldout": len(pa),
        "max_abs_diff": float(np.abs(pa - pb).max()),
        "decisions_changed": int(((pa > 0.5) != (pb > 0.5)).sum()),
    }


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(
        prog="python -m export.head_ab", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("a", help="model folder A (e.g. before)")
    p.add_argument("b", help="model folder B (e.g. after)")
    p.add_argument("--k", type=int, default=128)
    p.add_argument("--rounds", type=int, default=40)
    p.add_argument("--calls", type=int, default=20)
    args = p.parse_args(argv)
    if min(args.k, args.rounds, args.calls) < 1:
        p.error("--k, --rounds and --calls must be >= 1")
    for d in (args.a, args.b):
        if not (Path(d) / "model_card.json").is_file():
            p.error(f"{d!r} holds no model_card.json")
    r = compare(args.a, args.b, args.k, args.rounds, args.calls)
    print(
        f"head, k = {r['k']}, 1 thread, median of {args.rounds} x {args.calls} interleaved calls each: "
        f"A {r['a']['head_ms']:.3f} ms ({r['a']['head_precision']}), B {r['b']['head_ms']:.3f} ms "
        f"({r['b']['head_precision']}): A / B = {r['a_over_b']:.2f}x"
    )
    print(
        f"{r['n_heldout']} held-out crops, each grasp scored alone: max |p_A - p_B| {r['max_abs_diff']:.2e}, "
        f"{r['decisions_changed']} decisions changed"
    )
    return r


if __name__ == "__main__":
    main()
