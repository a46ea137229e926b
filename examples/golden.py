"""Golden scores of the bundled model on the example image, computed without the project's
crop or pose code: the window and the offsets are written out here by hand, then the ONNX
encoder and fp32 head run directly in onnxruntime.

    python examples/golden.py            # rewrite examples/golden_scores.json (with the model)

``scripts/make_default_model.sh`` reruns this after exporting the model; the golden file is
never regenerated on its own (``tests/test_golden_scores.py`` compares the running service,
this computation and the stored numbers).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import onnxruntime as ort
from PIL import Image

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
MODEL = ROOT / "models" / "fast-vgqcnn-default"
DEPTH = HERE / "depth_example.npy"
GOLDEN = HERE / "golden_scores.json"

# The example image is 300 x 300; the service's default window centre is the image centre
# (149.5, 149.5). A 96 px window centred there starts at pixel 149.5 - 48 + 0.5 = 102 and ends
# before 198; it shrinks 3 x (96 -> 32) with Pillow's bilinear filter. A grasp at (u, v)
# enters the network as ((u - 149.5) / 3, (v - 149.5) / 3) crop pixels.
CENTRE = 149.5
ROWS = COLS = slice(102, 198)
SHRINK = 3

# Offsets (source px) from the window centre, none symmetric to another: a flipped sign or
# swapped u and v scores a different place. z (m) and one camera-frame quaternion (w, x, y, z).
OFFSETS = [(-30.0, 0.0), (30.0, 0.0), (0.0, -30.0), (0.0, 30.0), (-21.0, 12.0), (15.0, -27.0),
           (6.0, 24.0), (-33.0, -33.0), (33.0, 9.0), (-9.0, -3.0), (12.0, 12.0), (-3.0, 34.5)]
Z = 0.73
QUAT = (0.644616, -0.295576, 0.232533, -0.665608)


def golden_grasps() -> np.ndarray:
    """(k, 7) grasps u, v, z, qw, qx, qy, qz: the example's grasps, then the hand-set offsets."""
    example = np.array(json.loads((HERE / "grasps_example.json").read_text())["grasps"], np.float64)
    offs = np.array([[CENTRE + du, CENTRE + dv, Z, *QUAT] for du, dv in OFFSETS])
    return np.concatenate([example, offs])


def hand_scores(depth: np.ndarray, grasps: np.ndarray, model_dir: Path = MODEL, head: str = "head.onnx") -> np.ndarray:
    """Success probabilities (k,) of ``grasps`` on the 300 x 300 ``depth`` (metres)."""
    assert depth.shape == (300, 300), depth.shape
    window = np.ascontiguousarray(depth[ROWS, COLS], np.float32)
    small = np.asarray(Image.fromarray(window).resize((96 // SHRINK,) * 2, Image.Resampling.BILINEAR), np.float32)
    q = grasps[:, 3:7] / np.linalg.norm(grasps[:, 3:7], axis=1, keepdims=True)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    poses = np.column_stack([(grasps[:, 0] - CENTRE) / SHRINK, (grasps[:, 1] - CENTRE) / SHRINK, grasps[:, 2], q])
    enc = ort.InferenceSession(str(model_dir / "encoder.onnx"), providers=["CPUExecutionProvider"])
    hd = ort.InferenceSession(str(model_dir / head), providers=["CPUExecutionProvider"])
    term = enc.run(None, {"depth_crop": small[None, None]})[0]
    return hd.run(None, {"image_term": term, "poses": poses.astype(np.float32)})[0]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model-dir", default=str(MODEL))
    p.add_argument("--out", default=str(GOLDEN))
    a = p.parse_args()
    model_dir = Path(a.model_dir)
    card = json.loads((model_dir / "model_card.json").read_text())
    g = golden_grasps()
    p32 = hand_scores(np.load(DEPTH), g, model_dir)
    doc = {"model_version": card["model_version"], "image": DEPTH.name, "window_center": [CENTRE, CENTRE],
           "head": "fp32", "grasps": [[round(float(x), 6) for x in r] for r in g],
           "p_success": [float(x) for x in p32]}
    import sys

    sys.path.insert(0, str(ROOT))
    from vgq import atomic

    atomic.write_json(Path(a.out), doc)
    print(f"{a.out}: {len(g)} golden scores of {card['model_version']}")


if __name__ == "__main__":
    main()
