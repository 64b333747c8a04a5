"""Run statistics on fixed inputs, against values computed by hand and by scipy."""

import numpy as np
import pytest
from scipy import stats

from sera_study.results.stats import (
    benjamini_hochberg,
    benjamini_yekutieli,
    decision_p_value,
    holm_adjusted,
    improvement_percent,
    iqm,
    min_max_normalized,
    normalized_auc,
    raw_permutation_p_value,
    runs_for_power,
    sample_std,
    smallest_p_value,
    studentized_permutation_p_value,
    welch_interval,
    welch_p_value,
    welch_power,
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
    # Welch-Satterthwaite df = (5/12 + 2)^2 / ((5/12)^2 / 3 + 2^2 / 4) = 5.52
    t, df = -3.5 / (5 / 12 + 2) ** 0.5, (5 / 12 + 2) ** 2 / ((5 / 12) ** 2 / 3 + 1)
    assert welch_p_value(a, b) == pytest.approx(2 * stats.t.sf(abs(t), df))
    assert welch_p_value([1.0], b) is None


def test_welch_power_matches_a_simulation_and_the_declared_figures():
    # 40,000 draws of 8 against 8 normal runs, SDs 1 and 1.5, a true difference of 1: the share Welch's test rejects
    rng = np.random.default_rng(0)
    a, b = rng.normal(1.0, 1.0, (40_000, 8)), rng.normal(0.0, 1.5, (40_000, 8))
    rejected = stats.ttest_ind(a, b, axis=1, equal_var=False).pvalue < 0.05
    assert welch_power(1.0, 1.0, 1.5, 8, 8) == pytest.approx(rejected.mean(), abs=0.01)
    # No difference: the test's size
    assert welch_power(0.0, 1.0, 1.5, 8, 8) == pytest.approx(0.05, abs=0.002)
    # results/claims.yml's figures: HalfCheetah 6x1 (seen at seeds 0-9, and the paper's) and Simple Spread (half the
    # paper's standardized effect, and all of it)
    assert welch_power(248, 478, 307, 20, 20) == pytest.approx(0.47, abs=0.005) and runs_for_power(248, 478, 307) == 43
    assert welch_power(689, 711, 721, 20, 20) == pytest.approx(0.84, abs=0.005) and runs_for_power(689, 711, 721) == 18
    assert welch_power(2, 2, 2.3, 20, 20) == pytest.approx(0.82, abs=0.005) and runs_for_power(2, 2, 2.3) == 20
    assert welch_power(2, 2, 2.3, 19, 19) < 0.8 and runs_for_power(4, 2, 2.3) == 6


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

    from sera_study.results.stats import iqm_interval, performance_profile, probability_of_improvement

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


def test_welch_interval_matches_scipy_and_a_hand_computation():
    a, b = [1.0, 2.0, 3.0, 4.0], [2.0, 4.0, 6.0, 8.0, 10.0]
    difference, low, high = welch_interval(a, b)
    expected = stats.ttest_ind(a, b, equal_var=False).confidence_interval(0.95)
    assert (low, high) == pytest.approx((expected.low, expected.high))
    # By hand: -3.5 +- t(0.975, df 5.52) * sqrt(5/12 + 2) = 2.4993 * 1.5546
    half = stats.t.ppf(0.975, (5 / 12 + 2) ** 2 / ((5 / 12) ** 2 / 3 + 2**2 / 4)) * np.sqrt(5 / 12 + 2)
    assert difference == -3.5 and high - difference == pytest.approx(half) and half == pytest.approx(3.885, abs=1e-3)
    assert welch_interval([1.0, 1.0], [0.0, 0.0]) == (1.0, 1.0, 1.0)
    with pytest.raises(ValueError, match="two values a side"):
        welch_interval([1.0], [1.0, 2.0])


def test_studentized_permutation_p_value_is_exact_and_matches_scipy():
    a, b = [1.0, 2.0, 3.0, 4.0, 5.5], [3.0, 4.0, 5.0, 6.0, 7.0, 9.0]
    expected = stats.permutation_test(
        (np.array(a), np.array(b)),
        lambda x, y: abs(stats.ttest_ind(x, y, equal_var=False).statistic),
        permutation_type="independent",
        n_resamples=np.inf,
        alternative="greater",
    ).pvalue
    assert studentized_permutation_p_value(a, b) == pytest.approx(expected)
    # Wholly separated sides of 5: only the observed split and its mirror are as far: 2 of C(10, 5) = 252
    assert studentized_permutation_p_value([10.0, 11, 12, 13, 14], [0.0, 1, 2, 3, 4]) == pytest.approx(2 / 252)
    # Constant sides: the split that separates them is infinitely far, as is its mirror
    assert studentized_permutation_p_value([1.0, 1.0], [0.0, 0.0]) == pytest.approx(2 / 6)
    # Above the exact limit: seeded random splits with the observed one counted in, near the exact value
    many = studentized_permutation_p_value(a, b, permutations=100)
    assert many == studentized_permutation_p_value(a, b, permutations=100) and abs(many - expected) < 0.15
    assert 0 < many <= 1
    with pytest.raises(ValueError, match="two runs a side"):
        studentized_permutation_p_value([1.0], [1.0, 2.0])


def test_the_decision_p_is_the_larger_of_the_permutation_and_welch_p():
    a, b = [1.0, 2.0, 3.0, 4.0, 5.5], [3.0, 4.0, 5.0, 6.0, 7.0, 9.0]
    decision, permutation, welch = decision_p_value(a, b)
    assert welch == pytest.approx(stats.ttest_ind(a, b, equal_var=False).pvalue)
    assert permutation == studentized_permutation_p_value(a, b) and decision == max(permutation, welch)
    # Two constant sides: no difference at all, or a certain one (as far as the permutation test can say)
    assert decision_p_value([1.0, 1.0], [1.0, 1.0])[0] == 1.0
    assert decision_p_value([2.0, 2.0, 2.0], [1.0, 1.0, 1.0]) == (pytest.approx(0.1), pytest.approx(0.1), 0.0)


def test_the_smallest_p_at_each_size():
    # 3 against 3: 2 of 20 splits, never below 0.05; 4 against 5: 1 of 126, below Holm's 0.05 / 6; random splits
    assert smallest_p_value(3, 3) == pytest.approx(0.1)
    assert smallest_p_value(4, 5) == pytest.approx(1 / 126) and smallest_p_value(4, 5) < 0.05 / 6
    assert smallest_p_value(4, 4) == pytest.approx(2 / 70) and smallest_p_value(4, 4) > 0.05 / 6
    assert smallest_p_value(20, 20) == pytest.approx(1 / 200_001)


@pytest.mark.parametrize(
    ("distribution", "larger_spread"),
    [
        ("normal", "smaller arm"),
        ("normal", "larger arm"),
        ("skewed", "larger arm"),
        # No test of the means holds its size at 5 runs of skewed data with the larger spread: Welch's t alone rejects
        # 6-12% of the time there (docs/results/index.md, "How a claim is decided")
        pytest.param("skewed", "smaller arm", marks=pytest.mark.xfail(strict=True, reason="skewed, 5 runs, larger spread")),
    ],
)
def test_the_decision_holds_its_size_at_10_against_5_with_spreads_apart(distribution, larger_spread):
    # Equal means, standard deviations 2.5x apart; skewed: a gamma of shape 4 (skewness 1), centred. The raw
    # difference of means permuted rejects 15% of the time when the smaller arm has the larger spread (normal data),
    # the studentized permutation alone 7-9%
    rng = np.random.default_rng(0)
    sizes, spreads = (10, 5), ((1.0, 2.5) if larger_spread == "smaller arm" else (2.5, 1.0))

    def draw(size: int, spread: float) -> np.ndarray:
        if distribution == "normal":
            return rng.normal(0.0, spread, size)
        return (rng.gamma(4.0, 1.0, size) - 4.0) / 2.0 * spread

    trials = 2000
    rejected = sum(decision_p_value(draw(sizes[0], spreads[0]), draw(sizes[1], spreads[1]))[0] < 0.05 for _ in range(trials))
    # At most 5.5%, but for the simulation's own noise (one-sided 1% above 5.5%: 0.055 + 2.33 standard errors)
    assert rejected / trials <= 0.055 + 2.33 * np.sqrt(0.055 * 0.945 / trials)


def test_benjamini_hochberg_by_hand():
    # Sorted 0.01, 0.03, 0.04, 0.2 times 4/1, 4/2, 4/3, 4/4: 0.04, 0.06, 0.0533, 0.2 -> from the top 0.2, 0.0533,
    # 0.0533, 0.04
    assert benjamini_hochberg([0.01, 0.04, 0.03, 0.2]) == pytest.approx([0.04, 0.16 / 3, 0.16 / 3, 0.2])
    assert benjamini_hochberg([0.5]) == [0.5] and benjamini_hochberg([]) == []


def test_benjamini_yekutieli_by_hand():
    # BH's q-values times 1 + 1/2 + 1/3 + 1/4 = 25/12, capped at 1
    expected = [0.04 * 25 / 12, 0.16 / 3 * 25 / 12, 0.16 / 3 * 25 / 12, 1.0]
    assert benjamini_yekutieli([0.01, 0.04, 0.03, 0.5]) == pytest.approx(expected)
    assert benjamini_yekutieli([0.02]) == [0.02] and benjamini_yekutieli([]) == []


def test_the_first_declared_raw_permutation_test_by_hand():
    # 0, 0 against 1, 1: of the 6 splits two put both ones on a side (difference 1, as observed), four mix them (0)
    assert raw_permutation_p_value([0, 0], [1, 1]) == pytest.approx(1 / 3)
    # Every arm run above every baseline run: only the observed split and its mirror are as extreme, 2 of 252, where
    # Welch's test, whose interval the outlier's spread widens, is far from 0.05
    arm, baseline = [10, 11, 12, 13, 200], [0, 1, 2, 3, 4]
    assert raw_permutation_p_value(arm, baseline) == pytest.approx(2 / 252)
    assert welch_p_value(arm, baseline) > 0.25


def test_holm_by_hand():
    # Sorted 0.005, 0.01, 0.03, 0.04 times 4, 3, 2, 1: 0.02, 0.03, 0.06, 0.04 -> monotone 0.02, 0.03, 0.06, 0.06
    assert holm_adjusted([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    assert holm_adjusted([0.5, 0.9]) == pytest.approx([1.0, 1.0])
    assert holm_adjusted([]) == []


@pytest.mark.parametrize("shape", ["normal", "skewed"])
@pytest.mark.parametrize("spread", [1.0, 2.5])
def test_welch_interval_covers_at_five_against_five(shape, spread):
    """
    Coverage of the 95% Welch interval of a difference of means at 5 runs a side, 4,000 simulated comparisons:
    normal data, and gamma data of shape 4 (skewness 1), with equal standard deviations or one side's 2.5 times the
    other's. Measured here: 95.4% and 95.0% (normal), 96.2% and 94.4% (skewed); a percentile bootstrap of the same difference
    covers 86-88%. Heavier skew lowers it (exponential data, 2.5x: 91.6% in 20,000 comparisons).
    """
    rng = np.random.default_rng(0)
    draws = 4000
    if shape == "normal":
        x, y, truth = rng.normal(0, spread, (draws, 5)), rng.normal(0, 1, (draws, 5)), 0.0
    else:
        x, y = spread * rng.gamma(4, 1, (draws, 5)), rng.gamma(4, 1, (draws, 5))
        truth = (spread - 1) * 4.0
    covered = 0
    for sample, baseline in zip(x, y, strict=True):
        _, low, high = welch_interval(sample, baseline)
        covered += low <= truth <= high
    assert covered / draws >= 0.93
