"""Keep a few whole depth images of held-out test objects, with labelled grasps, in the
repository, so tests can score them through the service's own upload path (crop, pose
rows, encoder, head) instead of pre-made crops.

    python examples/make_heldout_images.py

The objects are test-split objects of the bundled model's recipe (``datagen recipe``:
the object ids of ``heldout_test_crops.npz``), regenerated with the recipe's config and
seed (datagen is deterministic per object), so the images and labels are exactly the
dataset's. Per object, ``--images`` images are drawn among those with a positive grasp, and
up to ``--per-class`` positive and as many negative grasps at random among their grasps
with psi < 90 deg (the sampling stage's filter); each grasp
gets its own window centre drawn as the crop stage draws it for Fast-VGQ-CNN (within kappa
per axis, an integer window). Only the images those grasps lie on are kept. Writes
``heldout_images.npz`` (see ``heldout.py`` for the arrays).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from datagen.__main__ import RECIPE
from datagen.config import DatagenConfig
from datagen.crops import fast_window_origins
from datagen.mesh import mesh_sources
from datagen.pipeline import generate_object, object_seed
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
    a = p.parse_args()

    crops = np.load(HERE / "heldout_test_crops.npz")
    test_ids = sorted(set(int(i) for i in crops["object_id"]))[: a.objects]
    cfg = DatagenConfig().with_overrides(
        {
            "cameras_per_pose": RECIPE["cameras"],
            "seed": RECIPE["seed"],
            "num_objects": RECIPE["objects"],
            **RECIPE["set"],
        }
    )
    geom = vcrop.CropGeometry(kappa_px=RECIPE["kappa"])
    sources = mesh_sources(cfg.source)[: RECIPE["objects"]]
    rng = np.random.default_rng(a.seed)
    depth, obj, rows, labels, image_index, centers = [], [], [], [], [], []
    for oid in test_ids:
        src = sources[oid]
        images, grasps = generate_object(src, cfg, oid, object_seed(cfg.seed, src.name))
        keep = grasps["psi"] < cfg.sampling.max_psi
        pos = keep & (grasps["quality"] > cfg.label_threshold)
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
            centers.append(vcrop.window_center(fast_window_origins(uv, geom, rng), geom))
            rows.append(np.column_stack([uv, grasps["z"][s], grasps["q"][s]]))
            labels.append(pos[s].astype(np.uint8))
            image_index.append(np.full(len(s), len(depth), np.int32))
            depth.append(images["depth"][img].astype(np.float32))
            obj.append(oid)
        print(f"object {oid} ({src.name}): {len(depth)} images so far", flush=True)
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
