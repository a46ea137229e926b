"""ONNX export: graphs reproduce torch, LRN is exported without ORT's slow LRN kernel."""

from __future__ import annotations

import copy
import json

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from conftest import synthetic_crops

from export.graphs import ExportLRN, HeadGraph, bilinear_point_major
from export.onnx_export import ExportError, export_model
from training.networks import GraspQualityNet, LocalResponseNorm
from vgq.camera import DEFAULT_INTRINSICS
from vgq.crop import CropGeometry
from vgq.model_card import ModelCard

GEOM = CropGeometry(96, 32, 36.0)


def tf_lrn(x: torch.Tensor, radius=2, alpha=2e-5, beta=0.75, bias=1.0) -> torch.Tensor:
    """TensorFlow's tf.nn.local_response_normalization, written out channel by channel."""
    c = x.shape[1]
    out = torch.empty_like(x)
    for i in range(c):
        lo, hi = max(0, i - radius), min(c, i + radius + 1)
        s = (x[:, lo:hi] ** 2).sum(dim=1)
        out[:, i] = x[:, i] / (bias + alpha * s) ** beta
    return out


def test_lrn_matches_tensorflow_semantics():
    x = torch.randn(2, 64, 8, 8) * 30  # large activations so the normaliser matters
    assert torch.allclose(LocalResponseNorm(64)(x), tf_lrn(x), rtol=1e-5, atol=1e-5)


def test_lrn_differs_from_torch_builtin_alpha_convention():
    x = torch.randn(2, 64, 8, 8) * 30
    builtin = torch.nn.LocalResponseNorm(5, alpha=2e-5, beta=0.75, k=1.0)(x)
    assert not torch.allclose(LocalResponseNorm(64)(x), builtin, rtol=1e-4)


def test_export_lrn_form_matches_tensorflow_semantics():
    x = torch.relu(torch.randn(2, 64, 8, 8)) * 30
    assert torch.allclose(ExportLRN(LocalResponseNorm(64))(x), tf_lrn(x), rtol=1e-5, atol=1e-5)


def test_export_lrn_form_matches_for_other_beta():
    x = torch.relu(torch.randn(2, 64, 8, 8)) * 30
    assert torch.allclose(ExportLRN(LocalResponseNorm(64, beta=0.5))(x), tf_lrn(x, beta=0.5), rtol=1e-5, atol=1e-5)


def test_exported_encoder_uses_sqrt_not_pow(model_dir):
    ops = {n.op_type for n in onnx.load(str(model_dir / "encoder.onnx")).graph.node}
    assert "Pow" not in ops and "Sqrt" in ops


def test_exported_encoder_has_no_onnx_lrn_node(model_dir):
    ops = {n.op_type for n in onnx.load(str(model_dir / "encoder.onnx")).graph.node}
    assert "LRN" not in ops and "Conv" in ops


def test_model_card_records_geometry_normalisation_and_verification(model_dir):
    card = ModelCard.load(model_dir)
    assert card.architecture == "fast_vgqcnn" and card.geometry == GEOM
    assert card.intrinsics == DEFAULT_INTRINSICS
    assert card.export["verification"]["max_abs_diff_probability"] <= 1e-4
    assert card.model_version.startswith("fast_vgqcnn-")
    assert json.loads((model_dir / "model_card.json").read_text())["format"] == "vgq-model-card"


def test_encoder_plus_head_graphs_equal_torch_on_fresh_inputs(model_dir, briefly_trained):
    net, _, _ = briefly_trained  # the net the fixture's model was exported from
    imgs, poses, _ = synthetic_crops(16, np.random.default_rng(7))
    enc = ort.InferenceSession(str(model_dir / "encoder.onnx"), providers=["CPUExecutionProvider"])
    head = ort.InferenceSession(str(model_dir / "head.onnx"), providers=["CPUExecutionProvider"])
    term = enc.run(None, {"depth_crop": imgs[:1, None]})[0]
    got = head.run(None, {"image_term": term, "poses": poses})[0]
    with torch.no_grad():
        ref = net.head(net.encode(torch.from_numpy(imgs[:1, None])), torch.from_numpy(poses)).numpy()
    assert got.shape == (16,) and np.abs(got - ref).max() < 1e-4


def strongly_activated(net: GraspQualityNet, crops: np.ndarray, poses: np.ndarray) -> GraspQualityNet:
    """A copy of ``net`` whose every layer matters: conv1_2 x150 and conv2_2 x10 drive both LRNs
    far into their non-linear range (alpha sum x^2 >> 1), fc4_image is rescaled to a unit-spread
    image term and fc6 x10 (bias centred) spreads the probabilities over (0.15, 0.85)."""
    s = copy.deepcopy(net).eval()
    x, p = torch.from_numpy(crops[:, None]), torch.from_numpy(poses)
    with torch.no_grad():
        for layer, f in ((s.conv1_2, 150.0), (s.conv2_2, 10.0)):
            layer.weight *= f
            layer.bias *= f
        s.fc4_image.weight /= s.encode(x).std()
        s.fc6.weight *= 10.0
        s.fc6.bias[1] -= torch.logit(s.head(s.encode(x), p)).median()
    return s


def encode_without_lrn(net: GraspQualityNet, x: torch.Tensor, which: int) -> torch.Tensor:
    """``net.encode`` with its first (0) or second (1) LRN left out."""

    def lrn(y, i):
        return y if i == which else net.lrn(y)

    y = torch.relu(net.conv1_1((x - net.image_mean) / net.image_std))
    y = torch.nn.functional.max_pool2d(lrn(torch.relu(net.conv1_2(y)), 0), 2)
    y = torch.nn.functional.max_pool2d(lrn(torch.relu(net.conv2_2(torch.relu(net.conv2_1(y)))), 1), 2)
    return net.fc4_image(torch.relu(net.fc3(torch.flatten(y, 1))))


@pytest.fixture(scope="module")
def strong(tmp_path_factory, briefly_trained):
    """(net, model folder) of :func:`strongly_activated`, exported (its own verification included)."""
    net, imgs, poses = briefly_trained
    s = strongly_activated(net, imgs[:64], poses[:64])
    out = tmp_path_factory.mktemp("strong") / "m"
    export_model(s, out, imgs[:32], poses[:32], GEOM, DEFAULT_INTRINSICS)
    return s, out


def test_strong_net_needs_each_lrn_and_spreads_its_probabilities(strong, briefly_trained):
    """The parity check below can see a missing layer: leaving out either LRN moves the image
    term by > 10% of its largest value and some probability by > 0.1."""
    net, _ = strong
    imgs, poses, _ = synthetic_crops(64, np.random.default_rng(11))
    x, p = torch.from_numpy(imgs[:, None]), torch.from_numpy(poses)
    with torch.no_grad():
        term, prob = net.encode(x), net.head(net.encode(x), p)
        assert prob.std() > 0.1 and 0.02 < prob.min() and prob.max() < 0.98
        for which in (0, 1):
            t = encode_without_lrn(net, x, which)
            assert (t - term).abs().max() > 0.1 * term.abs().max(), which
            assert (net.head(t, p) - prob).abs().max() > 0.1, which
        np.testing.assert_allclose(encode_without_lrn(net, x, -1), term, rtol=1e-6, atol=1e-6)  # the helper is encode


def test_onnx_encoder_and_head_reproduce_a_net_whose_every_layer_matters(strong):
    net, out = strong
    imgs, poses, _ = synthetic_crops(64, np.random.default_rng(12))
    enc = ort.InferenceSession(str(out / "encoder.onnx"), providers=["CPUExecutionProvider"])
    head = ort.InferenceSession(str(out / "head.onnx"), providers=["CPUExecutionProvider"])
    terms = enc.run(None, {"depth_crop": imgs[:, None]})[0]
    with torch.no_grad():
        ref_terms = net.encode(torch.from_numpy(imgs[:, None])).numpy()
        ref_p = net.head(torch.from_numpy(ref_terms[:1]), torch.from_numpy(poses)).numpy()
    rel = np.abs(terms - ref_terms).max(axis=1) / np.abs(ref_terms).max(axis=1)  # per image, to its own scale
    assert rel.max() < 1e-5, rel.max()
    got = head.run(None, {"image_term": terms[:1], "poses": poses})[0]
    assert np.abs(got - ref_p).max() < 1e-5 and ref_p.std() > 0.1
    assert ModelCard.load(out).export["verification"]["max_rel_diff_image_term"] < 1e-5


def test_folded_head_equals_network_head():
    net = GraspQualityNet("fast_vgqcnn").eval()
    imgs, poses, _ = synthetic_crops(32, np.random.default_rng(1))
    from vgq.normalization import Normalization

    net.set_normalization(Normalization.from_data(imgs, poses, net.pose_columns))
    with torch.no_grad():
        t = net.encode(torch.from_numpy(imgs[:1, None]))
        assert torch.allclose(
            HeadGraph(net)(t, torch.from_numpy(poses)), net.head(t, torch.from_numpy(poses)), atol=1e-6
        )


@pytest.mark.parametrize("arch", ["vgqcnn", "gqcnn"])
def test_one_piece_export_for_vgqcnn_and_gqcnn(tmp_path, arch):
    net = GraspQualityNet(arch).eval()
    imgs, poses7, _ = synthetic_crops(8, np.random.default_rng(2))
    cols = {"vgqcnn": [2, 3, 4, 5, 6], "gqcnn": [2]}[arch]
    card = export_model(net, tmp_path / arch, imgs, poses7[:, cols], CropGeometry(96, 32, 0.0), DEFAULT_INTRINSICS)
    assert card.files == {"model": f"{arch}.onnx"} and (tmp_path / arch / f"{arch}.onnx").is_file()


def test_export_refuses_wrong_inputs_and_writes_nothing(tmp_path):
    net = GraspQualityNet("fast_vgqcnn").eval()
    with pytest.raises(ExportError, match="poses"):
        export_model(
            net,
            tmp_path / "m",
            np.zeros((4, 32, 32), np.float32),
            np.zeros((4, 5), np.float32),
            GEOM,
            DEFAULT_INTRINSICS,
        )
    assert list(tmp_path.iterdir()) == []


def test_export_fails_verification_above_tolerance(tmp_path):
    net = GraspQualityNet("fast_vgqcnn").eval()
    imgs, poses, _ = synthetic_crops(4, np.random.default_rng(3))
    with pytest.raises(ExportError, match="does not reproduce"):
        export_model(net, tmp_path / "m", imgs, poses, GEOM, DEFAULT_INTRINSICS, tolerance=-1.0)
    assert list(tmp_path.iterdir()) == []


def _tiny_run(tmp_path):
    from training.config import TrainConfig
    from training.synthetic import make_synthetic_crop_dataset
    from training.train import train

    make_synthetic_crop_dataset(tmp_path / "d", 16, 8, 8, positive_rate=0.5, seed=0)
    train(
        TrainConfig(samples=16, batch_size=8, val_every_samples=10**6), tmp_path / "d", tmp_path / "run", progress=False
    )
    return tmp_path / "d", tmp_path / "run"


def test_export_cli_records_recipe_and_pose_only_baseline(tmp_path):
    from export.__main__ import main
    from training.baseline import BaselineConfig, run_baseline

    data, run = _tiny_run(tmp_path)
    run_baseline(data, BaselineConfig(model="logreg", epochs=1, batch_size=8), tmp_path / "b", progress=False)
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
            "--recipe",
            "python -m datagen recipe --out data/recipe",
            "--baseline",
            str(tmp_path / "b" / "baseline_logreg.json"),
        ]
    )
    card = ModelCard.load(tmp_path / "m")
    assert card.dataset["recipe"] == "python -m datagen recipe --out data/recipe"
    base = card.metrics["baseline_logreg"]
    assert base["columns"] == ["u", "v", "z", "qw", "qx", "qy", "qz"]
    recorded = json.loads((tmp_path / "b" / "baseline_logreg.json").read_text())["test"]
    assert base["test"] == recorded and base["test"]["n"] == 8  # the baseline's own test numbers, all 8 test crops
    assert card.training["samples_seen"] == 16
    copied = tmp_path / "m" / "baseline_logreg.npz"  # the model file travels with the model, for planning.bench
    assert copied.read_bytes() == (tmp_path / "b" / "baseline_logreg.npz").read_bytes()


def _lfo_result(tmp_path, data, run) -> dict:
    """`training evaluate` of ``run`` on a copy of ``data`` whose odd objects are a family ("mug")
    held out of training: tmp_path / "lfo_eval" / "metrics_test.json"."""
    import shutil

    from training.evaluate import evaluate

    lfo = tmp_path / "lfo"
    shutil.copytree(data, lfo)
    m = json.loads((lfo / "manifest.json").read_text())
    m["source"] = {
        "objects": [{"object_id": i, "family": "mug" if i % 2 else "box"} for i in range(30)],
        "sampling": {"holdout_families": ["mug"]},
    }
    (lfo / "manifest.json").write_text(json.dumps(m))
    return evaluate(run, lfo, "test", out_dir=tmp_path / "lfo_eval", progress=False)


def test_export_cli_records_the_leave_family_out_result(tmp_path, capsys):
    from export.__main__ import main
    from training.evaluate import evaluate

    data, run = _tiny_run(tmp_path)
    rec = _lfo_result(tmp_path, data, run)
    assert rec["held_out_families"]["families"] == ["mug"]
    assert rec["held_out_families"]["n"] == rec["by_family"]["mug"]["n"]
    args = ["--run", str(run), "--data", str(data), "--out", str(tmp_path / "m"), "--verify-n", "4"]
    main([*args, "--leave-family-out", str(tmp_path / "lfo_eval" / "metrics_test.json")])
    card = ModelCard.load(tmp_path / "m")
    assert card.metrics["leave_family_out"]["balanced_accuracy"] == rec["held_out_families"]["balanced_accuracy"]
    assert list(card.metrics["leave_family_out"]["by_family"]) == ["mug"]
    evaluate(run, data, "test", out_dir=tmp_path / "plain", progress=False)  # no held-out family
    with pytest.raises(SystemExit) as e:
        main([*args[:-3], str(tmp_path / "m2"), "--leave-family-out", str(tmp_path / "plain" / "metrics_test.json")])
    assert e.value.code == 2 and "without held-out families" in capsys.readouterr().err


def test_leave_family_out_is_recorded_in_an_exported_card_and_nothing_else_changes(tmp_path, capsys):
    from export.__main__ import main as export_main
    from export.leave_family_out import main
    from training.evaluate import evaluate

    data, run = _tiny_run(tmp_path)
    rec = _lfo_result(tmp_path, data, run)
    result = str(tmp_path / "lfo_eval" / "metrics_test.json")
    args = ["--run", str(run), "--data", str(data), "--verify-n", "4"]
    export_main([*args, "--out", str(tmp_path / "m")])
    export_main([*args, "--out", str(tmp_path / "at_export"), "--leave-family-out", result])
    before = {f.name: f.read_bytes() for f in (tmp_path / "m").iterdir()}
    card_before = json.loads(before["model_card.json"])
    assert "leave_family_out" not in card_before["metrics"]

    assert main(["--model-dir", str(tmp_path / "m"), result]) == 0
    assert "balanced accuracy" in capsys.readouterr().out
    card = json.loads((tmp_path / "m" / "model_card.json").read_text())
    expected = ModelCard.load(tmp_path / "at_export").metrics["leave_family_out"]  # what export records
    assert card["metrics"]["leave_family_out"] == expected
    assert expected["balanced_accuracy"] == rec["held_out_families"]["balanced_accuracy"]
    card["metrics"].pop("leave_family_out")
    assert card == card_before  # every other key as exported
    assert {f.name: f.read_bytes() for f in (tmp_path / "m").iterdir() if f.name != "model_card.json"} == {
        k: v for k, v in before.items() if k != "model_card.json"
    }

    evaluate(run, data, "test", out_dir=tmp_path / "plain", progress=False)  # no held-out family
    changed = (tmp_path / "m" / "model_card.json").read_bytes()
    assert main(["--model-dir", str(tmp_path / "m"), str(tmp_path / "plain" / "metrics_test.json")]) == 2
    assert "without held-out families" in capsys.readouterr().err
    assert main(["--model-dir", str(tmp_path / "nothing"), result]) == 2
    assert "no readable model card" in capsys.readouterr().err
    assert (tmp_path / "m" / "model_card.json").read_bytes() == changed  # a refused call writes nothing


def test_export_cli_refuses_baseline_of_another_dataset(tmp_path, capsys):
    from export.__main__ import main
    from training.baseline import BaselineConfig, run_baseline
    from training.synthetic import make_synthetic_crop_dataset

    data, run = _tiny_run(tmp_path)
    make_synthetic_crop_dataset(tmp_path / "other", 16, 8, 8, positive_rate=0.5, seed=1)
    run_baseline(
        tmp_path / "other", BaselineConfig(model="logreg", epochs=1, batch_size=8), tmp_path / "b", progress=False
    )
    with pytest.raises(SystemExit) as e:
        main(
            [
                "--run",
                str(run),
                "--data",
                str(data),
                "--out",
                str(tmp_path / "m"),
                "--baseline",
                str(tmp_path / "b" / "baseline_logreg.json"),
            ]
        )
    assert e.value.code == 2 and "not on" in capsys.readouterr().err
    assert not (tmp_path / "m").exists()


def test_int8_head_quantises_only_the_largest_layer_and_records_its_check(int8_model):
    out, card = int8_model
    q = card.export["int8_head"]
    assert card.files["head_int8"] == "head_int8.onnx" and q["quantized_nodes"] == ["/head/fc5/Gemm"]
    assert q["n"] == 400 and q["max_abs_diff_probability"] <= 0.05
    ops = [n.op_type for n in onnx.load(str(out / "head_int8.onnx")).graph.node]
    assert ops.count("MatMulInteger") == 1 and ops.count("MatMul") + ops.count("Gemm") >= 3  # pose layers stay fp32


def test_service_runtime_serves_the_int8_head_by_default_and_fp32_on_request(int8_model, briefly_trained):
    from service.runtime import FastModel

    out, _ = int8_model
    _, imgs, poses = briefly_trained
    m8, m32 = FastModel(out), FastModel(out, head_precision="fp32")
    assert (m8.head_precision, m32.head_precision) == ("int8", "fp32")
    term = m32.encode(imgs[0])
    p8, p32 = m8.score(term, poses[:64]), m32.score(term, poses[:64])
    assert np.abs(p8 - p32).max() <= 0.05 and not np.array_equal(p8, p32)


def test_int8_check_refuses_a_head_that_scores_differently(int8_model):
    from export.quantize import QuantizationError, check_int8_head

    out, _ = int8_model
    imgs, poses, labels = synthetic_crops(64, np.random.default_rng(3))
    with pytest.raises(QuantizationError, match="unlike the fp32 head"):
        check_int8_head(
            out / "encoder.onnx", out / "head.onnx", out / "head_int8.onnx", imgs, poses, labels, max_abs_diff=0.0
        )


def test_int8_head_is_for_fast_vgqcnn_only(tmp_path, briefly_trained):
    _, imgs, poses = briefly_trained
    net = GraspQualityNet("vgqcnn").eval()
    with pytest.raises(ExportError, match="fast_vgqcnn only"):
        export_model(
            net,
            tmp_path / "v",
            imgs[:4],
            poses[:4, 2:],
            GEOM,
            DEFAULT_INTRINSICS,
            int8_check=(imgs[:200], poses[:200, 2:], np.arange(200) % 2),
        )
    assert not (tmp_path / "v").exists()


def _export_with_int8_head(net, out, imgs, poses, labels, config):
    """Export on 400 synthetic rows: 16 verify, 200 find the head's dead units, 200 check int8."""
    return export_model(
        net,
        out,
        imgs[:16],
        poses[:16],
        GEOM,
        DEFAULT_INTRINSICS,
        training={"config": config},
        int8_check=(imgs[200:], poses[200:], labels[200:]),
        prune_calibration=(imgs[:200], poses[:200]),
    )


def test_relative_depth_and_rotation_features_export_and_read_back(tmp_path):
    """A net with depth_reference centre and rotation pose features: the encoder and head graphs
    reproduce torch (export's own verification), the pruned int8 head builds, and the folder reads
    back into the same torch net (export.from_onnx)."""
    from export.from_onnx import fast_net_from_model_dir
    from service.runtime import FastModel
    from vgq.normalization import Normalization

    torch.manual_seed(0)
    opts = {"depth_reference": "centre", "pose_features": "rotation", "pose_units": 32}
    net = GraspQualityNet("fast_vgqcnn", **opts).eval()
    imgs, poses, labels = synthetic_crops(400, np.random.default_rng(5))
    net.set_normalization(Normalization.from_data(imgs, poses, net.pose_columns, "centre"))
    card = _export_with_int8_head(net, tmp_path / "m", imgs, poses, labels, opts)
    assert card.normalization.image_reference == "centre" and "head_int8" in card.files
    back, _ = fast_net_from_model_dir(tmp_path / "m")
    for k, v in net.state_dict().items():
        if not k.startswith("fc6"):  # read back as one logit difference
            torch.testing.assert_close(back.state_dict()[k], v, rtol=1e-5, atol=1e-6, msg=k)
    served = FastModel(tmp_path / "m", head_precision="fp32")
    with torch.no_grad():
        x, p = torch.from_numpy(imgs[:1, None]), torch.from_numpy(poses[:64])
        ref = net.head(net.encode(x), p).numpy()
        np.testing.assert_allclose(back.head(back.encode(x), p).numpy(), ref, atol=1e-5)
    assert np.abs(served.score(served.encode(imgs[0]), poses[:64]) - ref).max() < 1e-5
    from export.prune_encoder import dead_channels, prune_encoder_graph
    from export.quantize import image_terms, quantize_encoder

    enc, q8, pruned = tmp_path / "m" / "encoder.onnx", tmp_path / "q8.onnx", tmp_path / "q8_pruned.onnx"
    assert "/fc4_ref/MatMul" in quantize_encoder(enc, q8, imgs[:200])
    prune_encoder_graph(q8, pruned, dead_channels(q8, imgs[:200]))
    t32, t8, tp = (image_terms(g, imgs[200:264]) for g in (enc, q8, pruned))
    assert np.abs(t8 - t32).max() < 0.05 * np.abs(t32).max() and np.abs(tp - t8).max() < 1e-3 * np.abs(t8).max()


def test_jaw_depth_head_exports_and_serves(tmp_path):
    """ "jaw_depth" (here with a wider hidden layer, ``roi_units``): the encoder graph's output
    also carries the crop; the head graph reproduces torch, the service's runtime scores with it
    and the folder reads back into the same net."""
    from export.from_onnx import fast_net_from_model_dir
    from service.runtime import FastModel
    from vgq.normalization import Normalization

    torch.manual_seed(0)
    opts = {"roi_head": "jaw_depth", "roi_units": 48}
    net = GraspQualityNet("fast_vgqcnn", **opts).eval()
    torch.nn.init.normal_(net.roi_fc2.weight, std=0.05)
    torch.nn.init.normal_(net.roi_fc1.weight[:, -24:], std=0.5)  # a head that reads the depths
    imgs, poses, labels = synthetic_crops(400, np.random.default_rng(7))
    net.set_normalization(Normalization.from_data(imgs, poses, net.pose_columns))
    card = _export_with_int8_head(net, tmp_path / "m", imgs, poses, labels, opts)
    assert card.export["verification"]["max_abs_diff_probability"] < 1e-5
    back, _ = fast_net_from_model_dir(tmp_path / "m")
    torch.testing.assert_close(back.roi_fc2.weight, net.roi_fc2.weight)  # (1024, 48)
    served = FastModel(tmp_path / "m", head_precision="fp32")
    term = served.encode(imgs[:1])
    assert term.shape == (1, net.encoding_width)
    with torch.no_grad():
        ref = net.head(net.encode(torch.from_numpy(imgs[:1, None])), torch.from_numpy(poses[:16])).numpy()
    np.testing.assert_allclose(served.score(term, poses[:16]), ref, atol=1e-5)


@pytest.mark.parametrize("windows", [1, 6])
def test_the_head_graphs_bilinear_reads_are_the_networks_point_major(windows):
    """export's four-Gather reads equal the network's (``_bilinear_rows``, grid_sample's border
    reads) flattened point by point, for one window shared by every grasp or a window each."""
    torch.manual_seed(0)
    rows = torch.randn(windows, 256, 64)
    grid = torch.rand(6, 8, 3, 2) * 2.4 - 1.2  # some points off the map: border reads
    want = GraspQualityNet._bilinear_rows(rows, 16, grid).reshape(6, -1)
    torch.testing.assert_close(bilinear_point_major(rows, 16, grid), want, rtol=1e-5, atol=1e-6)


def test_jaw_grid_head_exports_and_serves(tmp_path):
    """A net whose head reads the encoder's feature map on a grid turned to the jaw: the encoder
    graph's output carries the map, the head graph (row Gathers) reproduces torch against one
    shared window, the service's runtime scores with it, and the folder reads back into torch."""
    from export.from_onnx import fast_net_from_model_dir, vgq_net_like
    from service.runtime import FastModel
    from vgq.normalization import Normalization

    torch.manual_seed(0)
    net = GraspQualityNet("fast_vgqcnn", roi_head="jaw").eval()
    torch.nn.init.normal_(net.roi_fc2.weight, std=0.05)  # a head that uses the grid
    imgs, poses, labels = synthetic_crops(400, np.random.default_rng(7))
    net.set_normalization(Normalization.from_data(imgs, poses, net.pose_columns))
    card = _export_with_int8_head(net, tmp_path / "m", imgs, poses, labels, {"roi_head": "jaw"})
    assert card.export["verification"]["max_abs_diff_probability"] < 1e-5 and "head_int8" in card.files
    grid_layers = {"/head/roi_fc1/Gemm", "/head/roi_fc2/MatMul"}  # in int8 beside fc5
    assert set(card.export["int8_head"]["quantized_nodes"]) == {"/head/fc5/Gemm", *grid_layers}
    imgs, poses = imgs[:16], poses[:16]
    served = FastModel(tmp_path / "m", head_precision="fp32")
    term = served.encode(imgs[:1])
    assert term.shape == (1, net.encoding_width)
    with torch.no_grad():
        ref = net.head(net.encode(torch.from_numpy(imgs[:1, None])), torch.from_numpy(poses)).numpy()
    np.testing.assert_allclose(served.score(term, poses), ref, atol=1e-5)
    back, _ = fast_net_from_model_dir(tmp_path / "m")  # read back (a fine-tune's --init)
    for k, v in net.state_dict().items():
        if not k.startswith("fc6"):  # read back as one logit difference
            torch.testing.assert_close(back.state_dict()[k], v, rtol=1e-5, atol=1e-6, msg=k)
    assert vgq_net_like(back).roi_head == "none"  # the benchmark's VGQ-CNN of the same weights
    with torch.no_grad():  # the grid matters: without its layer the scores move
        net.roi_fc2.weight.zero_()
        flat = net.head(net.encode(torch.from_numpy(imgs[:1, None])), torch.from_numpy(poses)).numpy()
    assert np.abs(flat - ref).max() > 1e-3


def test_jaw_grid_encoder_keeps_the_map_it_hands_the_head_when_pruned(tmp_path):
    """Pruning a jaw-grid model's encoder: conv2_2's channels leave the encoder as the head's
    feature map, so all of them stay (the whole encoding unchanged); conv1_2's dead ones still go."""
    from export.prune_encoder import dead_channels, prune_encoder_graph
    from export.quantize import image_terms
    from vgq.normalization import Normalization

    torch.manual_seed(0)
    net = GraspQualityNet("fast_vgqcnn", roi_head="jaw").eval()
    with torch.no_grad():  # dead channels: zero filters, bias -0.1 (a constant -0.1 before the ReLU)
        for conv in (net.conv1_2, net.conv2_2):
            conv.weight[::2] = 0.0
            conv.bias[::2] = -0.1
    imgs, poses, _ = synthetic_crops(64, np.random.default_rng(3))
    net.set_normalization(Normalization.from_data(imgs, poses, net.pose_columns))
    export_model(
        net, tmp_path / "m", imgs[:16], poses[:16], GEOM, DEFAULT_INTRINSICS, training={"config": {"roi_head": "jaw"}}
    )
    enc = tmp_path / "m" / "encoder.onnx"
    kept = dead_channels(enc, imgs)  # the crops compared below: no unit dead on them fires on them
    summary = prune_encoder_graph(enc, tmp_path / "p.onnx", kept)
    assert sorted(summary.values())[:4] == [(32, 64), (64, 64), (64, 64), (64, 64)]  # conv1_2 pruned; conv2_2 whole
    full, pruned = image_terms(enc, imgs), image_terms(tmp_path / "p.onnx", imgs)
    assert pruned.shape == full.shape == (64, net.encoding_width)
    np.testing.assert_allclose(pruned, full, rtol=1e-4, atol=1e-4 * np.abs(full).max())
