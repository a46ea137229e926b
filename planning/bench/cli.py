"""Planning benchmark: speed, and precision judged by datagen's oracle (the command line of
``python -m planning.bench``; the package's docstring says what each command measures)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from ..types import PlanParams
from .ceiling import read_trials_run, run_ceiling
from .common import MODEL_DIR
from .oracle import ORACLES
from .pool import run_pool
from .precision import run_precision
from .ranking import run_ranker
from .scenes import HELDOUT
from .timing import run_timing
from .trials import run_trials_bench


def main(argv=None) -> int:
    args = parse_args(argv)
    run = {
        "timing": run_timing,
        "precision": run_precision,
        "trials": run_trials_bench,
        "ranker": run_ranker,
        "pool": run_pool,
        "ceiling": run_ceiling,
    }[args.what]
    from service.runtime import ModelError

    if args.against and not (Path(args.against) / "planning" / "policy.py").is_file():
        print(
            f"python -m planning.bench: error: --against {args.against}: no planning/policy.py there", file=sys.stderr
        )
        return 2
    try:
        out = run(args)
    except (ModelError, OSError) as e:  # a model folder or held-out file it cannot read
        print(f"python -m planning.bench: error: {e}", file=sys.stderr)
        return 2
    if args.json:
        from vgq import atomic

        atomic.write_bytes(Path(args.json), json.dumps(out, indent=1).encode())
    return 0


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m planning.bench", description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=["timing", "precision", "trials", "ranker", "pool", "ceiling"])
    ap.add_argument("--model", default=MODEL_DIR)
    ap.add_argument(
        "--heldout",
        default=HELDOUT,
        help="the scenes' objects: a held-out crop file, a crop dataset folder (with --split), or "
        "'unseen': objects outside the model's dataset (to fit the ranker and p_hold on)",
    )
    ap.add_argument(
        "--split",
        choices=["train", "val", "test"],
        default="test",
        help="the objects of this split when --heldout is a crop dataset folder (train / val: to fit on other objects)",
    )
    ap.add_argument("--scenes", type=int, default=None, help="timing: 4, precision: 20")
    ap.add_argument("--repeats", type=int, default=26, help="timing: passes over the scenes (the first is warm-up)")
    ap.add_argument("--threads", type=int, default=2, help="onnxruntime intra-op threads")
    ap.add_argument(
        "--against",
        metavar="DIR",
        help="timing: also time the planner of another checkout (a folder holding planning/, e.g. a git "
        "worktree of an earlier commit), plan by plan interleaved with this one's, and print the ratio",
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--trials",
        type=int,
        default=None,
        help="trials / pool / ceiling: pybullet trials per grasp (with execution noise); default 5, ceiling: the "
        "recipe's label trials",
    )
    ap.add_argument("--per-scene", type=int, default=24, help="pool: random candidates tried per scene")
    ap.add_argument(
        "--grasps", type=int, default=None, help="ceiling: antipodal grasps sampled per scene (default: the recipe's)"
    )
    ap.add_argument(
        "--approaches", type=int, default=1, help="ceiling: approaches (random omega) per grasp (datagen: 1)"
    )
    ap.add_argument(
        "--plan",
        metavar="FILE",
        help="ceiling --confirm: a `trials --json` run of the same --seed and --scenes, whose top-1 verdicts are "
        "counted per class of scene by its best true-mesh grasp",
    )
    ap.add_argument(
        "--confirm",
        type=int,
        default=0,
        metavar="K",
        help="ceiling: also judge each scene's top K grasps on 3x more trials and pick the best by all (0: off)",
    )
    ap.add_argument(
        "--robust",
        type=int,
        default=0,
        metavar="P",
        help="trials: also judge the top-1 by the score averaged over P noisy copies of each candidate (0: off)",
    )
    ap.add_argument(
        "--retest",
        action="store_true",
        help="pool: judge each scene's best judged candidate again on fresh trials (what a ranker that knew "
        "the oracle's answer would score on a new judging)",
    )
    ap.add_argument(
        "--table-margin",
        type=float,
        default=PlanParams().table_margin,
        help="fingertips at least this far above the estimated table (m)",
    )
    ap.add_argument("--cem", type=int, default=0, help="CEM iterations over omega (0: off)")
    ap.add_argument("--windows", choices=["cover", "grid"], default="cover")
    ap.add_argument(
        "--centre-offset",
        type=float,
        default=PlanParams().max_centre_offset,
        help="max distance (m) of the jaw line from the estimated centre of mass; <= 0: off",
    )
    ap.add_argument("--min-width", type=float, default=PlanParams().min_width, help="min contact distance (m)")
    ap.add_argument(
        "--max-approach-tilt",
        type=float,
        default=float(np.degrees(PlanParams().max_approach_tilt)),
        help="approaches within this angle (deg) of straight down",
    )
    ap.add_argument(
        "--top-view-cell",
        type=float,
        default=PlanParams().top_view_cell,
        help="grid (m) of the objects' tops seen from above that ends a contact line's hidden part; <= 0: off",
    )
    ap.add_argument(
        "--oracle",
        choices=ORACLES,
        default=None,
        help="precision: judge by robust Ferrari-Canny (fc) or by pybullet trials (physics); default: the one "
        "matching the label of the model's recipe",
    )
    ap.add_argument(
        "--random-sample",
        type=int,
        default=16,
        help="precision with the physics oracle: random candidates judged per scene for the random baseline",
    )
    ap.add_argument(
        "--baseline",
        metavar="FILE",
        help="precision: a pose-only baseline file (`training baseline --out DIR` writes DIR/baseline_mlp.npz) "
        "whose ranking of the same candidates is judged too; default: the one in the model folder, if any",
    )
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args(argv)
    if args.centre_offset is not None and args.centre_offset <= 0:
        args.centre_offset = None
    if args.random_sample < 1:
        ap.error("--random-sample must be >= 1")
    if args.robust < 0:
        ap.error(f"--robust must be >= 0, got {args.robust}")
    if args.scenes is None:
        args.scenes = {"timing": 4, "precision": 20, "trials": 10, "ranker": 20, "pool": 60, "ceiling": 30}[args.what]
    if args.confirm < 0:
        ap.error(f"--confirm must be >= 0, got {args.confirm}")
    args.plan_run = None
    if args.plan:  # read before the run: a bad file must not cost the benchmark's minutes
        try:
            args.plan_run = read_trials_run(args.plan, args.seed, args.scenes)
        except ValueError as e:
            ap.error(f"--plan {args.plan}: {e}")
    if args.approaches < 1 or (args.grasps is not None and args.grasps < 1):
        ap.error(f"--approaches and --grasps must be >= 1, got {args.approaches} and {args.grasps}")
    if args.trials is not None and args.trials < 1:
        ap.error(f"--trials must be >= 1, got {args.trials}")
    if args.trials is None and args.what != "ceiling":
        args.trials = 5
    if not 0 < args.max_approach_tilt <= 90:
        ap.error(f"--max-approach-tilt must be in (0, 90] degrees, got {args.max_approach_tilt:g}")
    return args
