"""training.stacker and export.stack_head: a placement stacker fitted on a model's scores, and
the stacked head graphs that serve it (on the tests' briefly trained model with an int8 head:
the bundled model is itself stacked)."""

import json
import shutil

import numpy as np
import pytest

from export.stack_head import write_stacked
from service.runtime import FastModel
from training.stacker import INPUTS, Stacker
from vgq.calibration import logit
from vgq.model_card import ModelCard


def random_stacker(rng: np.random.Generator, hidden: int = 8) -> Stacker:
    shapes = [(hidden, len(INPUTS)), (hidden, hidden), (1, hidden)]
    layers = tuple(
        (rng.normal(0, 0.5, s).astype(np.float32), rng.normal(0, 0.1, s[0]).astype(np.float32)) for s in shapes
    )
    return Stacker(
        rng.normal(0, 1, len(INPUTS)).astype(np.float32), rng.uniform(0.5, 2, len(INPUTS)).astype(np.float32), layers
    )


def example_rows(model_dir, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The example image's centre window (32, 32), its 16 example grasps' pose rows (16, 7) and
    random placement rows (16, 7), the first 4 unknown."""
    from export.benchmark import fast_preprocess

    depth = np.load("examples/depth_example.npy")
    g = np.asarray(json.loads(open("examples/grasps_example.json").read())["grasps"], np.float64)
    centre = np.array([(depth.shape[1] - 1) / 2, (depth.shape[0] - 1) / 2])
    crop, poses = fast_preprocess(depth, g, ModelCard.load(model_dir).geometry, centre)
    k = len(poses)
    place = np.c_[np.ones(k), rng.uniform(0, 0.1, (k, 3)), rng.uniform(-0.05, 0.05, k), rng.uniform(0, 0.2, (k, 2))]
    place[:4] = 0.0
    return crop[0, 0], poses.astype(np.float32), place.astype(np.float32)


@pytest.fixture(scope="module")
def base(int8_model, tmp_path_factory):
    """The briefly trained model (fp32 and int8 heads) with a calibration and a test result in its card."""
    from export.evaluate import record_in_card

    out = tmp_path_factory.mktemp("base") / "m"
    shutil.copytree(int8_model[0], out)
    path = out / "model_card.json"
    d = json.loads(path.read_text())
    d["calibration"] = {"method": "platt", "target_positivity": 0.2, "target_positivity_source": "tests"}
    path.write_text(json.dumps(d))
    record_in_card(out, "test", {"balanced_accuracy": 0.5})
    shutil.copy("models/fast-vgqcnn-default/planner_ranker.json", out)  # as if fitted on the unstacked scores
    return out


@pytest.fixture(scope="module")
def stacked(base, tmp_path_factory):
    stacker = random_stacker(np.random.default_rng(0))
    out = write_stacked(base, stacker, tmp_path_factory.mktemp("stk") / "m", {"fit_on": ["test"]})
    return stacker, out


@pytest.mark.parametrize("precision", ["fp32", "int8"])
def test_the_stacked_head_scores_as_the_stacker_on_the_heads_own_logit(base, stacked, precision):
    stacker, out = stacked
    rng = np.random.default_rng(1)
    unstacked = FastModel(base, threads=1, head_precision=precision, encoder_precision="fp32")
    model = FastModel(out, threads=1, head_precision=precision, encoder_precision="fp32")
    assert unstacked.head_precision == model.head_precision == precision
    crop, poses, place = example_rows(base, rng)
    term = unstacked.encode(crop)
    p = unstacked.score(term, poses)
    assert ((p > 1e-3) & (p < 1 - 1e-3)).all()  # logit(p) is the head's own logit to float precision
    want = 1 / (1 + np.exp(-stacker.apply(logit(p), place)))
    got = model.score(term, np.c_[poses, place])
    np.testing.assert_allclose(got, want, atol=1e-5)
    np.testing.assert_array_equal(got[:4], p[:4])  # unknown rows: the head as it was
    assert np.abs(got[4:] - p[4:]).max() > 1e-2


def test_the_stacked_card_asks_for_placement_rows_under_a_new_version(base, stacked):
    stacker, out = stacked
    before, card = ModelCard.load(base), ModelCard.load(out)
    assert card.placement_columns and card.head_pose_width == 14
    assert card.model_version.startswith(before.model_version + "-stk") and card.model_version != before.model_version
    assert Stacker.from_dict(card.export["stacker"]["weights"]).to_dict() == stacker.to_dict()
    assert card.calibration == {}  # the calibration fits the unstacked scores: dropped unless refitted
    # the test result was the unstacked graphs': kept as theirs, not as the stacked model's
    assert "test" not in card.metrics and card.metrics["before_stacker"]["test"] == before.metrics["test"]
    assert (base / "planner_ranker.json").is_file() and not (out / "planner_ranker.json").exists()


def test_a_stacked_folder_gives_the_network_it_was_stacked_on(base, stacked):
    import torch

    from export.from_onnx import fast_net_from_model_dir

    net, _ = fast_net_from_model_dir(base)
    under, card = fast_net_from_model_dir(stacked[1])
    assert card.placement_columns and under.n_place == 0  # the stacker's rows, not the network's
    a, b = net.state_dict(), under.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_a_folder_whose_head_reads_placement_rows_is_not_stacked_again(stacked, tmp_path):
    stacker, out = stacked
    with pytest.raises(ValueError, match="already reads placement rows"):
        write_stacked(out, stacker, tmp_path / "again", {})


def test_an_out_folder_that_is_not_a_model_folder_is_left_alone(base, stacked, tmp_path):
    stacker, _ = stacked
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "keep.txt").write_text("mine")
    with pytest.raises(ValueError, match="not a model folder"):
        write_stacked(base, stacker, tmp_path / "data", {})
    assert (tmp_path / "data" / "keep.txt").read_text() == "mine"
    again = write_stacked(base, stacker, tmp_path / "m", {})
    assert write_stacked(base, stacker, again, {}) == again  # a model folder it wrote is replaced


def test_a_stacker_fitted_where_the_label_follows_the_placement_row_beats_the_model(base, tmp_path, capsys):
    from training.__main__ import main
    from training.synthetic import make_synthetic_crop_dataset

    for name, seed in (("fit", 1), ("judge", 2)):
        make_synthetic_crop_dataset(tmp_path / name, 8, 8, 600, signal="placement", seed=seed)
    judge = str(tmp_path / "judge")
    argv = ["stacker", "--model-dir", str(base), "--fit", str(tmp_path / "fit"), "--judge", judge, "--test", judge]
    assert main([*argv, "--out", str(tmp_path / "m"), "--per-object", "600", "--epochs", "300"]) == 0
    card = ModelCard.load(tmp_path / "m")
    judged = card.export["stacker"]["judged"]
    assert judged["stacked"]["all"]["balanced_accuracy"] > judged["model"]["all"]["balanced_accuracy"] + 0.1
    assert "| all |" in capsys.readouterr().out
    rec = json.loads((tmp_path / "m" / "model_card.json").read_text())
    assert rec["calibration"]["method"] == "platt" and (tmp_path / "m" / "reliability_diagram.png").is_file()
    # --test: the card's test result is the stacked graphs', measured on the judge crops' test split
    test = card.metrics["test"]
    assert (
        test["data"] == judge
        and test["n"] == card.export["stacker"]["judge_rows"]
        and test["balanced_accuracy"] == pytest.approx(judged["stacked"]["all"]["balanced_accuracy"], abs=0.03)
    )
    assert card.metrics["before_stacker"]["test"] == {"balanced_accuracy": 0.5}


def test_bad_stacker_options_exit_2_naming_them(base, tmp_path, capsys):
    from training.__main__ import main

    argv = [
        "stacker",
        "--model-dir",
        str(base),
        "--fit",
        str(tmp_path),
        "--judge",
        str(tmp_path),
        "--out",
        str(tmp_path / "m"),
    ]
    assert main([*argv, "--per-object", "0"]) == 2
    assert "--per-object" in capsys.readouterr().err
    assert main([*argv, "--test", str(tmp_path / "nowhere")]) == 2
    assert "nowhere: not a crop dataset" in capsys.readouterr().err
    assert not (tmp_path / "m").exists()


def test_family_balance_weighs_each_familys_classes_alike():
    from training.stacker import row_weights

    labels = np.array([1, 0, 0, 0, 1, 1, 1, 0], bool)
    family = np.array(["mug"] * 4 + ["box"] * 4)
    w = row_weights(labels, family, "family")
    for f in ("mug", "box"):
        for c in (False, True):
            r = (family == f) & (labels == c)
            assert w[r].sum() == pytest.approx(len(labels) / 4)
    w = row_weights(labels, family, "class")
    assert w[labels].sum() == pytest.approx(w[~labels].sum()) and w.mean() == pytest.approx(1.0)
    with pytest.raises(ValueError, match="balance"):
        row_weights(labels, family, "objects")


def test_crops_whose_rows_put_the_grasp_at_its_true_depth_are_refused(base, tmp_path, capsys):
    # crops cut before placement_grasp_depth: their rows disagree with what the service computes
    from training.__main__ import main
    from training.synthetic import make_synthetic_crop_dataset

    make_synthetic_crop_dataset(tmp_path / "old", 8, 8, 64, signal="placement", seed=1)
    m = json.loads((tmp_path / "old" / "manifest.json").read_text())
    del m["placement_grasp_depth"]
    (tmp_path / "old" / "manifest.json").write_text(json.dumps(m))
    argv = ["stacker", "--model-dir", str(base), "--fit", str(tmp_path / "old"), "--judge", str(tmp_path / "old")]
    assert main([*argv, "--out", str(tmp_path / "m"), "--per-object", "8"]) == 2
    assert "placement_grasp_depth" in capsys.readouterr().err and not (tmp_path / "m").exists()
