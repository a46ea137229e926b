"""The trial-noise ceiling: exact on a known two-point distribution of success probabilities,
unchanged by re-weighting the classes, and read from a crop dataset's physics labels."""

import json

import numpy as np
import pytest
from scipy.stats import binom

from training.__main__ import main as cli
from training.label_noise import dataset_ceiling, label_ceiling
from training.synthetic import make_synthetic_crop_dataset

T, M = 8, 5  # 8 trials, positive with >= 5 successes (success rate > 0.5)


def expected_counts(ps, weights, n=1_000_000):
    k = np.arange(T + 1)
    return n * sum(w * binom.pmf(k, T, p) for p, w in zip(ps, weights))


def test_two_point_distribution_gives_the_analytic_ceiling():
    # half the grasps succeed with p = 0.3, half with 0.8: the best rule calls the 0.8 ones positive
    c = label_ceiling(expected_counts([0.3, 0.8], [0.5, 0.5]), T, M)
    a, b = binom.sf(M - 1, T, 0.3), binom.sf(M - 1, T, 0.8)  # P(label positive | p)
    tpr, tnr = b / (a + b), (1 - a) / ((1 - a) + (1 - b))
    assert c.balanced_accuracy == pytest.approx((tpr + tnr) / 2, abs=2e-3)
    assert c.auc == pytest.approx(tpr * tnr + 0.5 * (tpr * (1 - tnr) + (1 - tpr) * tnr), abs=0.01)


def test_noise_free_labels_have_a_perfect_ceiling():
    c = label_ceiling(expected_counts([0.0, 1.0], [0.7, 0.3]), T, M)
    assert c.balanced_accuracy == pytest.approx(1.0, abs=1e-6) and c.auc == pytest.approx(1.0, abs=1e-6)


def test_reweighting_to_the_native_positivity_undoes_resampling():
    native = expected_counts([0.05, 0.4, 0.9], [0.8, 0.15, 0.05])
    pos = native[M:].sum() / native.sum()
    resampled = native.copy()
    resampled[M:] *= 4.0  # positives kept 4x as often, as the sampling stage does
    a = label_ceiling(native, T, M)
    b = label_ceiling(resampled, T, M, native_positivity=pos)
    assert b.balanced_accuracy == pytest.approx(a.balanced_accuracy, abs=2e-3)


def test_cli_reads_the_physics_labels_of_a_crop_dataset(tmp_path, capsys):
    make_synthetic_crop_dataset(tmp_path / "d", 32, 16, 64, seed=0)
    m = json.loads((tmp_path / "d" / "manifest.json").read_text())
    m["source"] = {"config": {"label": {"kind": "physics", "trials": T, "success_threshold": 0.5}}}
    m["label_threshold"] = 0.5
    (tmp_path / "d" / "manifest.json").write_text(json.dumps(m))
    q = np.repeat([0.0, 1.0], 32).astype(np.float32)  # noise-free: every grasp 0/8 or 8/8
    np.save(tmp_path / "d" / "test" / "quality.npy", q)
    assert cli(["label-noise", "--data", str(tmp_path / "d")]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["counts"] == [32] + [0] * 7 + [32] and out["balanced_accuracy"] == pytest.approx(1.0, abs=1e-6)


def test_other_labels_are_refused(tmp_path):
    make_synthetic_crop_dataset(tmp_path / "d", 32, 16, 16, seed=0)
    with pytest.raises(ValueError, match="physics label"):
        dataset_ceiling(tmp_path / "d")
