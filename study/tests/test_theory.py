"""
The TD-target estimator study (sera_study.theory) against hand-checkable values, and the paper's
Lemma 4.1 and Propositions 4.2-4.3 on synthetic ensembles, measured through the package's aggregation code.

Sampling tolerances are four standard errors (or a stated margin far above them), so a test fails on a wrong
formula or estimator, not on noise; every draw uses a fixed seed.
"""

import itertools
import math

import pytest
import torch as th

from sera_study import theory as te

DRAWS = 100_000

# Expected minimum of K independent standard normals (minus the expected maximum): K = 2: 1 / sqrt(pi);
# K = 3: 3 / (2 sqrt(pi)); K = 5: 1.16296 (tabulated, and checked by numerical integration of K x phi(x) (1 - Phi(x))^(K-1))
EXPECTED_MIN = {2: -1.0 / math.sqrt(math.pi), 3: -3.0 / (2.0 * math.sqrt(math.pi)), 5: -1.162964}
# Lower middle order statistic of K standard normals (torch.median): K = 3 variance 0.448671; K = 4 mean -0.297011
MEDIAN3_VARIANCE = 0.448671
LOWER_MEDIAN4_MEAN = -0.297011


def _within(moment: float, expected: float, standard_error: float, n_se: float = 4.0) -> bool:
    return abs(moment - expected) <= n_se * standard_error


def test_geometric_sigmas():
    assert te.geometric_sigmas(3, 100.0).tolist() == pytest.approx([0.1, 1.0, 10.0])
    assert te.geometric_sigmas(4, 1.0, scale=2.0).tolist() == pytest.approx([2.0] * 4)
    sigmas = te.geometric_sigmas(5, 10.0, scale=3.0)
    assert (sigmas[-1] / sigmas[0]).item() == pytest.approx(10.0)
    assert sigmas.log().mean().exp().item() == pytest.approx(3.0)
    with pytest.raises(ValueError):
        te.geometric_sigmas(1, 2.0)


def test_samples_have_the_requested_covariance():
    sigmas = th.tensor([0.5, 1.0, 2.0], dtype=th.float64)
    q_values = te.sample_critic_values(sigmas, DRAWS, seed=1, correlation=0.5, true_value=3.0).to(th.float64)
    assert q_values.dtype == th.float64
    assert q_values.mean(dim=0).tolist() == pytest.approx([3.0] * 3, abs=0.02)
    expected = te.error_covariance(sigmas, 0.5)  # e.g. Cov(eps_0, eps_2) = 0.5 * 2 * 0.5 = 0.5
    assert expected[0, 2].item() == pytest.approx(0.5)
    assert th.allclose(th.cov(q_values.T), expected, rtol=0.03, atol=0.01)


def test_mean_variance_is_sigma_squared_over_k():
    # Equal sigma = 2, K = 4 independent critics: Var(mean) = 4 / 4 = 1, unbiased
    result = te.estimator_moments(te.geometric_sigmas(4, 1.0, scale=2.0), DRAWS, seed=2)["mean"]
    assert _within(result.variance, 1.0, result.variance_se)
    assert _within(result.bias, 0.0, result.bias_se)
    # Equal correlation rho: Var = sigma^2 (1 + (K - 1) rho) / K = 4 * 2.5 / 4 = 2.5
    correlated = te.estimator_moments(te.geometric_sigmas(4, 1.0, scale=2.0), DRAWS, seed=2, correlation=0.5)["mean"]
    assert _within(correlated.variance, 2.5, correlated.variance_se)


@pytest.mark.parametrize("n_critics", [2, 3, 5])
def test_min_bias_is_the_expected_minimum(n_critics):
    sigma = 1.5
    result = te.estimator_moments(te.geometric_sigmas(n_critics, 1.0, scale=sigma), DRAWS, seed=3)["min"]
    assert result.bias < 0
    assert _within(result.bias, EXPECTED_MIN[n_critics] * sigma, result.bias_se)


def test_median_is_the_lower_middle_order_statistic():
    odd = te.estimator_moments(te.geometric_sigmas(3, 1.0), DRAWS, seed=4)
    assert _within(odd["median"].variance, MEDIAN3_VARIANCE, odd["median"].variance_se)
    assert _within(odd["median"].bias, 0.0, odd["median"].bias_se)
    # Even K: torch.median's lower middle value is biased low, and SERA (anchored on it) inherits part of it
    even = te.estimator_moments(te.geometric_sigmas(4, 1.0), DRAWS, seed=4)
    assert _within(even["median"].bias, LOWER_MEDIAN4_MEAN, even["median"].bias_se)
    assert LOWER_MEDIAN4_MEAN < even["SERA"].bias < -0.1


def test_sera_with_two_critics_is_the_mean():
    # K = 2: the median is the lower critic, the softmax puts weight 1 on the other one, alpha = 0.5 gives the mean
    sigmas = te.geometric_sigmas(2, 10.0)
    q_values = te.sample_critic_values(sigmas, 1000, seed=5)
    sera = te.aggregate(q_values, te.ESTIMATORS[te.ESTIMATOR_NAMES.index("SERA")])
    assert th.allclose(sera, q_values.mean(dim=1), atol=1e-6)
    # SERA-Median does not: the median critic (deviation 0) gets the larger softmax weight, so it leans low
    result = te.estimator_moments(sigmas, DRAWS, seed=5)
    assert result["SERA-Median"].bias < result["SERA"].bias - 10 * result["SERA"].bias_se


@pytest.mark.parametrize("n_critics", [3, 5, 10])
def test_proposition_4_3_variance_below_a_single_critic(n_critics):
    # The paper's assumptions: independent, zero-mean errors of equal variance sigma^2, 0 < alpha < 1
    sigma = 0.8
    sigmas = te.geometric_sigmas(n_critics, 1.0, scale=sigma)
    for alpha in (0.2, 0.5, 0.8):
        result = te.estimator_moments(sigmas, DRAWS, seed=6, alpha=alpha)
        sera = result["SERA"]
        assert sera.variance < 0.6 * sigma**2  # a single critic's variance is sigma^2
        if n_critics % 2:  # odd K and symmetric noise: unbiased (SERA is odd and translation-equivariant)
            assert _within(sera.bias, 0.0, sera.bias_se)
        else:  # even K: anchored on the lower middle value, so biased low (not covered by the proposition)
            assert sera.bias < -10 * sera.bias_se
        # The paper's remark: with equal, independent noise the mean (sigma^2 / K) is the better average
        assert result["mean"].variance < sera.variance


def test_proposition_4_3_proof_formula_is_not_the_variance():
    # The proof holds the weights fixed ("conditioned on the aggregation weights"), but they are functions of the
    # errors: E[sigma^2 sum w~_i^2] is neither the variance nor a bound on it
    small = te.sera_diagnostics(te.geometric_sigmas(3, 1.0), DRAWS, seed=7)
    assert small.formula_variance < 0.95 * small.measured_variance
    large = te.sera_diagnostics(te.geometric_sigmas(10, 1.0), DRAWS, seed=7)
    assert large.formula_variance > 1.5 * large.measured_variance


def test_heterogeneous_noise_against_the_mean_and_single_critics():
    # The paper's comparison with mean aggregation (not a proposition): with uneven critic noise SERA should beat
    # the mean. It does once the spread is large enough, not for nearly equal noise
    strong = te.estimator_moments(te.geometric_sigmas(5, 30.0), DRAWS, seed=8)
    assert strong["SERA"].variance < 0.25 * strong["mean"].variance
    mild = te.estimator_moments(te.geometric_sigmas(5, 2.0), DRAWS, seed=8)
    assert mild["mean"].variance < 0.9 * mild["SERA"].variance
    # Below the average and the worst single critic, and below the median, but not below the best single critic
    references = te.reference_variances(te.geometric_sigmas(5, 30.0))
    assert strong["SERA"].variance < strong["median"].variance
    assert strong["SERA"].variance < 0.1 * references["average critic"]
    assert strong["SERA"].variance > 3 * references["best critic"]


def test_lemma_4_1_and_proposition_4_2_on_every_draw():
    diagnostics = te.sera_diagnostics(te.geometric_sigmas(5, 10.0), DRAWS, seed=9)
    # Lemma 4.1, sample-wise: d_i < d_j => w_i > w_j for every non-median pair of every draw
    assert diagnostics.ordered_pairs == 6 * DRAWS  # C(4, 2) pairs per draw, no ties in float32 here
    assert diagnostics.ordering_violations == 0
    assert diagnostics.ordering_ties == 0
    # Proposition 4.2: every target inside [min_i q_i, max_i q_i]
    assert diagnostics.bound_violations == 0
    # Batch level: a critic's total share w~ decreases with its noise; its softmax weight alone does not, since the
    # least noisy critic is the anchor most often and then has w = 0
    effective = diagnostics.mean_effective_weight.tolist()
    assert all(a > b + 0.005 for a, b in itertools.pairwise(effective))
    assert diagnostics.median_frequency[0] > diagnostics.median_frequency[1] > diagnostics.median_frequency[4]
    assert diagnostics.mean_weight[0] < diagnostics.mean_weight[1] - 0.005
    assert th.allclose(diagnostics.mean_effective_weight.sum(), th.tensor(1.0, dtype=th.float64))


def test_tables_and_figure(tmp_path):
    sweeps = {"spread": te.SWEEPS["spread"][:2], "scale": te.SWEEPS["scale"][:2]}
    rows = te.run(2000, seed=0, sweeps=sweeps)
    assert [row.axis_value for row in rows] == [1.0, 2.0, 0.01, 0.1]
    # The scale sweep reports bias in units of the scale: min's bias for K = 5 is about -1.9 scale at spread 10
    assert rows[2].bias("min") == pytest.approx(rows[2].moments["min"].bias / 0.01)
    tables = te.markdown_tables(rows, 2000, 0)
    assert "### Sweep `spread`" in tables and "### Sweep `scale`" in tables
    te.write_csv(rows, tmp_path / "table.csv")
    lines = (tmp_path / "table.csv").read_text().splitlines()
    assert len(lines) == 1 + len(rows) * len(te.ESTIMATORS)
    te.plot(rows, tmp_path / "figure.png")
    assert (tmp_path / "figure.png").stat().st_size > 10_000
