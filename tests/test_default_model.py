"""The bundled default model is a trained grasp model, not a placeholder: its card records how
it was made and what it scores, and its ONNX graphs (the service's runtime, no torch) classify
real held-out crops of test objects better than chance."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.runtime import FastModel
from vgq.model_card import ModelCard

ROOT = Path(__file__).resolve().parent.parent
DEFAULT = ROOT / "models" / "fast-vgqcnn-default"
HELDOUT = ROOT / "examples" / "heldout_test_crops.npz"


@pytest.fixture(scope="module")
def card() -> ModelCard:
    return ModelCard.load(DEFAULT)


def test_card_records_recipe_training_and_test_metrics(card):
    assert card.dataset["recipe"].startswith("python -m datagen recipe")
    assert card.dataset["counts"]["test"]["n"] > 10_000
    assert card.training["samples_seen"] > 100_000 and card.training["seed"] == 0
    test = card.metrics["test"]
    assert {"balanced_accuracy", "tpr", "tnr"} <= set(test)


def test_card_beats_the_pose_only_baseline_on_the_same_test_split(card):
    model, base = card.metrics["test"], card.metrics["baseline_mlp"]["test"]
    assert model["n"] == base["n"]
    assert model["balanced_accuracy"] > base["balanced_accuracy"] + 0.05


def test_onnx_graphs_classify_heldout_test_crops():
    d = np.load(HELDOUT)
    m = FastModel(DEFAULT, threads=1)
    p = np.concatenate([m.score(m.encode(img), pose[None]) for img, pose in zip(d["images"], d["poses"])])
    pred, y = p > 0.5, d["labels"] == 1
    tpr, tnr = pred[y].mean(), (~pred[~y]).mean()
    assert y.sum() >= 100 and (~y).sum() >= 100
    assert (tpr + tnr) / 2 > 0.7, (tpr, tnr)
