"""Golden scores of the bundled model on the example image, computed without the project's
crop or pose code: the window and the offsets are written out here by hand, then the ONNX
encoder and fp32 head run directly in onnxruntime.

    python examples/golden.py   # rewrite golden_scores.json and golden_heldout.json (with the model)

A model whose head reads placement rows (``vgq.placement``: where each grasp sits on its object) gets
them from the project's one analysis of the image (``planning.placement``, as datagen and the service
compute them): only they are not written out by hand.

``scripts/make_default_model.sh`` reruns this after exporting the model; the golden file is
never regenerated on its own (``tests/test_golden_scores.py`` and ``tests/test_default_model.py``
compare the running service, this computation and the stored numbers). ``golden_heldout.json``
holds the fp32 scores of the held-out grasps of ``heldout_images.npz`` (``heldout.py``), each in
its own window.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import onnxruntime as ort
from PIL import Image

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
MODEL = ROOT / "models" / "fast-vgqcnn-default"
DEPTH = HERE / "depth_example.npy"
GOLDEN = HERE / "golden_scores.json"
GOLDEN_HELDOUT = HERE / "golden_heldout.json"

# The example image is 300 x 300; the service's default window centre is the image centre
# (149.5, 149.5). A 96 px window centred there starts at pixel 149.5 - 48 + 0.5 = 102 and ends
# before 198; it shrinks 3 x (96 -> 32) with Pillow's bilinear filter. A grasp at (u, v)
# enters the network as ((u - 149.5) / 3, (v - 149.5) / 3) crop pixels.
CENTRE = 149.5
ROWS = COLS = slice(102, 198)
SHRINK = 3

# Offsets (source px) from the window centre, none symmetric to another: a flipped sign or
# swapped u and v scores a different place. z (m) and one camera-frame quaternion (w, x, y, z).
OFFSETS = [
    (-30.0, 0.0),
    (30.0, 0.0),
    (0.0, -30.0),
    (0.0, 30.0),
    (-21.0, 12.0),
    (15.0, -27.0),
    (6.0, 24.0),
    (-33.0, -33.0),
    (33.0, 9.0),
    (-9.0, -3.0),
    (12.0, 12.0),
    (-3.0, 34.5),
]
Z = 0.73
QUAT = (0.644616, -0.295576, 0.232533, -0.665608)


def golden_grasps() -> np.ndarray:
    """(k, 7) grasps u, v, z, qw, qx, qy, qz: the example's grasps, then the hand-set offsets."""
    example = np.array(json.loads((HERE / "grasps_example.json").read_text())["grasps"], np.float64)
    offs = np.array([[CENTRE + du, CENTRE + dv, Z, *QUAT] for du, dv in OFFSETS])
    return np.concatenate([example, offs])


class HandScorer:
    """The bundled model's ONNX graphs, run directly, on windows cut out by hand."""

    def __init__(self, model_dir: Path = MODEL, head: str = "head.onnx"):
        self.encoder = ort.InferenceSession(str(model_dir / "encoder.onnx"), providers=["CPUExecutionProvider"])
        self.head = ort.InferenceSession(str(model_dir / head), providers=["CPUExecutionProvider"])
        #: the head's pose width: 7, or 14 for a placement head (each pose row, then its placement row)
        self.pose_width = int(self.head.get_inputs()[1].shape[1])

    def placement_rows(self, depth: np.ndarray, grasps: np.ndarray, image_index: np.ndarray) -> np.ndarray | None:
        """None for a head without placement; else the (m, 7) placement rows of ``grasps`` (m, 7), each
        on its image ``depth[image_index]`` ((n, 300, 300) metres, the default camera)."""
        if self.pose_width == 7:
            return None
        sys.path.insert(0, str(ROOT))
        from planning.placement import placement_rows
        from vgq.camera import DEFAULT_INTRINSICS

        g, out = np.asarray(grasps, np.float64), np.zeros((len(grasps), 7), np.float32)
        for i in np.unique(image_index):
            on = image_index == i
            out[on] = placement_rows(np.asarray(depth[i], np.float32), DEFAULT_INTRINSICS, g[on, :3], g[on, 3:7])
        return out

    @staticmethod
    def with_rows(poses: np.ndarray, rows: np.ndarray | None) -> np.ndarray:
        """A placement head's input: each pose row followed by its placement row (``rows`` None: none)."""
        return poses if rows is None else np.column_stack([poses, rows]).astype(np.float32)

    @staticmethod
    def small_window(depth: np.ndarray, centre=(CENTRE, CENTRE)) -> np.ndarray:
        """The 96 px window centred on ``centre`` (u, v; a window centre: an integer + 0.5),
        the image's edge pixels repeated where the window leaves it, shrunk to 32 x 32."""
        u0, v0 = centre[0] - 47.5, centre[1] - 47.5
        assert u0 == int(u0) and v0 == int(v0), centre
        u0, v0 = int(u0) + 96, int(v0) + 96  # in the image padded by 96 px of repeated edge
        padded = np.pad(np.asarray(depth, np.float32), 96, mode="edge")
        window = np.ascontiguousarray(padded[v0 : v0 + 96, u0 : u0 + 96])
        return np.asarray(Image.fromarray(window).resize((96 // SHRINK,) * 2, Image.Resampling.BILINEAR), np.float32)

    @staticmethod
    def poses(grasps: np.ndarray, centre=(CENTRE, CENTRE)) -> np.ndarray:
        """Network pose rows: offsets from ``centre`` / 3, z, unit quaternion with w >= 0."""
        q = grasps[:, 3:7] / np.linalg.norm(grasps[:, 3:7], axis=1, keepdims=True)
        q *= np.where(q[:, :1] < 0, -1.0, 1.0)
        du, dv = (grasps[:, 0] - centre[0]) / SHRINK, (grasps[:, 1] - centre[1]) / SHRINK
        return np.column_stack([du, dv, grasps[:, 2], q]).astype(np.float32)

    @staticmethod
    def poses_each(grasps: np.ndarray, centres: np.ndarray) -> np.ndarray:
        """Pose rows of grasps (m, 7), each in its own window (centres (m, 2))."""
        g = np.asarray(grasps, np.float64)
        return np.concatenate([HandScorer.poses(g[j : j + 1], centres[j]) for j in range(len(g))])

    def terms(self, small: np.ndarray) -> np.ndarray:
        """(n, 32, 32) shrunk windows -> (n, 1024) image terms."""
        return self.encoder.run(None, {"depth_crop": np.asarray(small, np.float32)[:, None]})[0]

    def scores(self, term: np.ndarray, poses: np.ndarray) -> np.ndarray:
        """(1 or k, 1024) image terms, (k, 7) pose rows -> (k,) success probabilities."""
        return self.head.run(None, {"image_term": term, "poses": poses})[0]


def hand_scores(
    depth: np.ndarray,
    grasps: np.ndarray,
    model_dir: Path = MODEL,
    head: str = "head.onnx",
    placement_from: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Success probabilities (k,) of ``grasps`` on the 300 x 300 ``depth`` (metres), default window.
    A placement head's rows are read off ``placement_from`` (an image and the same grasps in its
    pixels, e.g. the image before a shift by hand) or else off ``depth`` and ``grasps``."""
    assert depth.shape == (300, 300), depth.shape
    s = HandScorer(model_dir, head)
    on, at = placement_from if placement_from is not None else (depth, grasps)
    rows = s.placement_rows(np.asarray(on)[None], at, np.zeros(len(grasps), int))
    return s.scores(s.terms(s.small_window(depth)[None]), s.with_rows(s.poses(grasps), rows))


def heldout_scores(
    depth: np.ndarray, grasps: np.ndarray, image_index: np.ndarray, center: np.ndarray, model_dir: Path = MODEL
) -> np.ndarray:
    """fp32 success probabilities (m,) of held-out grasps, each in the window at its ``center``."""
    s = HandScorer(model_dir)
    terms = s.terms(np.stack([s.small_window(depth[i], c) for i, c in zip(image_index, center)]))
    return s.scores(terms, s.with_rows(s.poses_each(grasps, center), s.placement_rows(depth, grasps, image_index)))


def balanced_accuracy(labels: np.ndarray, p: np.ndarray) -> float:
    y, pred = np.asarray(labels) == 1, np.asarray(p) > 0.5
    return float((pred[y].mean() + (~pred[~y]).mean()) / 2)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model-dir", default=str(MODEL))
    p.add_argument("--out", default=str(GOLDEN))
    p.add_argument("--heldout-out", default=str(GOLDEN_HELDOUT))
    a = p.parse_args()
    model_dir = Path(a.model_dir)
    card = json.loads((model_dir / "model_card.json").read_text())
    g = golden_grasps()
    p32 = hand_scores(np.load(DEPTH), g, model_dir)
    doc = {
        "model_version": card["model_version"],
        "image": DEPTH.name,
        "window_center": [CENTRE, CENTRE],
        "head": "fp32",
        "grasps": [[round(float(x), 6) for x in r] for r in g],
        "p_success": [float(x) for x in p32],
    }
    sys.path.insert(0, str(ROOT))
    from heldout import load_heldout_images

    from vgq import atomic

    atomic.write_json(Path(a.out), doc)
    print(f"{a.out}: {len(g)} golden scores of {card['model_version']}")
    h = load_heldout_images()
    p = heldout_scores(h.depth, h.grasps, h.image_index, h.center, model_dir)
    atomic.write_json(
        Path(a.heldout_out),
        {
            "model_version": card["model_version"],
            "images": "heldout_images.npz",
            "head": "fp32",
            "balanced_accuracy": balanced_accuracy(h.labels, p),
            "p_success": [float(x) for x in p],
        },
    )
    print(f"{a.heldout_out}: {len(p)} held-out scores, balanced accuracy {balanced_accuracy(h.labels, p):.4f}")


if __name__ == "__main__":
    main()
