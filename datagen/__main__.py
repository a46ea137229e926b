"""Command line: ``python -m datagen {generate,physics-cache,planner-grasps,sample,crops,bench,recipe,config,objects,stats} ...``.

Bad input (missing folders, unreadable meshes, nonsense config values) exits with code 2
and one line naming the problem; an interrupted ``generate`` resumes when rerun.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from vgq.crop import CONTEXT_SCALES

from .recipe import RECIPE, RECIPES


class CliError(Exception):
    """A usage problem detected after argument parsing (exit code 2)."""


def _int_at_least(name: str, low: int):
    """argparse type: an integer >= ``low``; the error names the option."""

    def parse(s):
        try:
            v = int(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be an integer, got {s!r}") from None
        if v < low:
            raise argparse.ArgumentTypeError(f"{name} must be >= {low}, got {v}")
        return v

    return parse


def _positive_int(name):
    return _int_at_least(name, 1)


def _count(name):
    return _int_at_least(name, 0)


def parse_family_counts(text: str) -> dict[str, int]:
    """``"mug=5,box=3"`` (or ``"all=5"``) -> {family: count}; CliError naming a bad entry."""
    from .families import family_names, get_family

    out: dict[str, int] = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        name, sep, n = part.partition("=")
        name = name.strip()
        try:
            count = int(n)
        except ValueError:
            count = -1
        if not sep or count < 0:
            raise CliError(f"--families entry {part!r} must look like FAMILY=COUNT with COUNT >= 0, e.g. mug=5")
        for fam in family_names() if name == "all" else [get_family(name).name]:
            out[fam] = count
    if not out:
        raise CliError("--families is empty; give FAMILY=COUNT entries, e.g. mug=5,box=5 or all=5")
    return out


def _add_config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", metavar="FILE", help="JSON config file (see `datagen config`)")
    p.add_argument(
        "--set",
        metavar="KEY=VALUE",
        action="append",
        default=[],
        help="override one config field, e.g. --set quality.num_samples=10 --set camera.d_range=[0.5,0.9]",
    )


def _build_config(args, base=None, **fields):
    from .config import DatagenConfig, load_config, parse_override

    cfg = base if base is not None else (load_config(args.config) if args.config else DatagenConfig())
    overrides = dict(parse_override(s) for s in args.set)
    overrides.update({k: v for k, v in fields.items() if v is not None})
    return cfg.with_overrides(overrides) if overrides else cfg


def cmd_generate(args) -> int:
    from .config import DatagenConfig
    from .parallel import default_workers
    from .pipeline import run_generate
    from .storage import GRASP_FORMAT, MANIFEST, read_manifest

    out = Path(args.out)
    base = None
    if args.resume:
        if not (out / MANIFEST).is_file():
            raise CliError(f"--resume: no {MANIFEST} in {out}")
        from .config import recorded_config

        base = DatagenConfig.from_dict(recorded_config(read_manifest(out, GRASP_FORMAT)["config"]))
    cfg = _build_config(
        args,
        base,
        source=str(Path(args.source).resolve()) if args.source else None,
        num_objects=args.objects,
        first_object=args.first_object,
        cameras_per_pose=args.cameras,
        seed=args.seed,
        families=parse_family_counts(args.families) if args.families else None,
    )
    if args.source and not Path(args.source).exists():
        raise CliError(f"--source {args.source} does not exist")
    workers = args.workers or default_workers()
    cache = None
    if args.physics_cache:
        from .physics_cache import PhysicsCache

        cache = PhysicsCache.load(args.physics_cache)
    m = run_generate(out, cfg, workers=workers, use_ray=args.ray, progress=not args.quiet, physics_cache=cache)
    c = m["counts"]
    print(
        f"{out}: {c['objects_done']} objects done, {c['objects_skipped']} skipped, {c['images']} images, "
        f"{c['grasps']} grasps, positivity {100 * c['positivity_rate']:.1f}%"
    )
    skipped = [o for o in m["objects"] if o["status"] == "skipped"]
    for o in skipped:
        print(f"warning: skipped object {o['name']} ({o['source']}): {o.get('reason')}", file=sys.stderr)
    if c["objects_done"] == 0 and skipped:
        raise CliError(f"no object produced data; first problem: {skipped[0]['source']}: {skipped[0].get('reason')}")
    return 0


def cmd_sample(args) -> int:
    from .sampling import sample_dataset

    cfg = _build_config(args)
    params = cfg.sampling
    if args.seed is not None:
        import dataclasses

        params = dataclasses.replace(params, seed=args.seed)
    split_over = None
    if args.split_over:
        try:
            split_over = json.loads(Path(args.split_over).read_text())
        except (OSError, ValueError) as e:
            raise CliError(f"--split-over {args.split_over}: not a readable JSON file ({e})") from e
        if not isinstance(split_over, list) or not all(isinstance(i, int) and i >= 0 for i in split_over):
            raise CliError(f"--split-over {args.split_over}: must hold a JSON list of object ids (integers >= 0)")
    from .parallel import default_workers

    sample_dataset(
        args.inp,
        args.out,
        params,
        plot=not args.no_plots,
        split_over=split_over,
        workers=args.workers or default_workers(),
        progress=not args.quiet,
    )
    return 0


def cmd_crops(args) -> int:
    from .crops import make_crops
    from .parallel import default_workers
    from .sensor import parse_override

    make_crops(
        args.inp,
        args.out,
        args.arch,
        args.kappa,
        seed=args.seed,
        progress=not args.quiet,
        sensor=args.sensor,
        sensor_overrides=dict(parse_override(o) for o in args.sensor_set),
        splits=tuple(args.splits),
        workers=args.workers or default_workers(),
        window=args.window,
        align_jaw=args.align_jaw,
        jaw_turns=args.jaw_turns,
        context_scale=args.context_scale,
    )
    return 0


def cmd_planner_grasps(args) -> int:
    from .parallel import default_workers
    from .planner_grasps import PlannerGraspParams, run_planner_grasps, source_trials
    from .storage import GRASP_FORMAT, read_manifest

    src_m = read_manifest(args.grasps, GRASP_FORMAT)  # DatasetError naming a missing / foreign SRC
    trials = args.trials if args.trials is not None else source_trials(src_m)
    if trials is None:
        raise CliError(
            f"--grasps {args.grasps} is not physics-labelled (config.label.kind "
            f"{src_m.get('config', {}).get('label', {}).get('kind', 'paper')!r}); give --trials N"
        )
    params = PlannerGraspParams(
        images_per_object=args.images_per_object,
        candidates=args.candidates,
        trials=trials,
        sensor=args.sensor,
        sensor_seed=args.sensor_seed,
        seed=args.seed,
    )
    m = run_planner_grasps(
        args.grasps,
        args.out,
        params,
        workers=args.workers or default_workers(),
        max_objects=args.objects,
        progress=not args.quiet,
    )
    c = m["counts"]
    print(
        f"{args.out}: {c['objects_done']} objects done, {c['images']} images, {c['grasps']} planner candidates, "
        f"{100 * c['collision_free'] / max(c['grasps'], 1):.1f}% collision-free, "
        f"positivity {100 * c['positivity_rate']:.1f}% (success rate > {m['label_threshold']:g})"
    )
    failed = [o for o in m["objects"] if o.get("failed")]
    for o in failed:
        print(f"error: object {o['name']} (id {o['object_id']}): {o.get('reason')}", file=sys.stderr)
    return 1 if failed else 0


def cmd_bench(args) -> int:
    from .bench import run_bench

    cfg = _build_config(
        args,
        source=str(Path(args.source).resolve()) if args.source else None,
        num_objects=args.objects,
        cameras_per_pose=args.cameras,
        seed=args.seed,
    )
    if args.physics:
        from .bench import run_physics_bench

        res = run_physics_bench(cfg, workers=args.workers, grasps=args.grasps, trials=args.trials)
    else:
        res = run_bench(cfg, workers=args.workers)
    if args.json:
        print(json.dumps(res, indent=2))
    return 0


def cmd_labelstudy(args) -> int:
    from .label_study import StudyParams, augment, run_study, summarise, write_report

    out = Path(args.out)
    params = StudyParams(
        grasps=args.grasps,
        label_trials=args.label_trials,
        eval_trials=args.eval_trials,
        per_family=args.per_family,
        random_urdfs=args.random_urdfs,
        seed=args.seed,
    )
    cfg = _build_config(args)
    results = run_study(out, params, cfg, workers=args.workers) if not args.summary_only else None
    if args.more_label_trials:
        from .label_study import add_label_trials, load_results

        add_label_trials(
            out,
            args.more_label_trials,
            cfg,
            params,
            workers=args.workers,
            upto=args.label_trials + args.more_label_trials,
        )
        results = load_results(out)
    if results is None:
        from .label_study import load_results

        results = load_results(out)
    if augment(out, cfg, params):  # cached objects from an older study: add the newer analytic scores
        from .label_study import load_results

        results = load_results(out)
    if not any(r.get("status") == "done" for r in results):
        raise CliError(f"{out}: no object produced study data")
    summary = summarise(results, out / "plots", cfg.quality.label_threshold, cfg.label.success_threshold)
    write_report(out, summary)
    print(json.dumps(summary, indent=2))
    return 0


def cmd_recipe(args) -> int:
    import shlex

    from . import recipe as recipes
    from .parallel import default_workers

    steps = recipes.recipe_steps(
        args.version,
        Path(args.out),
        objects=args.objects,
        workers=args.workers or default_workers(),
        physics_cache=not args.no_physics_cache,
        leave_out=not args.no_leave_out,
        more_test=args.more_test,
        stacker=args.stacker,
    )
    for s, _ in steps:
        print(s)
    if args.dry_run:
        return 0
    for s, o in steps:
        if o is not None and (o / "manifest.json").is_file():
            if json.loads((o / "manifest.json").read_text()).get("complete", True):
                print(f"\n{o} exists: skipping `{' '.join(shlex.split(s)[3:5])}`", flush=True)
                continue
            raise CliError(f"{o} holds an unfinished dataset (an interrupted run); delete it and rerun the recipe")
        print(f"\n$ {s}", flush=True)
        rc = main(shlex.split(s)[3:])
        if rc:
            return rc
    return 0


def cmd_objects(args) -> int:
    from vgq import atomic

    from .families import FAMILIES, family_names, get_family, make_object
    from .families.sheet import contact_sheet

    if args.list:
        for f in FAMILIES.values():
            print(f"{f.name:<10} {f.summary} (extents {100 * f.extent_range[0]:g}-{100 * f.extent_range[1]:g} cm)")
        return 0
    if not args.family or not args.out:
        raise CliError("give --family NAME (or all) and --out DIR, or --list")
    names = family_names() if args.family == "all" else [get_family(n.strip()).name for n in args.family.split(",")]
    out = Path(args.out)
    entries, rows, views = [], [], {}
    for fam in names:
        objs = [make_object(fam, i, args.seed) for i in range(args.count)]
        for i, o in enumerate(objs):
            rel = f"{fam}/{o.name}.stl"
            atomic.write_bytes(out / rel, o.mesh.export(file_type="stl"))
            entries.append(
                {
                    "name": o.name,
                    "family": fam,
                    "index": i,
                    "seed": args.seed,
                    "params": o.params,
                    "file": rel,
                    "extents_m": [round(float(x), 5) for x in o.mesh.extents],
                    "volume_m3": float(o.mesh.volume),
                    "watertight": bool(o.mesh.is_watertight),
                }
            )
        if not args.no_sheet:
            sheet = contact_sheet(
                [(fam, objs)],
                out / f"{fam}.png",
                f"{fam}: {FAMILIES[fam].summary} (seed {args.seed})",
                cols=5,
                cache=views,
            )
            print(f"{sheet}: {len(objs)} objects")
        rows.append((fam, objs))
    atomic.write_json(out / "objects.json", {"seed": args.seed, "objects": entries})
    if len(names) > 1 and not args.no_sheet:
        sheet = contact_sheet(
            [(f, o[:6]) for f, o in rows], out / "families.png", f"object families (seed {args.seed})", cache=views
        )
        print(f"{sheet}: {len(names)} families")
    print(f"{out}: {len(entries)} meshes (.stl, metres) and objects.json (family, parameters)")
    return 0


def cmd_physics_cache(args) -> int:
    from .physics_cache import PhysicsCache, from_dataset

    cache = None
    if args.merge:
        if not Path(args.out).is_file():
            raise CliError(f"--merge: {args.out} does not exist")
        cache = PhysicsCache.load(args.out)
    for root in args.inp:
        got = from_dataset(root)
        cache = got if cache is None else cache.merge(got)
    cache.save(args.out)
    size = Path(args.out).stat().st_size
    print(f"{args.out}: trials of {len(cache.objects)} objects, {cache.num_poses} stable poses ({size / 1e6:.1f} MB)")
    return 0


def cmd_stats(args) -> int:
    from . import storage

    m = storage.read_manifest(args.inp, storage.GRASP_FORMAT)
    fams = storage.family_counts(m)
    if args.json:
        print(json.dumps({"counts": m["counts"], "families": fams}, indent=2))
        return 0
    c = m["counts"]
    resume = "datagen planner-grasps" if "planner_grasps" in m else "datagen generate"  # the stage that wrote it
    print(
        f"{args.inp}: {c['objects_done']} of {c['objects']} objects done ({c['objects_skipped']} skipped), "
        f"{c['grasps']} grasps, positivity {100 * c['positivity_rate']:.2f}%"
        + ("" if m.get("complete") else f" (generation not complete: rerun `{resume}` to resume)")
    )
    print(
        f"{'family':<14}{'done':>6}{'skip':>6}{'todo':>6}{'grasps':>11}{'coll.-free':>11}{'positive':>10}{'no pos.':>9}"
    )
    for name, f in fams.items():
        print(
            f"{name or '-':<14}{f['done']:>6}{f['skipped']:>6}{f['pending']:>6}{f['grasps']:>11}"
            f"{100 * f['collision_free'] / max(f['grasps'], 1):>10.1f}%{100 * f['positivity']:>9.2f}%{f['no_positive']:>9}"
        )
    return 0


def cmd_config(args) -> int:
    cfg = _build_config(args)
    print(json.dumps(cfg.to_dict(), indent=2, sort_keys=True))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="datagen", description="VG-dset style grasp dataset generation")
    sub = p.add_subparsers(dest="command", required=True)

    g = sub.add_parser("generate", help="render a grasp dataset (vgq-grasps) from meshes; rerun to resume")
    g.add_argument("--out", required=True, help="output folder")
    g.add_argument("--source", help="mesh folder or file (default: pybullet_data random_urdfs)")
    g.add_argument(
        "--objects", type=_count("--objects"), help="use the first N objects of --source (sorted by name; 0: none)"
    )
    g.add_argument(
        "--first-object",
        type=_count("--first-object"),
        metavar="K",
        help="skip the first K objects of --source (sorted by name): --objects counts from the K-th (default 0)",
    )
    g.add_argument(
        "--families", metavar="FAMILY=N,...", help="add N procedural objects per family, e.g. mug=5,box=5 or all=5"
    )
    g.add_argument("--cameras", type=_positive_int("--cameras"), help="camera poses per stable pose (default 10)")
    g.add_argument("--workers", type=_positive_int("--workers"), help="worker processes (default: CPU cores)")
    g.add_argument("--ray", action="store_true", help="run the per-object tasks on Ray (pip install vgq-cnn[ray])")
    g.add_argument("--seed", type=_count("--seed"), help="run seed (default 0)")
    g.add_argument("--resume", action="store_true", help="continue the run in --out with its recorded config")
    g.add_argument("--quiet", action="store_true", help="no progress bar")
    g.add_argument(
        "--physics-cache",
        metavar="FILE",
        help="replay the physics trials recorded in FILE (`datagen physics-cache`) where they cover a pose",
    )
    _add_config_args(g)
    g.set_defaults(func=cmd_generate)

    pc = sub.add_parser(
        "physics-cache", help="record a physics-labelled dataset's trial outcomes for `generate --physics-cache`"
    )
    pc.add_argument("--in", dest="inp", required=True, nargs="+", help="grasp dataset folder(s) (vgq-grasps)")
    pc.add_argument("--out", required=True, help="cache file (.npz), written atomically")
    pc.add_argument("--merge", action="store_true", help="add to the objects already in --out")
    pc.set_defaults(func=cmd_physics_cache)

    s = sub.add_parser("sample", help="psi filter, positivity equalisation, uniform undersampling, object-wise split")
    s.add_argument("--in", dest="inp", required=True, help="grasp dataset folder")
    s.add_argument("--out", required=True, help="output folder (sampled vgq-grasps dataset + plots/)")
    s.add_argument("--seed", type=_count("--seed"), help="sampling and split seed (default: sampling.seed)")
    s.add_argument("--no-plots", action="store_true")
    s.add_argument(
        "--workers", type=_positive_int("--workers"), help="processes reading and writing shards (default: CPU cores)"
    )
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.add_argument(
        "--split-over",
        metavar="FILE",
        help="JSON list of object ids to draw the object-wise split over instead of the dataset's own "
        "(a partly generated run split as its whole run is)",
    )
    _add_config_args(s)
    s.set_defaults(func=cmd_sample)

    c = sub.add_parser("crops", help="training crops (vgq-crops) for one architecture")
    c.add_argument("--in", dest="inp", required=True, help="grasp dataset folder (normally `datagen sample` output)")
    c.add_argument("--out", required=True, help="output folder")
    c.add_argument("--arch", required=True, choices=("fast_vgqcnn", "vgqcnn", "gqcnn"))
    c.add_argument(
        "--kappa",
        type=float,
        help="Fast-VGQ-CNN offset range, source px (default 36 for the 96 px window, in proportion)",
    )
    c.add_argument(
        "--window",
        type=_positive_int("--window"),
        default=96,
        help="crop window side, source px, a multiple of 32 (each window is resized to 32 x 32; default 96)",
    )
    c.add_argument(
        "--align-jaw",
        action="store_true",
        help="vgqcnn probe: each crop turned about its grasp so the jaw axis is horizontal (GQ-CNN's input), "
        "the pose's orientation with it; the service does not serve such a model",
    )
    c.add_argument(
        "--jaw-turns",
        type=_count("--jaw-turns"),
        default=0,
        metavar="K",
        help="fast_vgqcnn: cut each grasp's window from the image turned by the multiple of 180/K deg nearest "
        "its jaw axis (the axis within 90/K deg of horizontal; vgq.turns); 0 (default) windows not turned",
    )
    c.add_argument(
        "--context-scale",
        type=int,
        choices=CONTEXT_SCALES,
        default=0,
        metavar="S",
        help="fast_vgqcnn: also cut each window's context view, S windows wide around the same centre, resized "
        "to 32 x 32 (field context, float16; what --context trains on); 0 (default) none",
    )
    c.add_argument(
        "--seed", type=_count("--seed"), default=0, help="window offsets and the sensor model's noise (default 0)"
    )
    c.add_argument(
        "--sensor",
        default="realistic",
        help="depth-sensor model: a preset (clean, realistic; default realistic) or a .json file of settings",
    )
    c.add_argument(
        "--sensor-set",
        metavar="NAME=VALUE",
        action="append",
        default=[],
        help="override one sensor setting, e.g. --sensor-set baseline_m=0.05 --sensor-set blob_rate=4",
    )
    c.add_argument(
        "--splits",
        nargs="+",
        choices=("train", "val", "test"),
        default=["train", "val", "test"],
        help="splits to crop, the others written empty (default all; e.g. --splits test --sensor clean "
        "for a clean copy of the test split)",
    )
    c.add_argument(
        "--workers", type=_positive_int("--workers"), help="processes cropping objects (default: one per CPU core)"
    )
    c.add_argument("--quiet", action="store_true")
    c.set_defaults(func=cmd_crops)

    pg = sub.add_parser(
        "planner-grasps",
        help="the grasp planner's candidates on a grasp dataset's images, labelled by physics trials (vgq-grasps)",
    )
    pg.add_argument("--grasps", required=True, help="source grasp dataset (vgq-grasps, `datagen generate` output)")
    pg.add_argument("--out", required=True, help="output folder (vgq-grasps); rerun to resume")
    pg.add_argument(
        "--images-per-object",
        type=_positive_int("--images-per-object"),
        default=2,
        help="images per object the planner samples on (default 2)",
    )
    pg.add_argument(
        "--candidates",
        type=_positive_int("--candidates"),
        default=24,
        help="candidates labelled per image (default 24)",
    )
    pg.add_argument(
        "--trials", type=_positive_int("--trials"), help="noisy trials per grasp (default: the source's label trials)"
    )
    pg.add_argument("--workers", type=_positive_int("--workers"), help="worker processes (default: CPU cores)")
    pg.add_argument("--seed", type=_count("--seed"), default=0, help="run seed (default 0)")
    pg.add_argument(
        "--objects", type=_positive_int("--objects"), help="only the first N objects (round-robin over the families)"
    )
    pg.add_argument(
        "--sensor",
        default=RECIPE["sensor"],
        help=f"depth-sensor preset the planner's image passes through (default {RECIPE['sensor']}, the recipe's)",
    )
    pg.add_argument(
        "--sensor-seed",
        type=_count("--sensor-seed"),
        default=RECIPE["seed"],
        help="the sensor's per-image seed: `datagen crops --seed` of the same value sees the planner's image "
        f"(default {RECIPE['seed']}, the recipe's)",
    )
    pg.add_argument("--quiet", action="store_true", help="no progress bar")
    pg.set_defaults(func=cmd_planner_grasps)

    b = sub.add_parser("bench", help="labelled datapoints per minute and native positivity of a small run")
    b.add_argument("--objects", type=_positive_int("--objects"), default=3)
    b.add_argument("--cameras", type=_positive_int("--cameras"), default=10)
    b.add_argument("--workers", type=_positive_int("--workers"), default=1)
    b.add_argument("--source")
    b.add_argument("--seed", type=_count("--seed"))
    b.add_argument("--json", action="store_true", help="also print the result as JSON")
    b.add_argument("--physics", action="store_true", help="measure physics grasp trials per second instead")
    b.add_argument("--grasps", type=_positive_int("--grasps"), default=16, help="--physics: grasps per object")
    b.add_argument("--trials", type=_positive_int("--trials"), default=4, help="--physics: noisy trials per grasp")
    _add_config_args(b)
    b.set_defaults(func=cmd_bench)

    ls = sub.add_parser("labelstudy", help="compare grasp labels against physics trials under noise (issue 17)")
    ls.add_argument("--out", required=True, help="study folder (per-object results are cached: rerun to resume)")
    ls.add_argument("--grasps", type=_positive_int("--grasps"), default=24, help="grasps per object")
    ls.add_argument("--label-trials", type=_positive_int("--label-trials"), default=5)
    ls.add_argument("--eval-trials", type=_positive_int("--eval-trials"), default=5)
    ls.add_argument("--per-family", type=_count("--per-family"), default=2, help="held-out objects per everyday family")
    ls.add_argument(
        "--random-urdfs", type=_count("--random-urdfs"), default=8, help="held-out random_urdfs objects (past #600)"
    )
    ls.add_argument("--workers", type=_positive_int("--workers"), default=1)
    ls.add_argument("--seed", type=_count("--seed"), default=17)
    ls.add_argument("--summary-only", action="store_true", help="only summarise the cached results")
    ls.add_argument(
        "--more-label-trials",
        type=_count("--more-label-trials"),
        default=0,
        help="add this many label trials per grasp to the cached objects (AUC vs label trials)",
    )
    _add_config_args(ls)
    ls.set_defaults(func=cmd_labelstudy)

    r = sub.add_parser("recipe", help="build a bundled model's dataset (generate -> sample -> crops)")
    r.add_argument("--out", required=True)
    r.add_argument(
        "--version",
        choices=sorted(RECIPES),
        default="v2",
        help="v1: the model bundled today (random_urdfs, paper label, clean); v2 (default): families, "
        "physics label, sensor model",
    )
    r.add_argument("--objects", type=_positive_int("--objects"), help="random_urdfs objects (default: the recipe's)")
    r.add_argument("--workers", type=_positive_int("--workers"))
    r.add_argument("--dry-run", action="store_true", help="only print the commands")
    r.add_argument(
        "--no-leave-out",
        action="store_true",
        help="skip the leave-family-out split (build it later by rerunning without this flag)",
    )
    r.add_argument(
        "--more-test",
        type=_positive_int("--more-test"),
        metavar="N",
        help="also N new objects of each procedural family (run seed + 1), all in test: grasps_more, "
        "sampled_more, crops_more (per-family test numbers on more objects, for the same model)",
    )
    r.add_argument(
        "--stacker",
        action="store_true",
        help="also the placement stacker's fit set (run seed + 2, objects the recipe and --more-test never "
        "draw; `training stacker --fit`): grasps_stacker, sampled_stacker, crops_stacker",
    )
    r.add_argument(
        "--no-physics-cache",
        action="store_true",
        help="run every physics trial, not replaying the recipe's recorded ones (datagen/recipes/)",
    )
    r.set_defaults(func=cmd_recipe)

    o = sub.add_parser("objects", help="write example meshes of the object families and contact sheets")
    o.add_argument("--family", help="family name, comma-separated names, or all")
    o.add_argument("--count", type=_positive_int("--count"), default=5, help="objects per family (default 5)")
    o.add_argument("--out", help="output folder")
    o.add_argument("--seed", type=_count("--seed"), default=0, help="run seed (default 0)")
    o.add_argument("--list", action="store_true", help="list the families and exit")
    o.add_argument("--no-sheet", action="store_true", help="skip the contact-sheet PNGs")
    o.set_defaults(func=cmd_objects)

    st = sub.add_parser("stats", help="per-family counts of a grasp dataset (also while it is generated)")
    st.add_argument("--in", dest="inp", required=True, help="grasp dataset folder (vgq-grasps)")
    st.add_argument("--json", action="store_true", help="print JSON instead of a table")
    st.set_defaults(func=cmd_stats)

    k = sub.add_parser("config", help="print the (default or given) config as JSON")
    _add_config_args(k)
    k.set_defaults(func=cmd_config)
    return p


def main(argv: list[str] | None = None) -> int:
    from .config import ConfigError
    from .parallel import RayNotInstalled
    from .storage import DatasetError

    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (CliError, ConfigError, DatasetError, RayNotInstalled, OSError, ValueError) as e:
        print(f"datagen {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"datagen {args.command}: interrupted (rerun the same command to resume)", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
