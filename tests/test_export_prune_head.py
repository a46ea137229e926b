"""export.prune_head: the head's dead ReLU units removed before it is quantised, checked against
the unpruned head, and written as the model folder's int8 head."""

from __future__ import annotations

import shutil

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from conftest import synthetic_crops
from onnx import numpy_helper

from export.prune_head import (
    WEIGHTS,
    DeadUnits,
    HeadWeights,
    PruningError,
    check_pruned_head,
    dead_units,
    image_terms,
    is_plain_head,
    main,
    measured_dead_units,
    prune_fc5_graph,
    prune_head_graph,
    rebuild_int8_head,
)
from service.runtime import FastModel
from vgq.model_card import HEAD_INPUTS, HEAD_OUTPUT, ModelCard

DEAD4, DEAD5 = np.arange(0, 1024, 9), np.arange(0, 1024, 3)  # units the fixture kills


@pytest.fixture(scope="module")
def dead_model(tmp_path_factory, model_dir):
    """A copy of the test model whose head has known dead units: a very negative bias on every
    9th fc4 unit and every 3rd fc5 unit (as training leaves some units, never active)."""
    out = tmp_path_factory.mktemp("prune") / "m"
    shutil.copytree(model_dir, out)
    g = onnx.load(str(out / "head.onnx"))
    for t in g.graph.initializer:
        if t.name in (WEIGHTS["fc4_b"], WEIGHTS["fc5_b"]):
            b = numpy_helper.to_array(t).copy()
            b[DEAD4 if t.name == WEIGHTS["fc4_b"] else DEAD5] = -100.0
            t.CopyFrom(numpy_helper.from_array(b, t.name))
    onnx.save(g, str(out / "head.onnx"))
    return out


def _score(path, terms, poses):
    s = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return s.run([HEAD_OUTPUT], {HEAD_INPUTS[0]: terms, HEAD_INPUTS[1]: poses})[0]


def _calibration(model, n=64, seed=31):
    crops, poses, _ = synthetic_crops(n, np.random.default_rng(seed))
    return image_terms(model / "encoder.onnx", crops), poses


def test_dead_units_are_the_units_that_never_fire(dead_model):
    terms, poses = _calibration(dead_model)
    w = HeadWeights.from_onnx(dead_model / "head.onnx")
    units = dead_units(w, terms, poses, cross_pairs=500)
    assert not set(DEAD4) & set(units.fc4_kept) and not set(DEAD5) & set(units.fc5_kept)
    # fc4's maximum is over every (term, pose) pairing: brute force agrees
    every = terms[:, None, :] + w.pose_part(poses)[None, :, :]
    assert np.array_equal(units.fc4_kept, np.flatnonzero(every.max((0, 1)) > 0))
    # fc5: every kept unit fires on some calibration pair
    assert (w.fc5_pre(terms, w.pose_part(poses))[:, units.fc5_kept].max(0) > 0).mean() > 0.5
    assert units.summary()["units"] == 1024 and units.n_calibration == 64


def test_removing_dead_units_leaves_every_probability_unchanged(dead_model, tmp_path):
    keep = DeadUnits(np.setdiff1d(np.arange(1024), DEAD4), np.setdiff1d(np.arange(1024), DEAD5), 1024, 0, 0)
    prune_head_graph(dead_model / "head.onnx", tmp_path / "p.onnx", keep)
    w = {t.name: t.dims for t in onnx.load(str(tmp_path / "p.onnx")).graph.initializer}
    assert list(w[WEIGHTS["fc5_w"]]) == [1024 - len(DEAD5), 1024 - len(DEAD4)]
    terms, poses = _calibration(dead_model, 40, seed=32)
    for t in (terms[:1], terms):  # one window's term broadcast over k grasps, and one per grasp
        full, pruned = _score(dead_model / "head.onnx", t, poses), _score(tmp_path / "p.onnx", t, poses)
        assert pruned.shape == full.shape == (40,) and np.abs(pruned - full).max() < 1e-6


def test_check_refuses_a_head_pruned_of_live_units(dead_model, tmp_path):
    terms, poses = _calibration(dead_model)
    units = dead_units(HeadWeights.from_onnx(dead_model / "head.onnx"), terms, poses, cross_pairs=0)
    too_many = DeadUnits(units.fc4_kept, units.fc5_kept[:5], 1024, 64, 0)
    prune_head_graph(dead_model / "head.onnx", tmp_path / "bad.onnx", too_many)
    check_terms, check_poses = _calibration(dead_model, 100, seed=33)
    with pytest.raises(PruningError, match="unlike the unpruned"):
        check_pruned_head(dead_model / "head.onnx", tmp_path / "bad.onnx", check_terms, check_poses, too_many)
    prune_head_graph(dead_model / "head.onnx", tmp_path / "ok.onnx", units)
    ok = check_pruned_head(dead_model / "head.onnx", tmp_path / "ok.onnx", check_terms, check_poses, units)
    assert ok.n_pairs == 200 and ok.decisions_changed == 0  # own pairs and as many crossed pairs


def test_not_a_head_graph_is_refused(model_dir):
    with pytest.raises(PruningError, match="not a Fast-VGQ-CNN head graph"):
        HeadWeights.from_onnx(model_dir / "encoder.onnx")


def test_rebuild_writes_a_smaller_int8_head_the_service_serves(dead_model, tmp_path):
    out = tmp_path / "m"
    shutil.copytree(dead_model, out)
    calib = synthetic_crops(64, np.random.default_rng(31))[:2]
    check = synthetic_crops(300, np.random.default_rng(34))
    rec = rebuild_int8_head(out, calib, check, check_data="synthetic", calibration_data="synthetic", cross_pairs=500)
    card = ModelCard.load(out)
    assert card.files["head_int8"] == "head_int8.onnx" and card.export["int8_head"] == rec
    assert rec["pruning"]["units"]["fc5_units_kept"] <= 1024 - len(DEAD5) and rec["quantized_nodes"] == [
        "/head/fc5/Gemm"
    ]
    q = {t.name: t.dims for t in onnx.load(str(out / "head_int8.onnx")).graph.initializer}
    assert q["head.fc5.weight_Transposed_quantized"][1] == rec["pruning"]["units"]["fc5_units_kept"]
    m8, m32 = FastModel(out), FastModel(out, head_precision="fp32")
    term = m32.encode(check[0][0])
    assert np.abs(m8.score(term, check[1][:64]) - m32.score(term, check[1][:64])).max() <= 0.05
    assert not list(out.glob(".*tmp")) and not list(out.glob(".prune-*"))


def test_refused_pruning_leaves_the_folder_unchanged(dead_model, tmp_path, monkeypatch):
    import export.prune_head as ph

    out = tmp_path / "m"
    shutil.copytree(dead_model, out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    monkeypatch.setattr(ph, "MAX_ABS_DIFF", -1.0)
    with pytest.raises(PruningError, match="unlike the unpruned"):
        rebuild_int8_head(
            out, synthetic_crops(32, np.random.default_rng(1))[:2], synthetic_crops(200, np.random.default_rng(2))
        )
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


@pytest.mark.parametrize(
    "args, message",
    [
        (["--calibration-n", "3"], "--calibration-n must be >= 16"),
        (["--cross-pairs", "-1"], "--cross-pairs must be >= 0"),
        (["--check-n", "-5"], "--check-n must be >= 0"),
    ],
)
def test_cli_refuses_bad_numbers(dead_model, tmp_path, capsys, args, message):
    with pytest.raises(SystemExit) as e:
        main(["--model-dir", str(dead_model), "--calibration", "c", "--check", "k", *args])
    assert e.value.code == 2 and message in capsys.readouterr().err


def test_cli_names_a_missing_calibration_file(dead_model, tmp_path, capsys):
    out = tmp_path / "m"
    shutil.copytree(dead_model, out)
    with pytest.raises(SystemExit) as e:
        main(["--model-dir", str(out), "--calibration", str(tmp_path / "none.npz"), "--check", str(tmp_path / "k.npz")])
    assert e.value.code == 2 and "none.npz" in capsys.readouterr().err


@pytest.mark.parametrize("prune", [True, False])
def test_export_cli_prunes_the_int8_head_unless_told_not_to(tmp_path, prune):
    from test_export import _tiny_run

    from export.__main__ import main as export_main

    data, run = _tiny_run(tmp_path)
    args = ["--run", str(run), "--data", str(data), "--out", str(tmp_path / "m"), "--verify-n", "4"]
    args += ["--no-calibration", "--int8-head", "--int8-check-n", "100", "--prune-calibration-n", "16"]
    export_main(args + ([] if prune else ["--no-prune"]))
    rec = ModelCard.load(tmp_path / "m").export["int8_head"]
    assert ("pruning" in rec) == prune
    if prune:
        assert rec["pruning"]["units"]["units"] == 1024 and rec["pruning"]["units"]["n_calibration"] == 16


def test_head_ab_times_two_folders_and_reports_their_agreement(dead_model, tmp_path, capsys):
    from export.model_ab import main as head_ab

    out = tmp_path / "m"
    shutil.copytree(dead_model, out)
    rebuild_int8_head(
        out, synthetic_crops(64, np.random.default_rng(31))[:2], synthetic_crops(300, np.random.default_rng(34))
    )
    r = head_ab([str(dead_model), str(out), "--rounds", "2", "--calls", "3", "--k", "16"])
    assert r["n_heldout"] == 256 and r["a"]["head_ms"] > 0 and r["b"]["head_ms"] > 0
    assert r["a"]["head_precision"] == "fp32" and r["b"]["head_precision"] == "int8"  # the copy gained an int8 head
    assert 0 < r["max_abs_diff"] <= 0.05 and "decisions changed" in capsys.readouterr().out
    with pytest.raises(SystemExit) as e:
        head_ab([str(dead_model), str(tmp_path / "none")])
    assert e.value.code == 2


@pytest.fixture(scope="module")
def jaw_model(tmp_path_factory):
    """An exported jaw-grid model (its head adds the grid's term to fc4) with every 3rd fc5 unit
    dead (a very negative bias), exported without an int8 head."""
    import torch

    from export.onnx_export import export_model
    from training.networks import GraspQualityNet
    from vgq.camera import DEFAULT_INTRINSICS
    from vgq.crop import CropGeometry
    from vgq.normalization import Normalization

    torch.manual_seed(0)
    net = GraspQualityNet("fast_vgqcnn", roi_head="jaw").eval()
    torch.nn.init.normal_(net.roi_fc2.weight, std=0.05)  # a head that uses the grid
    crops, poses, _ = synthetic_crops(64, np.random.default_rng(8))
    net.set_normalization(Normalization.from_data(crops, poses, net.pose_columns))
    with torch.no_grad():
        net.fc5.bias[DEAD5] = -100.0
    out = tmp_path_factory.mktemp("prune-jaw") / "m"
    export_model(net, out, crops[:16], poses[:16], CropGeometry(96, 32, 36.0), DEFAULT_INTRINSICS)
    return out


def test_a_jaw_grid_head_is_pruned_by_measuring_its_graph(jaw_model, model_dir, tmp_path):
    head, enc = jaw_model / "head.onnx", jaw_model / "encoder.onnx"
    assert is_plain_head(model_dir / "head.onnx") and not is_plain_head(
        head
    )  # the grid's reads also take the encoding: no closed-form fc4 maximum
    crops, poses, _ = synthetic_crops(96, np.random.default_rng(34))
    units = measured_dead_units(head, enc, crops, poses, cross_pairs=300, chunk=40)
    assert not set(DEAD5) & set(units.fc5_kept) and len(units.fc4_kept) == 1024  # fc4 kept whole
    assert len(units.fc5_kept) > 0.5 * (1024 - len(DEAD5)) and units.n_calibration == 96
    prune_fc5_graph(head, tmp_path / "p.onnx", units)
    w = {t.name: t.dims for t in onnx.load(str(tmp_path / "p.onnx")).graph.initializer}
    assert list(w[WEIGHTS["fc5_w"]]) == [len(units.fc5_kept), 1024]
    terms = image_terms(enc, crops[:40])
    for t in (terms[:1], terms):  # one window's encoding for k grasps, and one per grasp
        full, pruned = _score(head, t, poses[:40]), _score(tmp_path / "p.onnx", t, poses[:40])
        assert np.abs(pruned - full).max() < 1e-5
    check = check_pruned_head(head, tmp_path / "p.onnx", terms, poses[:40], units)
    assert check.decisions_changed == 0
    with pytest.raises(PruningError, match="keeps every fc4 unit"):
        prune_fc5_graph(head, tmp_path / "x.onnx", DeadUnits(units.fc4_kept[:10], units.fc5_kept, 1024, 0, 0))


def test_a_placement_stream_head_is_not_taken_for_the_papers_head(tmp_path):
    """Its stream adds a term to fc4 that the closed-form maxima would miss: measured instead."""
    import torch

    from export.onnx_export import export_model
    from training.networks import GraspQualityNet
    from vgq.camera import DEFAULT_INTRINSICS
    from vgq.crop import CropGeometry

    torch.manual_seed(1)
    net = GraspQualityNet("fast_vgqcnn", placement=True, placement_units=16).eval()
    crops, poses, _ = synthetic_crops(16, np.random.default_rng(3))
    rows = np.concatenate([poses, np.zeros((16, net.n_place), np.float32)], axis=1)
    export_model(net, tmp_path / "m", crops, rows, CropGeometry(96, 32, 36.0), DEFAULT_INTRINSICS)
    assert not is_plain_head(tmp_path / "m" / "head.onnx")


def test_cli_asks_for_check_n_when_a_dataset_holds_too_many_check_rows(dead_model, tmp_path, capsys, monkeypatch):
    from export import int8_encoder
    from training.synthetic import make_synthetic_crop_dataset

    make_synthetic_crop_dataset(tmp_path / "crops", 16, 16, 16, seed=2)
    monkeypatch.setattr(int8_encoder, "MAX_CHECK_ROWS", 20)  # 32 val + test rows here
    with pytest.raises(SystemExit) as e:
        main(
            [
                "--model-dir",
                str(dead_model),
                "--calibration",
                str(tmp_path / "crops"),
                "--check",
                str(tmp_path / "crops"),
            ]
        )
    assert e.value.code == 2 and "pass --check-n" in capsys.readouterr().err
