"""export.recalibrate: Platt scaling of an exported model on native grasps, with the ONNX
graphs only; it rewrites the card's calibration (readable by the service) and nothing else."""

import json
import shutil
from pathlib import Path

import numpy as np
from datagen_fakes import fake_dataset

from export.recalibrate import main
from vgq.model_card import ModelCard

DEFAULT = Path(__file__).resolve().parent.parent / "models" / "fast-vgqcnn-default"


def _ranked_by(model_dir: Path, native_rows):
    """``native_rows`` whose labels are the model's own ranking (a row is positive when the model
    scores it above its object's median): a fake dataset's random labels leave the Platt slope's
    sign to chance, and a fit that cannot rank is refused (exit 2)."""
    from export.recalibrate import score_native
    from service.runtime import FastModel

    model = FastModel(model_dir, head_precision="fp32")

    def relabelled(grasps_dir, *args, **kw):
        data = native_rows(grasps_dir, *args, **kw)
        for o, (depth, rows, _labels, image_index) in data.items():
            n = len(rows)
            # every row scored once, each "label" its own index: which score is whose
            p, row = score_native(
                model, {o: (depth, rows, np.arange(n), image_index)}, [o], n, np.random.default_rng(o)
            )
            score = np.empty(n)
            score[row] = p
            data[o] = (depth, rows, (score > np.median(score)).astype(np.int64), image_index)
        return data

    return relabelled


def test_recalibrate_rewrites_only_the_calibration(tmp_path, monkeypatch):
    import export.recalibrate as recalibrate

    fake_dataset(tmp_path / "g", n_objects=8, n_images=2, n_grasps=40)
    model = tmp_path / "m"
    shutil.copytree(DEFAULT, model)
    monkeypatch.setattr(recalibrate, "native_rows", _ranked_by(model, recalibrate.native_rows))
    before = json.loads((model / "model_card.json").read_text())
    assert main(["--model-dir", str(model), "--grasps", str(tmp_path / "g"), "--per-split", "100"]) == 0
    after = json.loads((model / "model_card.json").read_text())
    assert {k: v for k, v in after.items() if k != "calibration"} == {
        k: v for k, v in before.items() if k != "calibration"
    }
    cal = ModelCard.load(model).calibrator()
    p = np.linspace(0.01, 0.99, 5)
    assert np.all(np.diff(cal.apply(p)) > 0)  # monotone: the ranking is the network's
    assert (model / after["calibration"]["reliability_diagram"]).is_file()


def test_one_object_is_a_clear_error(tmp_path, capsys):
    fake_dataset(tmp_path / "g", n_objects=1, n_images=1, n_grasps=20)
    model = tmp_path / "m"
    shutil.copytree(DEFAULT, model)
    assert main(["--model-dir", str(model), "--grasps", str(tmp_path / "g")]) == 2
    assert "at least 2 objects" in capsys.readouterr().err


def test_a_model_of_turned_windows_is_calibrated_on_turned_windows(tmp_path, model_dir):
    from datagen.crops import turned_crops
    from export.recalibrate import native_rows, score_native
    from service.runtime import FastModel

    fake_dataset(tmp_path / "g", n_objects=2, n_images=1, n_grasps=40, seed=5)
    turned = tmp_path / "m"
    shutil.copytree(model_dir, turned)  # a model without placement rows (the bundle's head reads them)
    card = json.loads((turned / "model_card.json").read_text())
    card["geometry"]["jaw_turns"] = 4
    (turned / "model_card.json").write_text(json.dumps(card))
    model, data = FastModel(turned, head_precision="fp32"), native_rows(tmp_path / "g")
    p, _ = score_native(model, data, [0], 5, np.random.default_rng(1))
    rng = np.random.default_rng(1)
    pick = rng.choice(len(data[0][1]), 5, replace=False)
    depth, rows, _, image_index = data[0]
    for j, i in enumerate(pick):
        r = rows[i : i + 1]
        img, puv, _, q = turned_crops(
            depth[image_index[i]], r[:, :2], r[:, 2], r[:, 3:7], model.geometry, model.card.intrinsics, rng
        )
        pose = np.concatenate([puv, r[:, 2:3], q], axis=1).astype(np.float32)
        assert p[j] == float(model.score(model.encode(img), pose)[0])


def test_a_placement_head_is_scored_with_each_grasps_placement_row(tmp_path, model_dir):
    from export.recalibrate import native_rows, score_native
    from export.stack_head import write_stacked
    from planning.placement import placement_rows
    from service.runtime import FastModel
    from training.stacker import INPUTS, Stacker

    rng = np.random.default_rng(0)
    shapes = [(4, len(INPUTS)), (1, 4)]
    layers = tuple((rng.normal(0, 1, s).astype(np.float32), np.ones(s[0], np.float32)) for s in shapes)
    stacker = Stacker(np.zeros(len(INPUTS), np.float32), np.ones(len(INPUTS), np.float32), layers)
    stacked = write_stacked(model_dir, stacker, tmp_path / "m", {})  # a head without placement, stacked
    fake_dataset(tmp_path / "g", n_objects=2, n_images=1, n_grasps=40, seed=5)
    model, data = FastModel(stacked, head_precision="fp32"), native_rows(tmp_path / "g")
    base = FastModel(model_dir, head_precision="fp32")
    depth, rows, _, image_index = data[0]
    n = len(rows)  # all of object 0's rows, in a random order
    p, _ = score_native(model, data, [0], n, np.random.default_rng(1))  # a (k, 14) head: scored, not refused
    p0, _ = score_native(base, data, [0], n, np.random.default_rng(1))
    pick = np.random.default_rng(1).choice(n, n, replace=False)
    place = placement_rows(depth[image_index[pick[0]]], model.card.intrinsics, rows[pick, :3], rows[pick, 3:7])
    known = place[:, 0] > 0
    # rows with a placement known move by the stacker; the others score as the unstacked head
    np.testing.assert_allclose(p[~known], p0[~known], atol=1e-6)
    assert known.any() and np.abs(p[known] - p0[known]).min() > 1e-4
