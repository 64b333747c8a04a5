"""Run statistics on fixed inputs, against values computed by hand and by scipy."""

import numpy as np
import pytest
from scipy import stats

from sb3_sera.experiments.stats import (
    improvement_percent,
    iqm,
    min_max_normalized,
    normalized_auc,
    sample_std,
    welch_p_value,
)


def test_normalized_auc_by_hand():
    # Trapezoids over [0, 10] and [10, 30]: (0 + 10) / 2 * 10 + (10 + 30) / 2 * 20 = 450, over 30 steps
    assert normalized_auc([0, 10, 30], [0.0, 10.0, 30.0]) == pytest.approx(15.0)
    assert normalized_auc([5], [-3.0]) == -3.0
    with pytest.raises(ValueError, match="one return per timestep"):
        normalized_auc([0, 1], [1.0])


def test_welch_p_value_matches_scipy_and_a_hand_computation():
    a, b = [1.0, 2.0, 3.0, 4.0], [2.0, 4.0, 6.0, 8.0, 10.0]
    expected = stats.ttest_ind(a, b, equal_var=False).pvalue
    assert welch_p_value(a, b) == pytest.approx(expected)
    # By hand: means 2.5 and 6, variances 5/3 and 10, t = -3.5 / sqrt(5/12 + 2) = -2.2514,
    # Welch-Satterthwaite df = (5/12 + 2)^2 / ((5/12)^2 / 3 + 2^2 / 4) = 5.47
    t, df = -3.5 / (5 / 12 + 2) ** 0.5, (5 / 12 + 2) ** 2 / ((5 / 12) ** 2 / 3 + 1)
    assert welch_p_value(a, b) == pytest.approx(2 * stats.t.sf(abs(t), df))
    assert welch_p_value([1.0], b) is None


def test_improvement_percent():
    assert improvement_percent(5520, 4500) == pytest.approx(22.666, abs=1e-3)
    # Negative returns: -27 improves on -31 by 4 / 31
    assert improvement_percent(-27, -31) == pytest.approx(400 / 31)
    with pytest.raises(ValueError, match="baseline of 0"):
        improvement_percent(1.0, 0.0)


def test_sample_std_by_hand():
    # mean 2, squared deviations 1 + 0 + 1 = 2, over n - 1 = 2: std 1 (the population std would be 0.816)
    assert sample_std([1.0, 2.0, 3.0]) == pytest.approx(1.0)
    assert np.isnan(sample_std([4.0]))


def test_iqm_by_hand():
    # 8 runs on one task: the middle half is 3, 4, 5, 6 -> 4.5 (the mean, 12.375, is pulled up by 50 and 30)
    scores = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 30.0, 50.0])[:, None]
    assert iqm(scores)[0] == pytest.approx(4.5)


def test_min_max_normalized():
    np.testing.assert_allclose(min_max_normalized(np.array([-10.0, 0.0, 10.0]), -10.0, 10.0), [0.0, 0.5, 1.0])
    np.testing.assert_allclose(min_max_normalized(np.array([3.0]), 3.0, 3.0), [0.0])


def _rliable(func, *args, **kwargs):
    """rliable's bootstrap, which draws from numpy's global generator."""
    np.random.seed(0)
    return func(*args, **kwargs)


def test_vectorized_bootstraps_agree_with_rliable():
    from rliable import library as rly
    from rliable import metrics

    from sb3_sera.experiments.stats import iqm_interval, performance_profile, probability_of_improvement

    rng = np.random.default_rng(1)
    reps = 4000
    # IQM over runs and tasks, and per point of a curve: the same bounds up to the bootstraps' own sampling error
    for scores in (rng.normal(size=(10, 3)), rng.normal(size=(6, 1, 5))):
        point, low, high = iqm_interval(scores, reps=reps)
        func = (
            (lambda s: np.array([metrics.aggregate_iqm(s[..., i]) for i in range(s.shape[-1])]))
            if scores.ndim == 3
            else (lambda s: np.array([metrics.aggregate_iqm(s)]))
        )
        points, intervals = _rliable(rly.get_interval_estimates, {"x": scores}, func, reps=reps)
        np.testing.assert_allclose(point, points["x"])
        spread = np.ptp(scores)
        np.testing.assert_allclose(low, intervals["x"][0], atol=0.05 * spread)
        np.testing.assert_allclose(high, intervals["x"][1], atol=0.05 * spread)
    # P(X > Y), X's and Y's runs resampled apart
    x, y = rng.normal(0.5, 1.0, size=(8, 2)), rng.normal(size=(6, 2))
    point, low, high = probability_of_improvement(x, y, reps=reps)
    points, intervals = _rliable(rly.get_interval_estimates, {"p": (x, y)}, metrics.probability_of_improvement, reps=reps)
    assert point == pytest.approx(float(points["p"]))
    np.testing.assert_allclose([low, high], np.ravel(intervals["p"]), atol=0.03)
    # Performance profiles: fraction of runs above each threshold, with bands
    thresholds = np.linspace(-2, 2, 9)
    profiles, bands = performance_profile({"x": x}, thresholds, reps=reps)
    expected_profiles, expected_bands = _rliable(rly.create_performance_profile, {"x": x}, thresholds, reps=reps)
    np.testing.assert_allclose(profiles["x"], expected_profiles["x"])
    np.testing.assert_allclose(bands["x"], expected_bands["x"], atol=0.07)
