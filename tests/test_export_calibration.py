"""Export fits a calibration on the validation split, corrected to the native positivity, and
records it (parameters, positivity, ECE on test) with a reliability diagram in the model folder."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import torch
from conftest import synthetic_crops

from export.calibrate import DIAGRAM, calibration_report, native_positivity
from export.onnx_export import export_model
from vgq.camera import DEFAULT_INTRINSICS
from vgq.crop import CropGeometry
from vgq.model_card import ModelCard

GEOM = CropGeometry(96, 32, 36.0)


def _probs(net, imgs, poses):
    with torch.no_grad():
        return torch.softmax(net(torch.from_numpy(imgs[:, None]), torch.from_numpy(poses)), 1)[:, 1].numpy()


def test_export_records_calibration_and_writes_the_reliability_diagram(tmp_path, briefly_trained):
    net, imgs, poses = briefly_trained
    vi, vp, vy = synthetic_crops(300, np.random.default_rng(11))
    ti, tp, ty = synthetic_crops(300, np.random.default_rng(12))
    report = calibration_report(_probs(net, vi, vp), vy, _probs(net, ti, tp), ty, 0.047, "test: given")
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)  # the project's export raises none
        export_model(net, tmp_path / "m", imgs[:8], poses[:8], GEOM, DEFAULT_INTRINSICS, calibration=report)
    card = ModelCard.load(tmp_path / "m")
    k = card.calibration
    assert k["method"] == "platt" and k["target_positivity"] == 0.047 and k["target_positivity_source"] == "test: given"
    assert k["fit"]["n"] == 300 and k["test"]["n"] == 300 and 0 <= k["test"]["ece_calibrated"] <= 1
    assert k["fit"]["nll_calibrated"] <= k["fit"]["nll_raw"] + 1e-9  # the fit can only improve its own split
    assert (tmp_path / "m" / DIAGRAM).read_bytes()[:4] == b"\x89PNG" and k["reliability_diagram"] == DIAGRAM
    p_raw = _probs(net, ti, tp)
    np.testing.assert_allclose(card.calibrator().apply(p_raw), report.calibration.apply(p_raw), rtol=1e-12)
    assert json.loads((tmp_path / "m" / "model_card.json").read_text())["calibration"]["slope"] == k["slope"]


def test_export_without_calibration_has_an_empty_one(model_dir):
    card = ModelCard.load(model_dir)
    assert card.calibration == {} and card.calibrator() is None and not (model_dir / DIAGRAM).exists()


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    from training.config import TrainConfig
    from training.synthetic import make_synthetic_crop_dataset
    from training.train import train

    root = tmp_path_factory.mktemp("calib")
    make_synthetic_crop_dataset(root / "d", 64, 48, 48, positive_rate=0.3, seed=0)
    train(
        TrainConfig(samples=64, batch_size=16, base_lr=0.05, val_every_samples=10**6, class_balance="loss_weights"),
        root / "d",
        root / "run",
        progress=False,
    )
    return root / "d", root / "run"


def test_export_cli_calibrates_for_the_manifests_native_positivity(tiny_run, tmp_path):
    from export.__main__ import main

    data, run = tiny_run
    manifest = json.loads((data / "manifest.json").read_text())
    main(
        [
            "--run",
            str(run),
            "--data",
            str(data),
            "--out",
            str(tmp_path / "m"),
            "--verify-n",
            "4",
            "--reliability-png",
            str(tmp_path / "docs" / "reliability_diagram.png"),
        ]
    )
    k = ModelCard.load(tmp_path / "m").calibration
    nc = manifest["native_counts"]
    assert (
        k["target_positivity"] == pytest.approx(nc["positive"] / nc["n"])
        and "native_counts" in k["target_positivity_source"]
    )
    assert k["fit"]["split"] == "val" and k["fit"]["n"] == 48 and k["test"]["split"] == "test"
    assert (tmp_path / "docs" / "reliability_diagram.png").read_bytes() == (tmp_path / "m" / DIAGRAM).read_bytes()


def test_export_cli_temperature_and_given_positivity(tiny_run, tmp_path):
    from export.__main__ import main

    data, run = tiny_run
    main(
        [
            "--run",
            str(run),
            "--data",
            str(data),
            "--out",
            str(tmp_path / "m"),
            "--verify-n",
            "4",
            "--calibration-method",
            "temperature",
            "--native-positivity",
            "0.05",
        ]
    )
    k = ModelCard.load(tmp_path / "m").calibration
    assert k["method"] == "temperature" and k["target_positivity"] == 0.05 and k["temperature"] > 0


def test_export_cli_refuses_a_bad_positivity(tiny_run, tmp_path, capsys):
    from export.__main__ import main

    data, run = tiny_run
    with pytest.raises(SystemExit) as e:
        main(["--run", str(run), "--data", str(data), "--out", str(tmp_path / "m"), "--native-positivity", "4.7"])
    assert e.value.code == 2 and "fraction" in capsys.readouterr().err and not (tmp_path / "m").exists()


def test_native_positivity_prefers_given_then_manifest_then_sampled_source(tmp_path):
    m = {
        "counts": {"train": {"n": 100, "positive": 19}},
        "native_counts": {"n": 1000, "positive": 47, "positivity": 0.047},
    }
    assert native_positivity(m, 0.1) == (0.1, "given (--native-positivity)")
    assert native_positivity(m)[0] == pytest.approx(0.047)
    src = tmp_path / "sampled"
    src.mkdir()
    (src / "manifest.json").write_text(
        json.dumps(
            {
                "format": "vgq-grasps",
                "format_version": 1,
                "sampling": {"stats": {"steps": {"native": {"grasps": 2000, "positive": 80, "positivity": 4.0}}}},
            }
        )
    )
    old = {"counts": m["counts"], "source": {"dataset": str(src)}}  # a crop manifest from before native_counts
    assert native_positivity(old)[0] == pytest.approx(0.04)
    assert native_positivity({"counts": m["counts"]})[0] == pytest.approx(0.19)


def test_export_cli_without_both_classes_in_val_exits_2_naming_the_way_out(tmp_path, capsys):
    from export.__main__ import main
    from training.config import TrainConfig
    from training.synthetic import make_synthetic_crop_dataset
    from training.train import train

    make_synthetic_crop_dataset(tmp_path / "d", 16, 8, 8, positive_rate=0.0, seed=0)  # no positives anywhere
    train(
        TrainConfig(samples=16, batch_size=8, val_every_samples=10**6), tmp_path / "d", tmp_path / "run", progress=False
    )
    args = ["--run", str(tmp_path / "run"), "--data", str(tmp_path / "d"), "--verify-n", "4"]
    with pytest.raises(SystemExit) as e:
        main([*args, "--out", str(tmp_path / "m")])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "both classes" in err and "--no-calibration" in err and not (tmp_path / "m").exists()
    main([*args, "--out", str(tmp_path / "m"), "--no-calibration"])
    assert ModelCard.load(tmp_path / "m").calibration == {}
