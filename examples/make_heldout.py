"""Keep a small balanced sample of held-out test crops in the repository, so the tests can
check the bundled model on real data its training never saw (objects of the test split).

    python examples/make_heldout.py --data data/recipe/crops

Writes ``heldout_test_crops.npz``: ``images`` (n, 32, 32) float32 metres, ``poses`` (n, 7)
u, v (crop px), z (m), qw, qx, qy, qz as the head graph takes them, ``labels`` (n,) uint8,
``object_id`` (n,) int32; half positives, half negatives, drawn with a fixed seed.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from training.data import open_crop_dataset
from vgq import atomic

HERE = Path(__file__).resolve().parent


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True, help="a Fast-VGQ-CNN crop dataset (datagen crops)")
    p.add_argument("--per-class", type=int, default=128)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=str(HERE / "heldout_test_crops.npz"))
    a = p.parse_args()
    split = open_crop_dataset(a.data).split("test")
    labels = np.asarray(split.arrays["labels"])
    rng = np.random.default_rng(a.seed)
    idx = np.sort(np.concatenate([rng.choice(np.flatnonzero(labels == c), a.per_class, replace=False) for c in (1, 0)]))
    crops, poses, y = split.batch(idx, "fast_vgqcnn")
    atomic.save_npz(
        a.out,
        images=crops.numpy().astype(np.float32),
        poses=poses.numpy().astype(np.float32),
        labels=y.numpy().astype(np.uint8),
        object_id=np.asarray(split.arrays["object_id"])[idx].astype(np.int32),
    )
    print(
        f"wrote {a.out}: {len(idx)} crops from {len(np.unique(np.asarray(split.arrays['object_id'])[idx]))} test objects"
    )


if __name__ == "__main__":
    main()
