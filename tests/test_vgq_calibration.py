"""vgq.calibration: the raw -> calibrated map, the prior shift and the calibration error;
export.calibrate: fits recover known parameters from synthetic logits."""

import numpy as np
import pytest

from export.calibrate import CalibrationError, fit_platt, fit_temperature
from vgq.calibration import Calibration, expected_calibration_error, logit, prior_weights, sigmoid


def _labels(rng, p):
    return (rng.random(len(p)) < p).astype(np.uint8)


def test_platt_fit_recovers_known_slope_and_intercept():
    rng = np.random.default_rng(0)
    z = rng.normal(0.0, 2.0, 200_000)
    y = _labels(rng, sigmoid(0.6 * z - 1.2))  # the truth: P(success) = sigmoid(0.6 logit(p_raw) - 1.2)
    cal = fit_platt(sigmoid(z), y)
    assert cal.slope == pytest.approx(0.6, abs=0.01) and cal.intercept == pytest.approx(-1.2, abs=0.02)
    assert cal.target_positivity == cal.fit_positivity == pytest.approx(y.mean())


def test_temperature_fit_recovers_known_temperature_with_the_training_prior():
    rng = np.random.default_rng(1)
    z = rng.normal(0.0, 3.0, 400_000)
    # a net trained at an effective 50 % (balanced loss), over-confident by T = 2.5 ...
    y = _labels(rng, sigmoid(z / 2.5))
    # ... scored on a split whose positives were resampled to 20 % positivity
    keep = (y == 0) | (rng.random(len(y)) < 0.25 * (1 - y.mean()) / y.mean())
    cal = fit_temperature(sigmoid(z[keep]), y[keep], model_positivity=0.5)
    assert cal.fit_positivity == pytest.approx(0.2, abs=0.005)
    assert cal.temperature == pytest.approx(2.5, rel=0.03)
    np.testing.assert_allclose(cal.apply(sigmoid(z)), sigmoid(z / 2.5 + logit(cal.fit_positivity)), atol=0.01)


def test_prior_shift_moves_probabilities_towards_the_target_positivity():
    cal = Calibration("platt", 1.0, 0.0, fit_positivity=0.19, target_positivity=0.047)
    p = np.array([0.05, 0.19, 0.5, 0.9])
    low = cal.apply(p)
    assert np.all(low < p) and np.all(np.diff(low) > 0)  # lower, same order
    # Bayes: odds scale by (t / (1 - t)) / (f / (1 - f))
    odds = (p / (1 - p)) * (0.047 / 0.953) / (0.19 / 0.81)
    np.testing.assert_allclose(low, odds / (1 + odds), rtol=1e-9)
    assert np.all(cal.at_positivity(0.5).apply(p) > p)
    np.testing.assert_allclose(cal.at_positivity(0.19).apply(p), p, rtol=1e-9)  # no shift: identity


def test_prior_shift_matches_a_resampled_population():
    """Calibrated at 19 % and shifted to 4.7 %, probabilities match the outcome rates of the
    same population with negatives added back to 4.7 % (label shift)."""
    rng = np.random.default_rng(2)
    n_pos, n_neg = 40_000, 800_000
    s = np.concatenate([rng.normal(1.0, 1.0, n_pos), rng.normal(-1.0, 1.0, n_neg)])  # a score per grasp
    y = np.concatenate([np.ones(n_pos), np.zeros(n_neg)]).astype(np.uint8)
    native = n_pos / (n_pos + n_neg)
    keep = (y == 1) | (rng.random(len(y)) < n_pos * (0.81 / 0.19) / n_neg)  # resample negatives to 19 %
    fit = fit_platt(sigmoid(s[keep]), y[keep])
    assert fit.fit_positivity == pytest.approx(0.19, abs=0.005)
    shifted = fit.at_positivity(native)
    assert expected_calibration_error(shifted.apply(sigmoid(s)), y) < 0.005
    assert expected_calibration_error(fit.apply(sigmoid(s)), y) > 0.05  # unshifted: far too optimistic


def test_ece_of_a_perfectly_calibrated_set_is_about_zero_and_of_a_biased_one_is_the_bias():
    rng = np.random.default_rng(3)
    p = rng.random(500_000)
    y = _labels(rng, p)
    assert expected_calibration_error(p, y) < 0.005
    assert expected_calibration_error(np.clip(p + 0.1, 0, 1), y) == pytest.approx(0.1, abs=0.02)


def test_prior_weights_turn_a_split_into_the_target_positivity():
    y = np.array([1] * 20 + [0] * 80)
    w = prior_weights(y, 0.05)
    assert (w * y).sum() / w.sum() == pytest.approx(0.05) and w.mean() == pytest.approx(1.0)
    with pytest.raises(ValueError, match="both classes"):
        prior_weights(np.ones(5), 0.05)


def test_calibration_validates_itself_and_round_trips():
    cal = Calibration("platt", 0.8, -0.3, 0.19, 0.047)
    assert Calibration.from_dict({**cal.to_dict(), "test": {"ece_raw": 0.1}}) == cal
    for bad in (dict(slope=0.0), dict(target_positivity=1.0), dict(method="isotonic"), dict(intercept=float("nan"))):
        with pytest.raises(ValueError):
            Calibration(**{**cal.to_dict(), **bad})
    with pytest.raises(ValueError, match="not a calibration"):
        Calibration.from_dict({"method": "platt"})


def test_fit_refuses_one_class_and_saturated_probabilities_stay_finite():
    with pytest.raises(CalibrationError, match="both classes"):
        fit_platt(np.full(10, 0.3), np.zeros(10))
    cal = fit_platt(np.array([0.0, 0.0, 1.0, 1.0, 0.2, 0.9]), np.array([0, 0, 1, 1, 0, 1]))  # separable
    assert np.isfinite(cal.slope) and np.all(np.isfinite(cal.apply(np.array([0.0, 0.5, 1.0]))))
