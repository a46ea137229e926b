"""The numbers the README and docs/ quote about the bundled model are the model card's: a
retrained model with a new card, or an edited table, makes these fail until both agree.
(Numbers that are not in the card are marked in the text as measurements with their command.)"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from vgq.model_card import ModelCard

ROOT = Path(__file__).resolve().parent.parent
README = (ROOT / "README.md").read_text()
TRAINING = (ROOT / "docs" / "training.md").read_text()
PERFORMANCE = (ROOT / "docs" / "performance.md").read_text()


@pytest.fixture(scope="module")
def card() -> ModelCard:
    return ModelCard.load(ROOT / "models" / "fast-vgqcnn-default")


def percents(text: str, row_start: str) -> list[float]:
    """The percentages in the markdown table row that starts with ``row_start``."""
    rows = [line for line in text.splitlines() if line.startswith(row_start)]
    assert len(rows) == 1, f"expected one row starting {row_start!r}, found {len(rows)}"
    return [float(x) for x in re.findall(r"(\d+(?:\.\d+)?)%", rows[0])]


def pct(x: float) -> float:
    return round(100 * x, 1)


@pytest.mark.parametrize(
    "text, row", [(README, "| Fast-VGQ-CNN (bundled)"), (TRAINING, "| **Fast-VGQ-CNN, kappa 36 px**")]
)
def test_bundled_model_row_is_the_cards_test_metrics(card, text, row):
    m = card.metrics["test"]
    assert percents(text, row) == [pct(m["balanced_accuracy"]), pct(m["tpr"]), pct(m["tnr"])]


@pytest.mark.parametrize("text, row", [(README, "| pose-only MLP"), (TRAINING, "| pose-only MLP")])
def test_pose_only_row_is_the_cards_baseline(card, text, row):
    m = card.metrics["baseline_mlp"]["test"]
    assert percents(text, row) == [pct(m["balanced_accuracy"]), pct(m["tpr"]), pct(m["tnr"])]


def test_test_split_size_and_training_samples_are_the_cards(card):
    n = card.dataset["counts"]["test"]["n"]
    assert f"{n:,} test" in README and f"({n:,} grasps" in TRAINING
    seen = card.training["samples_seen"]
    assert f"{round(seen / 1000)}k training samples" in README and f"{seen:,} of a" in TRAINING
    counts = card.dataset["counts"]
    assert f"train {counts['train']['n']:,} / val {counts['val']['n']:,} / test {n:,}" in TRAINING
    assert f"best validation balanced accuracy | {pct(card.training['best_val_balanced_accuracy'])}%" in TRAINING


def test_int8_check_numbers_are_the_cards(card):
    q = card.export["int8_head"]
    assert percents(TRAINING, "| int8 head of the bundled model") == [
        pct(q["balanced_accuracy_int8"]),
        pct(q["balanced_accuracy_fp32"]),
    ]
    assert (
        f"balanced accuracy {100 * q['balanced_accuracy_int8']:.2f}% vs {100 * q['balanced_accuracy_fp32']:.2f}% for fp32"
        in PERFORMANCE
    )
    assert (
        f"mean {q['mean_abs_diff_probability']:.4f}" in PERFORMANCE
        and f"max {q['max_abs_diff_probability']:.3f}" in PERFORMANCE
    )
    assert f"{q['decisions_changed']} of {q['n']} decisions" in PERFORMANCE
    assert f"~{q['mean_abs_diff_probability']:.3f} on average (at most ~{q['max_abs_diff_probability']:.2f}" in README


def test_leave_family_out_numbers_are_the_cards(card):
    m = card.metrics["leave_family_out"]
    row = "| held-out families (mug + metaball), never seen"
    assert percents(TRAINING, row) == [pct(m["balanced_accuracy"]), pct(m["tpr"]), pct(m["tnr"])]
    assert f"{m['auc']:.3f}" in [line for line in TRAINING.splitlines() if line.startswith(row)][0]
    assert f"it scores {pct(m['balanced_accuracy'])}%" in README
    for family, r in m["by_family"].items():
        assert percents(TRAINING, f"| {family} | {pct(r['balanced_accuracy'])}%")[0] == pct(r["balanced_accuracy"])
