"""export.prune_encoder: the encoder's dead channels and units removed (fp32 or int8 graph), the
pruned graph checked against the unpruned one, and a folder's int8 encoder pruned in place."""

from __future__ import annotations

import shutil

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from conftest import synthetic_crops
from onnx import TensorProto, helper, numpy_helper

from export.int8_encoder import add_int8_encoder
from export.prune_encoder import (
    dead_channels,
    main,
    prune_encoder_graph,
    prune_folder_encoder,
)
from export.prune_head import PruningError
from service.runtime import FastModel
from vgq.model_card import ENCODER_INPUT, ENCODER_OUTPUT, ModelCard

KILL = {
    "net.conv1_2.bias": np.arange(0, 64, 2),
    "net.conv2_2.bias": np.arange(0, 64, 5),
    "net.fc3.bias": np.arange(0, 1024, 3),
}
RELU = {
    "net.conv1_2.bias": "/Relu_1_output_0",
    "net.conv2_2.bias": "/Relu_3_output_0",
    "net.fc3.bias": "/Relu_4_output_0",
}


@pytest.fixture(scope="module")
def dead_model(tmp_path_factory, model_dir):
    """A copy of the test model whose encoder has known dead channels (zero filter, bias -0.1: a
    constant -0.1 before the ReLU): half of conv1_2's channels (they feed an LRN), every 5th of
    conv2_2's (they feed the LRN, then Flatten and fc3) and every 3rd fc3 unit (it feeds fc4_image)."""
    out = tmp_path_factory.mktemp("prune_enc") / "m"
    shutil.copytree(model_dir, out)
    g = onnx.load(str(out / "encoder.onnx"))
    for t in g.graph.initializer:
        layer = t.name.rsplit(".", 1)[0] + ".bias"
        if layer in KILL:
            a = numpy_helper.to_array(t).copy()
            a[KILL[layer]] = -0.1 if t.name.endswith("bias") else 0.0
            t.CopyFrom(numpy_helper.from_array(a, t.name))
    onnx.save(g, str(out / "encoder.onnx"))
    return out


def _terms(path, crops):
    s = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return s.run([ENCODER_OUTPUT], {ENCODER_INPUT: np.asarray(crops, np.float32).reshape(len(crops), 1, 32, 32)})[0]


def test_dead_channels_are_those_that_never_fire(dead_model):
    kept = dead_channels(dead_model / "encoder.onnx", synthetic_crops(64, np.random.default_rng(1))[0])
    for bias, relu in RELU.items():
        assert not set(KILL[bias]) & set(kept[relu])
    assert len(kept["/Relu_output_0"]) <= 64 and set(kept) == {
        f"/Relu{s}_output_0" for s in ("", "_1", "_2", "_3", "_4")
    }


def test_removing_dead_channels_leaves_the_image_term_unchanged(dead_model, tmp_path):
    keep = {RELU[b]: np.setdiff1d(np.arange(1024 if "fc3" in b else 64), k) for b, k in KILL.items()}
    summary = prune_encoder_graph(dead_model / "encoder.onnx", tmp_path / "p.onnx", keep)
    assert summary["/Relu_1_output_0"] == (32, 64) and summary["/Relu_4_output_0"] == (1024 - 342, 1024)
    w = {t.name: tuple(t.dims) for t in onnx.load(str(tmp_path / "p.onnx")).graph.initializer}
    assert w["net.conv1_2.weight"] == (32, 64, 5, 5) and w["net.conv2_1.weight"][1] == 32
    assert w["net.fc3.weight"] == (1024 - 342, (64 - 13) * 64)  # conv2_2's kept channels x 8 x 8 columns
    crops = synthetic_crops(40, np.random.default_rng(2))[0]
    full, pruned = _terms(dead_model / "encoder.onnx", crops), _terms(tmp_path / "p.onnx", crops)
    assert pruned.shape == full.shape == (40, 1024)
    np.testing.assert_allclose(pruned, full, rtol=1e-4, atol=1e-4 * np.abs(full).max())


def test_int8_encoder_is_quantised_whole_then_pruned_and_both_checks_recorded(dead_model, tmp_path):
    out = tmp_path / "m"
    shutil.copytree(dead_model, out)
    calib, check = synthetic_crops(64, np.random.default_rng(21))[0], synthetic_crops(300, np.random.default_rng(22))
    add_int8_encoder(out, calib, check, check_data="synthetic", calibration="synthetic")
    rec = ModelCard.load(out).export["int8_encoder"]
    assert rec["pruning"]["kept"]["/Relu_1_output_0"][0] <= 32 and rec["pruning"]["check"]["precision"] == "pruned"
    assert rec["pruning"]["check"]["decisions_changed"] == 0 and rec["n"] == 300
    q = {t.name: tuple(t.dims) for t in onnx.load(str(out / "encoder_int8.onnx")).graph.initializer}
    assert q["net.conv1_2.weight_quantized"][0] <= 32 and q["net.conv1_2.weight_scale"][0] <= 32
    m8, m32 = FastModel(out, encoder_precision="int8"), FastModel(out, encoder_precision="fp32")
    t8, t32 = m8.encode(check[0][:8]), m32.encode(check[0][:8])
    assert np.abs(t8 - t32).max() <= 0.1 * np.abs(t32).max()
    assert not list(out.glob(".*tmp")) and not list(out.glob(".prune-*"))


def test_a_folder_int8_encoder_is_pruned_in_place_once(dead_model, tmp_path):
    out = tmp_path / "m"
    shutil.copytree(dead_model, out)
    calib, check = synthetic_crops(64, np.random.default_rng(21))[0], synthetic_crops(300, np.random.default_rng(22))
    with pytest.raises(PruningError, match="no int8 encoder"):
        prune_folder_encoder(out, calib, check)
    add_int8_encoder(out, calib, check, prune=False)
    before = ModelCard.load(out).export["int8_encoder"]
    rec = prune_folder_encoder(out, calib, check, "synthetic", "synthetic")
    after = ModelCard.load(out).export["int8_encoder"]
    assert after["pruning"] == rec and after["n"] == before["n"] and after["sha256"] != before["sha256"]
    q = {t.name: tuple(t.dims) for t in onnx.load(str(out / "encoder_int8.onnx")).graph.initializer}
    assert q["net.conv1_2.weight_quantized"][0] == rec["kept"]["/Relu_1_output_0"][0] <= 32
    with pytest.raises(PruningError, match="pruned already"):
        prune_folder_encoder(out, calib, check)


def test_a_layout_it_does_not_know_is_refused(tmp_path):
    w = numpy_helper.from_array(np.ones((4, 1, 3, 3), np.float32), "w")
    g = helper.make_graph(
        [
            helper.make_node("Conv", ["x", "w"], ["c"], name="conv", pads=[1, 1, 1, 1]),
            helper.make_node("Relu", ["c"], ["r"], name="relu"),
            helper.make_node("Transpose", ["r"], ["y"], name="t", perm=[0, 2, 3, 1]),
        ],
        "g",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 1, 4, 4])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)],
        [w],
    )
    onnx.save(helper.make_model(g), str(tmp_path / "g.onnx"))
    with pytest.raises(PruningError, match="cannot prune r through Transpose"):
        prune_encoder_graph(tmp_path / "g.onnx", tmp_path / "o.onnx", {"r": np.array([0, 1])})
    with pytest.raises(PruningError, match="not the ReLU"):
        prune_encoder_graph(tmp_path / "g.onnx", tmp_path / "o.onnx", {"c": np.array([0])})


def test_cli_refuses_bad_input_with_exit_2(dead_model, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(["--model-dir", str(dead_model), "--calibration", "c", "--check", "k", "--calibration-n", "2"])
    assert e.value.code == 2 and "--calibration-n must be >= 16" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["--model-dir", str(tmp_path), "--calibration", "c", "--check", "k"])
    assert e.value.code == 2 and "holds no model_card.json" in capsys.readouterr().err
