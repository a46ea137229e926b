"""The datasets of the bundled models (``python -m datagen recipe --version V``): each recipe's
settings, and the ``datagen`` commands that build it (generate -> sample -> crops, with the
recipe's extra test copies), each with the folder it writes."""

from __future__ import annotations

import json
import shlex
from pathlib import Path

RECIPES = {
    # v1: the model bundled until 2026-11-30 (fast_vgqcnn-60b272a5a797): random_urdfs only, the paper's label, clean renders
    "v1": {
        "objects": 600,  # first 600 of pybullet_data's random_urdfs (sorted by name)
        "families": None,
        "cameras": 10,  # camera poses per stable pose
        "seed": 0,
        "arch": "fast_vgqcnn",
        "kappa": 36.0,  # px in the 96 px window (the authors' default)
        "sampling": {"uniform_quantile": 0.1},  # small dataset: cap bins at the 10% quantile, not the minimum
        "sensor": "clean",
        "set": {"label.kind": "paper"},
    },
    # v2 (issue 10), bundled since 2026-11-30: everyday families + random_urdfs, the physics label
    # (docs/labels.md), the depth-sensor model
    "v2": {
        "objects": 600,
        "families": "all=40",  # 40 objects of each of the 11 families, split object-wise within every family
        "cameras": 50,  # Dex-Net 2.0's 50: labels are per grasp and stable pose, so more views cost only rendering
        "seed": 0,
        "arch": "fast_vgqcnn",
        "kappa": 36.0,
        # windows turned towards each grasp's jaw axis in K steps (`datagen crops --jaw-turns K`; 0: centred
        # windows, the bundled model's)
        "jaw_turns": 0,
        # cap (phi, beta) bins at their median count: at the 10% quantile the ~28 M native grasps would
        # leave ~1.5 M for training, below the paper's 2 M (measured on the first 245 objects: the
        # uniform step keeps 56% at 0.1, 75% at 0.3, 90% at 0.5)
        "sampling": {"uniform_quantile": 0.5},
        "sensor": "realistic",
        # round objects have up to 34 poses; a grasp's trials stop once its label is decided (the same labels,
        # -22% generation time, docs/labels.md; the bundled model's dataset ran all 8)
        "set": {"label.kind": "physics", "max_stable_poses": 6, "label.early_stop": True},
        # the leave-family-out experiment: these families' objects all go to test (a second sampled set)
        "leave_out": ["mug", "metaball"],
        # the physics trials of the objects generated so far (`datagen physics-cache`), replayed by `generate`:
        # the same dataset, without the trials' ~80% of the generation time
        "physics_cache": "v2_physics_trials.npz",
        # the placement stacker's fit set (`training stacker`, docs/training.md): objects neither the recipe
        # nor its --more-test draws (run seed + 2; random_urdfs from the 800th), nearly all in test
        "stacker": {"objects": 40, "first_object": 800, "families": "all=8"},
    },
}
RECIPE_FILES = Path(__file__).resolve().parent / "recipes"  # the recipes' data files
RECIPE = RECIPES["v2"]  # the bundled model's recipe


def _sets(items: dict, prefix: str = "") -> str:
    """``--set KEY=VALUE`` options (values as JSON) of config fields ``items``."""
    return " ".join(f"--set {prefix}{k}={json.dumps(v)}" for k, v in items.items())


def _holdout(families: list[str]) -> str:
    """The sample step's ``--set`` value that puts every object of ``families`` in test, shell-quoted."""
    return shlex.quote("sampling.holdout_families=" + json.dumps(families, separators=(",", ":")))


def _family_list(counts: str) -> list[str]:
    """The family names of a ``--families`` value (``mug=5,box=2``; ``all=N``: every family)."""
    from .families import family_names

    names = [f.split("=")[0] for f in counts.split(",")]
    return family_names() if names == ["all"] else names


def recipe_steps(
    version: str,
    out: Path,
    *,
    objects: int | None = None,
    workers: int = 1,
    physics_cache: bool = True,
    leave_out: bool = True,
    more_test: int | None = None,
    stacker: bool = False,
) -> list[tuple[str, Path | None]]:
    """The commands that build recipe ``version`` in ``out``, in order, each with the folder it
    writes (None: the generation, which always runs: it resumes). ``objects``: random_urdfs
    objects (default the recipe's); ``physics_cache``: replay the recipe's recorded physics trials
    when its file is there; ``leave_out``: the leave-family-out copy; ``more_test``: N new objects
    of each procedural family (run seed + 1), all in test; ``stacker``: the placement stacker's fit
    set (run seed + 2). ValueError naming what the recipe lacks."""
    recipe = RECIPES[version]
    seed, cameras = recipe["seed"], recipe["cameras"]
    sets, samp = _sets(recipe["set"]), _sets(recipe["sampling"], "sampling.")
    fams = f" --families {recipe['families']}" if recipe["families"] else ""
    cache = RECIPE_FILES / recipe["physics_cache"] if recipe.get("physics_cache") else None
    replay = f" --physics-cache {shlex.quote(str(cache))}" if physics_cache and cache and cache.is_file() else ""
    crops = f"--arch {recipe['arch']} --kappa {recipe['kappa']:g} --seed {seed}"
    if recipe.get("jaw_turns"):  # every crop step of the recipe: the model's input is one geometry
        crops += f" --jaw-turns {recipe['jaw_turns']}"
    steps: list[tuple[str, str | None]] = [
        (
            f"python -m datagen generate --out {out / 'grasps'} --objects {objects or recipe['objects']}{fams} "
            f"--cameras {cameras} --seed {seed} --workers {workers} {sets}{replay}",
            None,
        ),
        (f"python -m datagen sample --in {out / 'grasps'} --out {out / 'sampled'} --seed {seed} {samp}", "sampled"),
        (
            f"python -m datagen crops --in {out / 'sampled'} --out {out / 'crops'} {crops} --sensor {recipe['sensor']}",
            "crops",
        ),
    ]
    if recipe["sensor"] != "clean":  # the same test grasps without the sensor model: clean vs corrupted
        steps.append(
            (
                f"python -m datagen crops --in {out / 'sampled'} --out {out / 'crops_clean_test'} {crops} "
                "--sensor clean --splits test",
                "crops_clean_test",
            )
        )
    if recipe.get("leave_out") and leave_out:  # leave-family-out: those families only in test
        steps += [
            (
                f"python -m datagen sample --in {out / 'grasps'} --out {out / 'sampled_lfo'} --seed {seed} "
                f"{samp} --set {_holdout(recipe['leave_out'])}",
                "sampled_lfo",
            ),
            (
                f"python -m datagen crops --in {out / 'sampled_lfo'} --out {out / 'crops_lfo'} {crops} "
                f"--sensor {recipe['sensor']}",
                "crops_lfo",
            ),
        ]
    if more_test:  # more held-out objects per family: tighter per-family test numbers, no retraining
        if not recipe["families"]:
            raise ValueError(f"--more-test: recipe {version} has no procedural families")
        names = [f.split("=")[0] for f in recipe["families"].split(",")]
        more = f"all={more_test}" if names == ["all"] else ",".join(f"{n}={more_test}" for n in names)
        names = _family_list(recipe["families"])
        steps += [
            (  # another run seed: shapes the recipe never drew (same names, new parameters)
                f"python -m datagen generate --out {out / 'grasps_more'} --objects 0 --families {more} "
                f"--cameras {cameras} --seed {seed + 1} --workers {workers} {sets}",
                None,
            ),
            (
                f"python -m datagen sample --in {out / 'grasps_more'} --out {out / 'sampled_more'} "
                f"--seed {seed} {samp} --set {_holdout(names)}",
                "sampled_more",
            ),
            (
                f"python -m datagen crops --in {out / 'sampled_more'} --out {out / 'crops_more'} {crops} "
                f"--sensor {recipe['sensor']} --splits test",
                "crops_more",
            ),
        ]
    if stacker:  # objects of neither the recipe nor its tests, to fit `training stacker` on
        if not recipe.get("stacker"):
            raise ValueError(f"--stacker: recipe {version} has no stacker fit set")
        st = recipe["stacker"]
        names = _family_list(st["families"])
        steps += [
            (
                f"python -m datagen generate --out {out / 'grasps_stacker'} --objects {st['objects']} "
                f"--first-object {st['first_object']} --families {st['families']} --cameras {cameras} "
                f"--seed {seed + 2} --workers {workers} {sets}",
                None,
            ),
            (  # the families all in test; random_urdfs too but for a token train object (train may not be empty)
                f"python -m datagen sample --in {out / 'grasps_stacker'} --out {out / 'sampled_stacker'} "
                f"--seed {seed} {samp} --set {_holdout(names)} --set 'sampling.split_fractions=[0.02,0,0.98]'",
                "sampled_stacker",
            ),
            (
                f"python -m datagen crops --in {out / 'sampled_stacker'} --out {out / 'crops_stacker'} {crops} "
                f"--sensor {recipe['sensor']} --splits test",
                "crops_stacker",
            ),
        ]
    return [(s, None if o is None else out / o) for s, o in steps]
