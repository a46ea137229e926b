"""``vgq-plan``: the best grasps on a depth image, as JSON, with an optional overlay PNG.

    vgq-plan depth.npy --k 5 --out grasps.json --png overlay.png

The depth image is a .npy array in metres (float; an integer array is millimetres) or a
16-bit PNG in millimetres; 0 = no reading. Intrinsics default to the model's camera
(principal point at the image centre when the image has another size). Bad input exits with
status 2 and one line naming it.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from .types import MAX_K, PlanningError

DEFAULT_MODEL = "models/fast-vgqcnn-default"


class InputError(Exception):
    pass


def load_depth(path: str) -> np.ndarray:
    """(H, W) float32 metres from a .npy (metres; integer arrays are millimetres) or a
    16-bit PNG (millimetres)."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"depth image {path!r} not found")
    suffix = p.suffix.lower()
    try:
        if suffix == ".npy":
            a = np.load(p, allow_pickle=False)
        elif suffix == ".png":
            from PIL import Image

            with Image.open(p) as im:
                if im.mode not in ("I;16", "I;16B", "I;16L", "I"):
                    raise InputError(f"{path}: PNG mode {im.mode}; a depth PNG is 16-bit grey, millimetres")
                a = np.asarray(im)
        else:
            raise InputError(f"{path}: unknown depth format {suffix!r}; give a .npy (metres) or a 16-bit .png (mm)")
    except InputError:
        raise
    except Exception as e:  # a corrupt file
        raise InputError(f"cannot read {path}: {e}") from None
    if np.issubdtype(a.dtype, np.integer):
        a = a.astype(np.float64) / 1000.0
    elif not np.issubdtype(a.dtype, np.floating):
        raise InputError(f"{path}: depth must be a numeric array, got dtype {a.dtype}")
    return np.asarray(a, dtype=np.float32)


def parse_roi(text: str | None):
    if text is None:
        return None
    try:
        vals = [float(x) for x in text.split(",")]
    except ValueError:
        raise InputError(f"--roi must be u0,v0,u1,v1 (pixels), got {text!r}") from None
    if len(vals) != 4 or not np.isfinite(vals).all():
        raise InputError(f"--roi must be four finite numbers u0,v0,u1,v1 (pixels), got {text!r}")
    return np.array(vals)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="vgq-plan", description="Plan the best grasps on a depth image.")
    ap.add_argument(
        "depth", help="depth image: .npy (float metres or integer millimetres) or 16-bit .png (millimetres)"
    )
    ap.add_argument("--model", default=DEFAULT_MODEL, help="model folder (default: %(default)s)")
    for name in ("fx", "fy", "cx", "cy"):
        ap.add_argument(f"--{name}", type=float, default=None, help=f"{name} in pixels (default: the model's camera)")
    level = ap.add_mutually_exclusive_group()
    level.add_argument(
        "--up",
        type=float,
        nargs=3,
        metavar=("X", "Y", "Z"),
        help="the world's up direction in the camera frame (x right, y down, z forward): the image is turned level "
        "about the optical axis (default: the camera is taken as level)",
    )
    level.add_argument(
        "--level",
        choices=("table",),
        help="table: read the up direction from the table plane in the image (for a camera whose mounting is "
        "not known)",
    )
    ap.add_argument("--k", type=int, default=5, help=f"grasps to return, 1 to {MAX_K} (default: %(default)s)")
    ap.add_argument("--roi", help="region of interest u0,v0,u1,v1 in pixels (inclusive)")
    ap.add_argument("--seed", type=int, default=0, help="sampling seed (default: %(default)s)")
    ap.add_argument("--cem", type=int, default=0, help="CEM refinement iterations (default: off)")
    ap.add_argument("--threads", type=int, default=2, help="onnxruntime threads (default: %(default)s)")
    ap.add_argument("--out", help="write the grasps as JSON here (default: stdout)")
    ap.add_argument("--png", help="draw the grasps over the depth image into this PNG")
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    import dataclasses

    from vgq import atomic

    try:
        from service.runtime import FastModel, ModelError
    except ImportError as e:
        print(f"vgq-plan: error: onnxruntime is needed ({e}); install the service extra", file=sys.stderr)
        return 2
    from vgq.camera import describe_level, level_roll

    from .level import PARAMS as LEVEL_PARAMS
    from .level import table_level
    from .policy import camera_for, plan
    from .types import PlanParams

    try:
        depth = load_depth(args.depth)
        if depth.ndim != 2:
            raise InputError(f"{args.depth}: depth must be a 2-D image, got shape {depth.shape}")
        roi = parse_roi(args.roi)
        if args.cem < 0:
            raise InputError(f"--cem must be >= 0, got {args.cem}")
        if args.threads < 1:
            raise InputError(f"--threads must be >= 1, got {args.threads}")
        model = FastModel(args.model, threads=args.threads)
        intr = camera_for(depth.shape, model.card.intrinsics, args.fx, args.fy, args.cx, args.cy)
        params = dataclasses.replace(PlanParams(), cem_iterations=args.cem)
        up, source = args.up, None if args.up is None else "client"
        if args.level == "table":
            found = table_level(depth, intr)
            if found is None:
                raise InputError(
                    f"--level table: no table plane in {args.depth} (no plane holds "
                    f"{LEVEL_PARAMS.min_table_fraction:.0%} of its valid pixels); give --up X Y Z instead"
                )
            up, source = found.up, "table"
        result = plan(depth, intr, model, k=args.k, roi=roi, seed=args.seed, params=params, up=up)
    except (InputError, ModelError) as e:
        print(f"vgq-plan: error: {e}", file=sys.stderr)
        return 2
    except PlanningError as e:
        print(f"vgq-plan: error: {e.field}: {e}", file=sys.stderr)
        return 2
    level = describe_level(up, 0.0 if up is None else level_roll(up), source)
    doc = {"depth": args.depth, "intrinsics": intr.to_dict(), "level": level, "k": args.k, "seed": args.seed}
    doc.update(result.to_dict())
    text = json.dumps(doc, indent=1)
    if args.out:
        atomic.write_bytes(Path(args.out), text.encode())
    else:
        print(text)
    if args.png:
        import io

        from .draw import overlay

        buf = io.BytesIO()
        overlay(depth, intr, result.grasps).save(buf, format="PNG")
        atomic.write_bytes(Path(args.png), buf.getvalue())
    n = len(result.grasps)
    best = result.grasps[0] if n else None
    hold = f", p_hold {best.p_hold:.2f}" if best is not None and best.p_hold is not None else ""
    msg = f"{n} grasps ranked by {result.ranked_by}" + (
        f" (first: score {best.score:.3f}{hold})" if n else f": {result.reason}"
    )
    print(f"vgq-plan: {msg} in {1e3 * result.seconds.get('total', 0):.0f} ms", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
