"""Metrics on hand-made cases, camera-grid binning and the heat-map figure."""

import math

import numpy as np
import pytest

from training import metrics as M
from training.plots import plot_grid_heatmaps, plot_training_curves


def test_binary_metrics_hand_made():
    labels = np.array([1, 1, 1, 0, 0])
    p = np.array([0.9, 0.2, 0.6, 0.1, 0.7])  # tp, fn, tp, tn, fp
    m = M.binary_metrics(labels, p)
    assert (m["tp"], m["fn"], m["tn"], m["fp"]) == (2, 1, 1, 1)
    assert m["tpr"] == pytest.approx(2 / 3)
    assert m["tnr"] == pytest.approx(1 / 2)
    assert m["balanced_accuracy"] == pytest.approx((2 / 3 + 1 / 2) / 2)
    assert m["accuracy"] == pytest.approx(3 / 5)
    # AUC: of the 6 (positive, negative) pairs the positive scores higher in 4 (0.2 < 0.7, 0.6 < 0.7)
    assert m["auc"] == pytest.approx(4 / 6)


def test_metrics_by_group_are_the_metrics_of_each_groups_rows():
    labels = np.array([1, 0, 1, 0, 1, 1])
    p = np.array([0.9, 0.1, 0.2, 0.8, 0.7, 0.6])
    fam = np.array(["mug", "mug", "box", "box", "mug", "box"])
    g = M.metrics_by_group(labels, p, fam)
    assert list(g) == ["box", "mug"]
    assert g["mug"]["balanced_accuracy"] == 1.0 and g["mug"]["n"] == 3
    assert (g["box"]["tp"], g["box"]["fn"], g["box"]["fp"]) == (1, 1, 1)


def test_metrics_by_bin_split_rows_by_value_in_ascending_bins():
    labels = np.array([1, 0, 1, 0, 1])
    p = np.array([0.9, 0.1, 0.2, 0.8, 0.7])
    d = np.array([0.42, 0.48, 0.71, 0.79, 0.44])  # metres: bins 0.4-0.5 and 0.7-0.8, none at 0.5-0.7
    b = M.metrics_by_bin(labels, p, d, 0.1)
    assert list(b) == ["0.4-0.5", "0.7-0.8"]
    assert b["0.4-0.5"]["n"] == 3 and b["0.4-0.5"]["balanced_accuracy"] == 1.0
    assert (b["0.7-0.8"]["fn"], b["0.7-0.8"]["fp"]) == (1, 1)


def test_all_negative_predictor_has_half_balanced_accuracy():
    labels = np.array([1] * 19 + [0] * 81)
    m = M.binary_metrics(labels, np.zeros(100))
    assert m["accuracy"] == pytest.approx(0.81) and m["balanced_accuracy"] == pytest.approx(0.5)


def test_single_class_gives_nan_not_error():
    m = M.binary_metrics(np.zeros(4), np.zeros(4))
    assert math.isnan(m["tpr"]) and m["tnr"] == 1.0 and math.isnan(m["balanced_accuracy"])


def test_object_bootstrap_resamples_objects_not_rows():
    # 4 objects of 500 rows: two scored perfectly, two always wrong. By rows the estimate looks
    # exact (2,000 rows); by objects it is 4 draws, and the interval spans most of [0, 1].
    obj = np.repeat(np.arange(4), 500)
    y = np.tile(np.r_[np.ones(250), np.zeros(250)], 4)
    p = np.where(obj < 2, y, 1 - y)
    lo, hi = M.object_bootstrap_ci(y, p, obj)
    assert M.binary_metrics(y, p)["balanced_accuracy"] == 0.5
    assert lo <= 0.25 and hi >= 0.75


def test_object_bootstrap_is_tight_when_every_object_agrees_and_undefined_for_one_object():
    obj = np.repeat(np.arange(20), 10)
    y = np.tile(np.r_[np.ones(5), np.zeros(5)], 20)
    assert M.object_bootstrap_ci(y, y, obj) == [1.0, 1.0]
    assert M.object_bootstrap_ci(y[:10], y[:10], obj[:10]) == [None, None]


def test_grid_cells_of_005m_and_5deg():
    labels = np.array([1, 1, 0, 0, 1])
    p = np.array([0.9, 0.1, 0.2, 0.8, 0.7])
    d = np.array([0.42, 0.44, 0.47, 0.52, 0.52])
    phi = np.radians([1.0, 2.0, 3.0, 7.0, 7.0])
    g = M.grid_metrics(labels, p, d, phi)
    np.testing.assert_allclose(g["d_edges"], [0.40, 0.45, 0.50, 0.55])
    np.testing.assert_allclose(g["phi_edges_deg"], [0.0, 5.0, 10.0])
    assert g["tpr"][0, 0] == pytest.approx(0.5)  # two positives in (0.40-0.45 m, 0-5 deg), one found
    assert g["tnr"][1, 0] == pytest.approx(1.0)
    assert g["tpr"][2, 1] == pytest.approx(1.0) and g["tnr"][2, 1] == pytest.approx(0.0)
    assert np.isnan(g["tpr"][1, 1]) and g["n_positive"].sum() == 3


def test_heatmap_png_written(tmp_path):
    rng = np.random.default_rng(0)
    n = 400
    g = M.grid_metrics(rng.integers(0, 2, n), rng.random(n), rng.uniform(0.4, 1.1, n), rng.uniform(0, 1.2, n))
    out = plot_grid_heatmaps(g, tmp_path / "heat.png", title="t")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_training_curves_png_from_log(tmp_path):
    log = tmp_path / "metrics.jsonl"
    log.write_text(
        '{"kind": "train", "samples": 64, "loss": 0.7}\n{"kind": "val", "samples": 64, "loss": 0.6, '
        '"balanced_accuracy": 0.6, "tpr": 0.5, "tnr": 0.7}\nnot json\n'
    )
    assert plot_training_curves(log, tmp_path / "c.png").stat().st_size > 1000
