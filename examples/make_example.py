"""Make the example depth image and grasps kept in examples/ from a generated dataset.

    datagen generate --out data/example --objects 8 --cameras 4
    python examples/make_example.py --data data/example

Picks the rendered image with the most positive grasps inside the default crop window
(image centre +/- kappa) and writes ``depth_example.npy`` (300 x 300 float32 metres) and
``grasps_example.json`` (``grasps`` rows u, v, z, qw, qx, qy, qz, with their ground-truth
``labels`` and robust Ferrari-Canny ``quality``, which the service ignores).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from datagen.storage import open_dataset
from vgq import atomic

HERE = Path(__file__).resolve().parent


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True, help="a vgq-grasps dataset (datagen generate)")
    p.add_argument("--kappa", type=float, default=36.0, help="half window the grasps must lie in (source px)")
    p.add_argument("--max-grasps", type=int, default=16)
    p.add_argument("--out", default=str(HERE))
    a = p.parse_args()
    ds = open_dataset(a.data)
    best = None
    for shard in ds:
        g, im = shard.grasps, shard.images
        h, w = im["depth"].shape[1:]
        c = np.array([(w - 1) / 2, (h - 1) / 2])
        inside = np.all(np.abs(np.stack([g["u"], g["v"]], 1) - c) <= a.kappa, axis=1)
        pos = inside & (g["quality"] > ds.label_threshold)
        for i in range(len(im["depth"])):
            n = int(pos[g["image_index"] == i].sum())
            if best is None or n > best[0]:
                best = (n, shard, i, inside)
    if best is None:
        raise SystemExit(f"{a.data}: no images")
    n, shard, i, inside = best
    g = shard.grasps
    sel = np.flatnonzero(inside & (g["image_index"] == i))
    labels = g["quality"][sel] > ds.label_threshold
    rng = np.random.default_rng(0)
    pos, neg = sel[labels], sel[~labels]
    k_pos = min(len(pos), a.max_grasps // 2)
    pick = np.concatenate([rng.permutation(pos)[:k_pos], rng.permutation(neg)[: a.max_grasps - k_pos]])
    rows = np.concatenate([np.stack([g["u"][pick], g["v"][pick], g["z"][pick]], 1), g["q"][pick]], 1)
    out = Path(a.out)
    atomic.save_npy(out / "depth_example.npy", shard.images["depth"][i].astype(np.float32))
    atomic.write_json(
        out / "grasps_example.json",
        {
            "grasps": [[round(float(x), 6) for x in r] for r in rows],
            "labels": [int(x) for x in (g["quality"][pick] > ds.label_threshold)],
            "quality": [round(float(x), 6) for x in g["quality"][pick]],
            "source": {
                "dataset": str(a.data),
                "object": shard.name,
                "image_index": int(i),
                "camera_d": float(shard.images["camera_d"][i]),
                "camera_phi_deg": float(np.degrees(shard.images["camera_phi"][i])),
            },
        },
    )
    print(
        f"wrote {out}/depth_example.npy and grasps_example.json: object {shard.name}, {len(pick)} grasps, {n} positive in window"
    )


if __name__ == "__main__":
    main()
