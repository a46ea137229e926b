"""What every benchmark command shares: the model, the planner settings its command line asks
for, the pose-only baseline, and the seeded draw of scenes."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from ..types import PlanParams
from .scenes import recipe_config, scene_objects

MODEL_DIR = "models/fast-vgqcnn-default"


def load_model(model_dir: str, threads: int, head_precision: str = "auto"):
    from service.runtime import FastModel

    m = FastModel(model_dir, threads=threads, head_precision=head_precision)
    m.warm_up(5)
    return m


def pose_only_model(model_dir: str, path: str | None = None):
    """The pose-only baseline (:class:`vgq.pose_only.PoseOnlyModel`): ``path`` (a
    ``training baseline`` output), else the model folder's ``baseline_mlp.npz`` /
    ``baseline_logreg.npz`` (export copies it there), else None."""
    from vgq.pose_only import PoseOnlyModel, file_name

    if path:
        return PoseOnlyModel.load(path), Path(path)
    for name in (file_name("mlp"), file_name("logreg")):
        p = Path(model_dir) / name
        if p.exists():
            return PoseOnlyModel.load(p), p
    return None, None


def plan_params(args) -> PlanParams:
    """The planner settings a benchmark's command line asks for (the rest: ``PlanParams()``)."""
    return dataclasses.replace(
        PlanParams(),
        cem_iterations=args.cem,
        windows=args.windows,
        max_centre_offset=args.centre_offset,
        min_width=args.min_width,
        table_margin=args.table_margin,
        max_approach_tilt=np.radians(args.max_approach_tilt),
        top_view_cell=args.top_view_cell if args.top_view_cell > 0 else None,
    )


def draw_scenes(args):
    """(model, recipe config, planner params, held-out object ids drawn, rng) of a benchmark run:
    the same seed draws the same objects for every benchmark."""
    model = load_model(args.model, args.threads)
    params = plan_params(args)
    ids, config = scene_objects(args.heldout, args.split, recipe_config(model))
    rng = np.random.default_rng(args.seed)
    picked = rng.choice(ids, size=args.scenes, replace=args.scenes > len(ids))
    return model, config, params, picked, rng
