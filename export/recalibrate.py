"""Calibrate an exported model on grasps at their native positivity, with the ONNX graphs the
service runs (no torch checkpoint needed):

    python -m export.recalibrate --model-dir models/fast-vgqcnn-default --grasps DIR \\
        [--per-split 6000] [--reliability-png docs/img/reliability_diagram.png]

``DIR`` is a ``vgq-grasps`` dataset (``datagen generate``, not resampled) of objects the model
never saw, with the label the model learned. Its objects are split in two halves (object-wise,
seeded): Platt scaling is fitted on one and its expected calibration error measured on the
other. Rows are the grasps the service would score (psi < 90 deg), each in a window drawn as
the crop stage draws Fast-VGQ-CNN training windows (of the image turned towards the jaw for
a model of turned windows), cropped with the service's own preprocessing; so the calibrated ``p_success`` means the success rate of such grasps. The
card's ``calibration`` (the format of ``python -m export``'s) and the reliability diagram are
rewritten atomically; nothing else in the model folder changes.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from vgq import atomic
from vgq.crop import window_center
from vgq.grasps import pose_rows
from vgq.model_card import CARD_NAME, ModelCard

from .calibrate import DIAGRAM, CalibrationError, calibration_report, plot_reliability


def native_rows(grasps_dir: str | Path, max_psi: float = np.pi / 2):
    """(objects, per-object list of (depth images, rows (m, 7), labels (m,), image index (m,)))
    of a grasp dataset, keeping grasps with psi < ``max_psi``; labels by the dataset's threshold."""
    from datagen import storage

    ds = storage.open_dataset(grasps_dir)
    thr = float(ds.manifest["label_threshold"])
    out = {}
    for s in ds.manifest["shards"]:
        images, g = storage.read_shard(Path(grasps_dir) / s["file"], s.get("sha256"))
        keep = g["psi"] < max_psi
        rows = np.column_stack([g["u"], g["v"], g["z"], g["q"]])[keep]
        out[int(s["object_id"])] = (
            images["depth"],
            rows,
            (g["quality"][keep] > thr).astype(np.int64),
            g["image_index"][keep],
        )
    return out


def score_native(model, data: dict, object_ids, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Raw probabilities and labels of up to ``n`` random rows of ``object_ids``. A placement head
    (the card's ``placement_columns``) also reads each grasp's placement row, from its image as the
    crop stage and the service compute it (``planning.placement``, one analysis per image)."""
    from datagen.crops import fast_window_origins, turned_crops
    from planning.placement import ImagePlacement
    from service.preprocess import window_input

    index = [(o, i) for o in object_ids for i in range(len(data[o][1]))]
    pick = rng.choice(len(index), min(n, len(index)), replace=False)
    p, y = np.empty(len(pick)), np.empty(len(pick), np.int64)
    geom, intr = model.geometry, model.card.intrinsics
    analyses = {}  # (object, image) -> ImagePlacement
    for j, k in enumerate(pick):
        o, i = index[k]
        depth, rows, labels, image_index = data[o]
        row = rows[i : i + 1]
        if geom.jaw_turns:  # the window of the image turned towards the jaw, as the crop stage cuts it
            img, puv, _, q = turned_crops(depth[image_index[i]], row[:, :2], row[:, 2], row[:, 3:7], geom, intr, rng)
            poses = np.concatenate([puv, row[:, 2:3], q], axis=1).astype(np.float32)
        else:
            origin = fast_window_origins(row[:, :2], geom, rng)[0]
            img = window_input(depth[image_index[i]], origin, geom, 1.0).image
            poses = pose_rows(row, window_center(origin, geom), geom, 1)
        if model.card.placement_columns:
            key = (o, int(image_index[i]))
            if key not in analyses:
                analyses[key] = ImagePlacement.analyse(depth[image_index[i]], intr)
            poses = np.c_[poses, analyses[key].rows(row[:, :3], row[:, 3:7])].astype(np.float32)
        p[j] = float(model.score(model.encode(img), poses)[0])
        y[j] = labels[i]
    return p, y


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m export.recalibrate", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--model-dir", required=True)
    ap.add_argument("--grasps", required=True, help="a vgq-grasps dataset of unseen objects (datagen generate)")
    ap.add_argument(
        "--per-split", type=int, default=6000, help="rows scored for the fit and for the test (default 6000)"
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--reliability-png", help="also copy the reliability diagram here")
    a = ap.parse_args(argv)
    if a.per_split < 100:
        ap.error("--per-split must be >= 100")
    from service.runtime import FastModel

    model_dir = Path(a.model_dir)
    try:
        model = FastModel(model_dir, threads=1, head_precision="fp32")
        data = native_rows(a.grasps)
        ids = np.array(sorted(data))
        if len(ids) < 2:
            raise CalibrationError(f"{a.grasps}: need at least 2 objects with grasps, got {len(ids)}")
        rng = np.random.default_rng(a.seed)
        ids = rng.permutation(ids)
        fit_ids, test_ids = ids[: len(ids) // 2], ids[len(ids) // 2 :]
        labels_all = np.concatenate([data[o][2] for o in ids])
        native = float(labels_all.mean())
        print(f"{len(ids)} objects, {len(labels_all)} grasps with psi < 90 deg, native positivity {100 * native:.2f}%")
        p_fit, y_fit = score_native(model, data, fit_ids, a.per_split, rng)
        p_test, y_test = score_native(model, data, test_ids, a.per_split, rng)
        report = calibration_report(
            p_fit,
            y_fit,
            p_test,
            y_test,
            native,
            f"native rows (psi < 90 deg) of {len(ids)} unseen objects ({Path(a.grasps).name})",
            "platt",
            splits=(f"fit objects ({len(fit_ids)})", f"test objects ({len(test_ids)})"),
        )
    except (CalibrationError, ValueError, OSError) as e:
        print(f"recalibrate: error: {e}", file=sys.stderr)
        return 2
    d = json.loads((model_dir / CARD_NAME).read_text())  # every other key exactly as exported
    d["calibration"] = report.to_dict()
    ModelCard.from_dict(d).calibrator()  # the service must be able to read it back
    plot_reliability(report, model_dir / DIAGRAM)
    atomic.write_json(model_dir / CARD_NAME, d)
    if a.reliability_png:
        atomic.write_bytes(a.reliability_png, (model_dir / DIAGRAM).read_bytes())
    t = report.test
    print(
        f"Platt slope {report.calibration.slope:.3f}, intercept {report.calibration.intercept:.3f}; "
        f"ECE on {t['n']} test rows: raw {t['ece_raw']:.4f} -> calibrated {t['ece_calibrated']:.4f}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
