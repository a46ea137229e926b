"""export.int8_encoder / export.quantize: a checked int8 encoder beside fp32, and the service's
start-up choice between them (``encoder_precision``)."""

from __future__ import annotations

import shutil

import numpy as np
import onnx
import pytest
from conftest import synthetic_crops

from export.int8_encoder import add_int8_encoder, main
from export.quantize import QuantizationError, check_encoder_variant, encoder_nodes_to_quantize
from service.config import Settings
from service.runtime import FastModel, ModelError
from vgq.model_card import ModelCard


@pytest.fixture(scope="module")
def int8_enc_model(tmp_path_factory, model_dir):
    """A copy of the test model folder with an int8 encoder (calibrated and checked on
    different synthetic crops; thresholds as shipped)."""
    out = tmp_path_factory.mktemp("int8enc") / "m"
    shutil.copytree(model_dir, out)
    calib, _, _ = synthetic_crops(64, np.random.default_rng(21))
    check = synthetic_crops(300, np.random.default_rng(22))
    result = add_int8_encoder(out, calib, check, check_data="synthetic", calibration="synthetic")
    return out, result


def test_int8_encoder_is_written_checked_and_recorded_in_the_card(int8_enc_model):
    out, result = int8_enc_model
    card = ModelCard.load(out)
    rec = card.export["int8_encoder"]
    assert card.files["encoder_int8"] == "encoder_int8.onnx" and (out / "encoder_int8.onnx").is_file()
    assert rec["n"] == 300 and rec["decisions_changed"] == result.decisions_changed and rec["n_calibration"] == 64
    assert rec["quantized_nodes"] == ["/conv1_2/Conv", "/fc3/Gemm", "/fc4_image/MatMul"]
    ops = [n.op_type for n in onnx.load(str(out / "encoder_int8.onnx")).graph.node]
    assert "QuantizeLinear" in ops and "DequantizeLinear" in ops
    assert not list(out.glob(".*tmp"))  # no temp file left behind


def test_first_conv_and_lrn_bands_stay_fp32(model_dir):
    nodes = encoder_nodes_to_quantize(model_dir / "encoder.onnx")
    assert "/conv1_1/Conv" not in nodes and not any("lrn" in n for n in nodes)


def test_check_refuses_an_encoder_that_scores_differently(int8_enc_model):
    out, _ = int8_enc_model
    imgs, poses, labels = synthetic_crops(200, np.random.default_rng(23))
    with pytest.raises(QuantizationError, match="scores unlike"):
        check_encoder_variant(
            out / "encoder.onnx",
            out / "encoder_int8.onnx",
            out / "head.onnx",
            imgs,
            poses,
            labels,
            max_mean_abs_diff=0.0,
        )
    # the fp32 encoder against itself: identical, passes with zero tolerance
    same = check_encoder_variant(
        out / "encoder.onnx",
        out / "encoder.onnx",
        out / "head.onnx",
        imgs,
        poses,
        labels,
        precision="fp32",
        max_mean_abs_diff=0.0,
        max_flip_fraction=0.0,
        max_bacc_drop=0.0,
    )
    assert same.decisions_changed == 0 and same.max_abs_diff_probability == 0.0


def test_refused_encoder_leaves_the_folder_unchanged(tmp_path, model_dir, monkeypatch):
    import export.int8_encoder as ie

    out = tmp_path / "m"
    shutil.copytree(model_dir, out)
    before = (out / "model_card.json").read_text()
    monkeypatch.setattr(
        ie, "check_encoder_variant", lambda *a, **k: (_ for _ in ()).throw(QuantizationError("refused"))
    )
    with pytest.raises(QuantizationError):
        ie.add_int8_encoder(
            out, synthetic_crops(32, np.random.default_rng(1))[0], synthetic_crops(50, np.random.default_rng(2))
        )
    assert (out / "model_card.json").read_text() == before and sorted(p.name for p in out.iterdir()) == sorted(
        p.name for p in model_dir.iterdir()
    )


def test_cli_exits_2_with_one_line_for_a_missing_dataset(tmp_path, model_dir, capsys):
    with pytest.raises(SystemExit) as e:
        main(
            [
                "--model-dir",
                str(model_dir),
                "--calibration",
                str(tmp_path / "nope"),
                "--check",
                str(tmp_path / "nope.npz"),
            ]
        )
    assert e.value.code == 2 and capsys.readouterr().err.startswith("int8-encoder:")


def test_auto_times_both_encoders_and_serves_the_faster(int8_enc_model):
    out, _ = int8_enc_model
    m = FastModel(out, encoder_precision="auto", select_s=0.1)
    info = m.encoder_info
    assert info["available"] == ["fp32", "int8"] and set(info["median_ms"]) == {"fp32", "int8"}
    assert info["precision"] == min(info["median_ms"], key=info["median_ms"].get) == m.encoder_precision
    crop = np.full((32, 32), 0.6, np.float32)
    assert m.encode(crop).shape == (1, 1024)


def test_explicit_precision_is_served_without_timing(int8_enc_model, model_dir):
    out, _ = int8_enc_model
    a, b = FastModel(out, encoder_precision="fp32"), FastModel(out, encoder_precision="int8")
    assert (a.encoder_precision, b.encoder_precision) == ("fp32", "int8") and a.encoder_info["median_ms"] == {}
    crop = np.asarray(synthetic_crops(1, np.random.default_rng(3))[0][0], np.float32)
    assert np.abs(a.encode(crop) - b.encode(crop)).max() > 0  # two different graphs really run
    assert FastModel(model_dir).encoder_precision == "fp32"  # auto with one encoder: no timing
    with pytest.raises(ModelError, match="no such encoder"):
        FastModel(model_dir, encoder_precision="int8")
    with pytest.raises(ValueError, match="encoder_precision"):
        Settings(encoder_precision="fp16")


def test_export_cli_int8_encoder_flag_checks_and_records_the_outcome(tmp_path, caplog):
    """``python -m export --int8-encoder``: the fp32 export is written; the int8 encoder is added
    with its check in the card, or (on this tiny run, where one flip of 16 exceeds 2%) the
    refusal is logged and nothing of it is left in the folder."""
    import logging

    from test_export import _tiny_run

    from export.__main__ import main as export_main

    data, run = _tiny_run(tmp_path)
    with caplog.at_level(logging.INFO):
        export_main(
            [
                "--run",
                str(run),
                "--data",
                str(data),
                "--out",
                str(tmp_path / "m"),
                "--verify-n",
                "4",
                "--no-calibration",
                "--int8-encoder",
                "--int8-check-n",
                "100",
            ]
        )
    card = ModelCard.load(tmp_path / "m")
    kept = (tmp_path / "m" / "encoder_int8.onnx").is_file()
    assert kept == ("encoder_int8" in card.files) == ("int8_encoder" in card.export)
    assert kept or any("int8 encoder refused" in r.getMessage() for r in caplog.records)
    assert "calibrating on 16 train crops, checking on 8 val crops" in caplog.text
    assert not list((tmp_path / "m").glob(".*tmp"))


def test_crop_split_reads_only_the_rows_it_returns(tmp_path, monkeypatch):
    """A sample of n rows from GB-sized splits batches those n rows, not the whole split (the
    CLI once held all 3.3 M train crops in memory and was killed), and picks the same rows."""
    from export.int8_encoder import crop_split
    from training.data import CropSplit
    from training.synthetic import make_synthetic_crop_dataset

    make_synthetic_crop_dataset(tmp_path / "d", 64, 32, 16, seed=4)
    whole = crop_split(tmp_path / "d", ("train", "val"))
    asked = []
    real = CropSplit.batch
    monkeypatch.setattr(
        CropSplit, "batch", lambda self, idx, *a, **k: asked.append(len(idx)) or real(self, idx, *a, **k)
    )
    crops, poses, labels = crop_split(tmp_path / "d", ("train", "val"), 10, seed=3)
    assert sum(asked) == 10 == len(crops)
    idx = np.sort(np.random.default_rng(3).choice(len(whole[0]), 10, replace=False))
    np.testing.assert_array_equal(crops, whole[0][idx])
    np.testing.assert_array_equal(poses, whole[1][idx])
