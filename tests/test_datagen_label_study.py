"""datagen.label_study: the AUC used to compare labels, and the candidates' scores."""

from __future__ import annotations

import numpy as np

from datagen.label_study import candidate_labels
from training.metrics import auc


def test_auc_matches_the_pairwise_definition_with_ties():
    rng = np.random.default_rng(0)
    s = rng.integers(0, 5, 200).astype(float)
    y = rng.random(200) < 0.4
    pos, neg = s[y], s[~y]
    brute = ((pos[:, None] > neg[None]).sum() + 0.5 * (pos[:, None] == neg[None]).sum()) / (len(pos) * len(neg))
    assert abs(auc(s, y) - brute) < 1e-12
    assert auc(np.arange(4.0), np.array([0, 0, 1, 1], bool)) == 1.0
    assert np.isnan(auc(np.arange(3.0), np.ones(3, bool)))


def test_the_paper_label_is_robust_fc_above_the_threshold_at_collision_free_grasps():
    r = {
        "fc": np.array([0.001, 0.003, 0.003]),
        "fc_fixed": np.array([0.001, 0.003, 0.003]),
        "cf_nominal": np.array([True, True, False]),
        "p_cf": np.array([1.0, 0.5, 0.0]),
        "pad_q": np.zeros(3),
        "pad_q_fixed": np.zeros(3),
        "robust_pad_q": np.zeros(3),
        "label_held": np.array([[1, 1], [0, 1], [0, 0]], bool),
    }
    c = candidate_labels(r, 0.002)
    score, label = c["paper (robust FC > 0.002, nominal collision)"]
    np.testing.assert_array_equal(label, [False, True, False])
    np.testing.assert_allclose(score, [0.001, 0.003, 0.0])
    np.testing.assert_allclose(c["physics (success rate of label trials)"][0], [1.0, 0.5, 0.0])
