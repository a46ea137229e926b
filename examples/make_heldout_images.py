"""Keep a few whole depth images of held-out test objects, with labelled grasps, in the
repository, so tests can score them through the service's own upload path (crop, pose
rows, encoder, head) instead of pre-made crops.

    python examples/make_heldout_images.py                       # a recipe without families: regenerates
    python examples/make_heldout_images.py --grasps data/v2/grasps  # reads a generated dataset

With ``--grasps`` the test objects are taken round-robin over the dataset's families, in
proportion (``datagen.pipeline.interleaved``; v2: the first 44 then cover every family, not only
the ``random_urdfs``, whose ids come first).

The objects are test-split objects of the bundled model's recipe (``datagen recipe``:
the object ids of ``heldout_test_crops.npz``), regenerated with the recipe's config and
seed (datagen is deterministic per object), or with ``--grasps`` read from the recipe's
generated grasp dataset (a physics-labelled object takes ~40 s to regenerate), so the images
and labels are exactly the dataset's (clean renders: a sensor model is the caller's to add). Per object, ``--images`` images are drawn among those with a positive grasp, and
up to ``--per-class`` positive and as many negative grasps at random among their grasps
with psi < 90 deg (the sampling stage's filter); each grasp
gets its own window centre drawn as the crop stage draws it for Fast-VGQ-CNN (within kappa
per axis, an integer window), moved to the image's edge where it fell outside the image (the
service's ``center_u`` / ``center_v`` must lie in the image). Only the images those grasps lie on are kept. Writes
``heldout_images.npz`` (see ``heldout.py`` for the arrays).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from datagen.config import DatagenConfig
from datagen.crops import fast_window_origins
from datagen.mesh import mesh_sources
from datagen.pipeline import generate_object, interleaved, object_seed
from datagen.recipe import RECIPE
from datagen.sampling import SamplingParams
from vgq import atomic
from vgq import crop as vcrop

HERE = Path(__file__).resolve().parent


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--objects", type=int, default=44, help="test objects to use (first N test ids)")
    p.add_argument("--images", type=int, default=2, help="images per object (drawn among those with a positive)")
    p.add_argument("--per-class", type=int, default=16, help="positives and negatives per object (at most)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=str(HERE / "heldout_images.npz"))
    p.add_argument("--crops", default=str(HERE / "heldout_test_crops.npz"), help="whose object ids to use")
    p.add_argument("--grasps", help="the recipe's generated grasp dataset (datagen generate --out DIR) to read")
    a = p.parse_args()

    crops = np.load(a.crops)
    test_ids = sorted(set(int(i) for i in crops["object_id"]))
    geom = vcrop.CropGeometry(kappa_px=RECIPE["kappa"])
    if a.grasps:
        from datagen.storage import open_dataset

        ds = open_dataset(a.grasps)
        threshold, max_psi = ds.label_threshold, SamplingParams().max_psi
        test_ids = interleaved(test_ids, ds.manifest)  # every family in proportion, not only the first
        entries = {e["object_id"]: e for e in ds.shard_entries}

        def load(oid: int):
            if oid not in entries:
                raise SystemExit(f"make_heldout_images: object {oid} has no shard in {a.grasps} (not generated?)")
            shard = ds.load(entries[oid])
            return shard.name, shard.images, shard.grasps
    else:
        if RECIPE["families"]:
            raise SystemExit(
                "make_heldout_images: the bundled recipe has object families; read its generated dataset "
                "with --grasps DIR (datagen recipe --version v2 --out data/v2 writes data/v2/grasps)"
            )
        cfg = DatagenConfig().with_overrides(
            {
                "cameras_per_pose": RECIPE["cameras"],
                "seed": RECIPE["seed"],
                "num_objects": RECIPE["objects"],
                **RECIPE["set"],
            }
        )
        threshold, max_psi = cfg.label_threshold, cfg.sampling.max_psi
        sources = mesh_sources(cfg.source)[: RECIPE["objects"]]

        def load(oid: int):
            src = sources[oid]
            return (src.name, *generate_object(src, cfg, oid, object_seed(cfg.seed, src.name)))

    test_ids = test_ids[: a.objects]
    rng = np.random.default_rng(a.seed)
    depth, obj, rows, labels, image_index, centers = [], [], [], [], [], []
    for oid in test_ids:
        name, images, grasps = load(oid)
        keep = grasps["psi"] < max_psi
        pos = keep & (grasps["quality"] > threshold)
        with_pos = np.unique(grasps["image_index"][pos])
        if len(with_pos) == 0:
            continue
        imgs = rng.choice(with_pos, min(a.images, len(with_pos)), replace=False)
        on = keep & np.isin(grasps["image_index"], imgs)
        chosen = []
        for cls in (True, False):
            idx = np.flatnonzero(on & (pos == cls))
            chosen.append(rng.choice(idx, min(a.per_class, len(idx)), replace=False))
        sel = np.sort(np.concatenate(chosen))
        for img in np.unique(grasps["image_index"][sel]):
            s = sel[grasps["image_index"][sel] == img]
            uv = np.stack([grasps["u"][s], grasps["v"][s]], 1)
            c = vcrop.window_center(fast_window_origins(uv, geom, rng), geom)
            h, w = images["depth"][img].shape  # the service takes window centres in the image: move those
            centers.append(np.clip(c, 0.5, [w - 1.5, h - 1.5]))  # outside to its edge (still within kappa)
            rows.append(np.column_stack([uv, grasps["z"][s], grasps["q"][s]]))
            labels.append(pos[s].astype(np.uint8))
            image_index.append(np.full(len(s), len(depth), np.int32))
            depth.append(images["depth"][img].astype(np.float32))
            obj.append(oid)
        print(f"object {oid} ({name}): {len(depth)} images so far", flush=True)
    atomic.save_npz(
        a.out,
        compressed=True,
        depth=np.stack(depth),
        object_id=np.array(obj, np.int32),
        center=np.concatenate(centers).astype(np.float32),
        grasps=np.concatenate(rows).astype(np.float32),
        labels=np.concatenate(labels),
        image_index=np.concatenate(image_index),
    )
    y = np.concatenate(labels)
    print(
        f"wrote {a.out}: {len(depth)} images of {len(set(obj))} test objects, {len(y)} grasps ({int(y.sum())} positive)"
    )


if __name__ == "__main__":
    main()
