"""What a model folder scores when the camera is rolled about its optical axis and nobody says so.

Every training camera had level image rows (``datagen.camera.look_at_table_origin``). A camera
rolled by k quarter turns sees each crop window turned by k quarter turns, each grasp's offset
from its window's centre turned with it and each grasp's orientation R as R_z(roll)^T R: exact
for the network's inputs (no resampling), with the labels unchanged. This scores a crop split
so, for k = 0..3, and prints balanced accuracy overall and by the camera's elevation phi. (The
service undoes the roll when the client sends the world's up direction: README, "A camera at
any roll"; examples/camera_faults_check.py measures that end to end.)

    .venv/bin/python examples/rolled_camera_check.py --model-dir models/fast-vgqcnn-default \\
        --data data/v2/crops --max-n 10000
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from datagen import storage  # noqa: E402
from export.evaluate import crop_rows, raw_scores  # noqa: E402
from training import metrics as M  # noqa: E402
from vgq.camera import Intrinsics, map_pixels  # noqa: E402
from vgq.pose import canonical_quaternion, roll_quaternions  # noqa: E402

PHI_BINS_DEG = (0, 10, 20, 35, 50, 70)
#: a camera whose pixels are offsets from the window centre (unit focal length, centre at 0)
OFFSETS = Intrinsics(fx=1.0, fy=1.0, cx=0.0, cy=0.0, width=1, height=1)


def rolled_inputs(images: np.ndarray, poses: np.ndarray, quarter_turns: int) -> tuple[np.ndarray, np.ndarray]:
    """Crops (n, S, S) and pose rows (n, 7) as the camera rolled by ``quarter_turns`` x 90 deg sees them."""
    roll = quarter_turns * np.pi / 2
    p = poses.astype(np.float64).copy()
    p[:, :2] = map_pixels(p[:, :2], OFFSETS, OFFSETS, roll)  # offsets from the window centre turn as pixels do
    p[:, 3:7] = canonical_quaternion(roll_quaternions(poses[:, 3:7], roll))  # the network reads w >= 0
    # a pixel at offset (du, dv) moves to (c du + s dv, -s du + c dv): np.rot90 by +1 maps (du, dv) -> (dv, -du)
    return np.ascontiguousarray(np.rot90(images, k=quarter_turns, axes=(1, 2))), p.astype(np.float32)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model-dir", default="models/fast-vgqcnn-default")
    ap.add_argument("--data", required=True, help="a Fast-VGQ-CNN crop dataset (datagen crops)")
    ap.add_argument("--split", default="test")
    ap.add_argument("--max-n", type=int, default=10000, help="rows drawn at random (seed 0), as export.evaluate")
    args = ap.parse_args(argv)
    rows = crop_rows(args.data, args.split, args.max_n)
    labels = rows["labels"]
    arrays = storage.open_crops(args.data, args.split)
    phi = np.degrees(np.asarray(arrays["camera_phi"][M.sample_rows(len(arrays["labels"]), args.max_n, 0)]))
    bins = list(zip(PHI_BINS_DEG[:-1], PHI_BINS_DEG[1:]))
    print("roll (deg) | all | " + " | ".join(f"phi {lo}-{hi}" for lo, hi in bins) + " | decisions changed")
    first = None
    for k in range(4):
        images, poses = rolled_inputs(rows["images"], rows["poses"], k)
        s = raw_scores(args.model_dir, images, poses)
        first = s if first is None else first
        by_phi = []
        for lo, hi in bins:
            m = (phi >= lo) & (phi < hi)
            by_phi.append(f"{100 * M.binary_metrics(labels[m], s[m])['balanced_accuracy']:.1f}%")
        changed = np.mean((s > 0.5) != (first > 0.5))
        ba = 100 * M.binary_metrics(labels, s)["balanced_accuracy"]
        print(f"{90 * k} | {ba:.1f}% | " + " | ".join(by_phi) + f" | {100 * changed:.1f}%", flush=True)
    print(f"rows: {len(labels)}; by phi: " + ", ".join(f"{((phi >= lo) & (phi < hi)).sum()}" for lo, hi in bins))
    return 0


if __name__ == "__main__":
    sys.exit(main())
