"""The bundled default model is a trained grasp model, not a placeholder: its card records how
it was made and what it scores, and its ONNX graphs (the service's runtime, no torch) classify
whole held-out images of test objects through the real service as the stored scores say.

Scores compared here are the answers' ``raw_score`` (the network's output, whose 0.5 is its
decision threshold); ``p_success`` is that score through the card's calibration."""

from __future__ import annotations

import io
import json
import sys
from pathlib import Path

import httpx
import numpy as np
import pytest
from servers import running_service

from vgq.model_card import ModelCard

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "examples"))
from golden import GOLDEN_HELDOUT, HandScorer, balanced_accuracy, heldout_scores  # noqa: E402
from heldout import load_heldout_images  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
DEFAULT = ROOT / "models" / "fast-vgqcnn-default"
# balanced accuracy on the held-out images that separates the serving path from broken ones, just
# below what examples/golden.py measured for the bundled model: see test_service_classifies_whole_heldout_images
BOUND = json.loads(GOLDEN_HELDOUT.read_text())["balanced_accuracy"] - 0.015


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
    # the baseline scores the whole split; the model all of it or rows drawn from it (evaluate --max-n)
    assert model["n"] <= base["n"] == card.dataset["counts"]["test"]["n"]
    assert model["balanced_accuracy"] > base["balanced_accuracy"] + 0.05


@pytest.fixture(scope="module")
def heldout():
    return load_heldout_images()


@pytest.fixture(scope="module")
def served(heldout) -> np.ndarray:
    """fp32 scores of the held-out grasps from the real service: each grasp sent in a one-shot
    request with its whole image and its window centre (the npz ``center``)."""
    p = np.empty(len(heldout))
    fp32 = ("--head-precision", "fp32", "--encoder-precision", "fp32")  # the graphs golden.py ran
    with running_service(DEFAULT, *fp32) as url, httpx.Client(base_url=url) as c:
        for j in range(len(heldout)):
            body = io.BytesIO()
            np.savez(
                body,
                depth=heldout.depth[heldout.image_index[j]],
                grasps=heldout.grasps[j : j + 1],
                center=heldout.center[j].astype(np.float64),
            )
            r = c.post("/v1/score", content=body.getvalue(), headers={"content-type": "application/x-npz"})
            assert r.status_code == 200, r.text
            p[j] = r.json()["raw_score"][0]
    return p


def test_service_classifies_whole_heldout_images(card, heldout, served):
    """Balanced accuracy of the served model on whole images of the recipe's test objects.

    The bound is not the card's test balanced accuracy - 0.02: these grasps are drawn at random
    on whole images (no positivity equalisation, no uniform (phi, beta) binning as in the recipe's
    test split), where the model scores lower (fp32; examples/golden_heldout.json, measured by
    ``python examples/golden.py``). BOUND, 0.015 below that, lies between it and what a broken
    serving path scores on the same grasps (the next test). v1 on its 700 grasps: 0.784; u and
    v swapped 0.661, offsets negated 0.641, only u negated 0.758, the network's crop mirrored
    (left-right, in service/app.py) 0.754. A v2 checkpoint (1 M samples) on v2's 997 grasps:
    0.741; swapped 0.661, negated 0.594, u negated 0.653. A mirrored whole image (window and
    grasps staying put: v1 0.779) is not separable by accuracy here (the objects lie near the
    image centre, most of them near-symmetric); the per-grasp comparison below and
    tests/test_golden_scores.py catch it."""
    y = heldout.labels == 1
    assert y.sum() >= 200 and (~y).sum() >= 200 and len(np.unique(heldout.image_index)) >= 50
    ba = balanced_accuracy(heldout.labels, served)
    assert ba >= BOUND, ba
    assert card.metrics["test"]["balanced_accuracy"] - ba < 0.1  # same model, same objects: not far from the card


def test_service_scores_equal_the_stored_heldout_scores(card, served):
    """Grasp by grasp, the service scores what the hand computation of examples/golden.py
    stored for this model: any change of crop, offsets or image orientation moves them."""
    stored = json.loads(GOLDEN_HELDOUT.read_text())
    assert stored["model_version"] == card.model_version
    np.testing.assert_allclose(served, stored["p_success"], atol=1e-5, rtol=0)


def test_broken_serving_paths_fall_below_the_bound(heldout):
    """What the accuracy test would see from a serving path with u and v swapped, offsets
    negated, or u negated (the same graphs, windows cut by hand): all below BOUND. A mirrored
    image moves single scores far (> 0.2) although its accuracy barely changes."""
    h, s = heldout, HandScorer()
    terms = s.terms(np.stack([s.small_window(h.depth[i], c) for i, c in zip(h.image_index, h.center)]))
    g = h.grasps.astype(np.float64)
    rows = s.placement_rows(h.depth, g, h.image_index)  # a placement head's: read off the client's grasps

    def ba(transform):
        moved = np.concatenate([transform(g[j : j + 1], h.center[j]) for j in range(len(g))])
        return balanced_accuracy(h.labels, s.scores(terms, s.with_rows(s.poses_each(moved, h.center), rows)))

    def swap(x, c):
        x = x.copy()
        x[:, :2] = c + (x[:, :2] - c)[:, ::-1]
        return x

    def negate(x, c):
        x = x.copy()
        x[:, :2] = 2 * c - x[:, :2]
        return x

    def negate_u(x, c):
        x = x.copy()
        x[:, 0] = 2 * c[0] - x[:, 0]
        return x

    assert ba(lambda x, c: x) >= BOUND
    for broken in (swap, negate, negate_u):
        assert ba(broken) < BOUND, broken.__name__
    n = 200  # a mirrored image: single scores move far (on the first 200 grasps)
    mirrored = heldout_scores(h.depth[:, :, ::-1], h.grasps[:n], h.image_index[:n], h.center[:n])
    stored = np.array(json.loads(GOLDEN_HELDOUT.read_text())["p_success"][:n])
    assert np.abs(mirrored - stored).max() > 0.2


def test_card_is_calibrated_to_native_positivity(card):
    """The bundled card carries a Platt calibration fitted on unseen objects at their native
    positivity (``python -m export.recalibrate``), with its expected calibration error on other
    unseen objects at most 0.03 (issue 11's goal; measured 0.008, raw 0.163)."""
    cal = card.calibration
    assert cal and card.calibrator() is not None
    assert 0.01 < cal["target_positivity"] < 0.2
    assert cal["test"]["ece_calibrated"] <= 0.03 < cal["test"]["ece_raw"]


def test_service_p_success_is_the_calibrated_raw_score(card):
    """The service's p_success is the card's calibrator applied to its raw score."""
    depth = np.load(ROOT / "examples" / "depth_example.npy")
    grasps = np.array(json.loads((ROOT / "examples" / "grasps_example.json").read_text())["grasps"])
    buf = io.BytesIO()
    np.save(buf, depth.astype(np.float32))
    with running_service(DEFAULT) as url:
        up = httpx.post(f"{url}/v1/images", content=buf.getvalue(), headers={"content-type": "application/x-npy"})
        r = httpx.post(f"{url}/v1/images/{up.json()['image_id']}/scores", json={"grasps": grasps.tolist()}).json()
    assert r["calibrated"] is True
    np.testing.assert_allclose(r["p_success"], card.calibrator().apply(np.asarray(r["raw_score"])), atol=1e-6)


def test_the_training_ranges_the_flags_use_come_from_the_card(card):
    """One z range and one camera tilt range for the service's and the planner's flags: the
    card's recorded training grasps and dataset cameras, else its normalisation and datagen's
    default cameras."""
    import dataclasses
    from math import radians

    (lo, hi), source = card.z_range()
    assert (lo, hi) == tuple(card.dataset["z_range"]) and "dataset.z_range" in source
    assert card.tilt_range() == pytest.approx((0.0, radians(70.0)))
    bare = dataclasses.replace(card, dataset={})
    (lo, hi), source = bare.z_range()
    i = list(card.normalization.pose_columns).index("z")
    assert lo < card.normalization.pose_mean[i] < hi and "normalization" in source
    assert bare.tilt_range() == pytest.approx((0.0, radians(70.0)))
