"""The aggregation rules of SERA against hand-computed values (SPEC section 1, steps 2-4, 7, 8)."""

import itertools
import math
from typing import get_args

import pytest
import torch as th

from sb3_sera.common.correlation import correlation_matrix
from sb3_sera.sera.aggregation import (
    ACTOR_AGGREGATIONS,
    TARGET_AGGREGATIONS,
    ActorAggregation,
    SERAOptions,
    TargetAggregation,
    aggregate_target,
    critic_correlation,
    ensemble_disagreement,
    median_anchor,
    selected_critic,
    sera_aggregate,
    td_error_correlation,
)


def test_median_anchor_odd_and_even():
    values, index = median_anchor(th.tensor([[4.0, 1.0, 2.0], [1.0, 3.0, 2.0]]))
    assert values.tolist() == [2.0, 2.0]
    assert index.tolist() == [2, 2]
    # Even K: the lower middle value, so the anchor is one real critic
    values, index = median_anchor(th.tensor([[10.0, 1.0, 3.0, 2.0]]))
    assert values.tolist() == [2.0]
    assert index.tolist() == [3]


def test_sera_weights_and_value_by_hand():
    # q = (1, 2, 4): median 2 (index 1), deviations (1, 0, 2); softmax over critics 0 and 2 with tau = 1
    result = sera_aggregate(th.tensor([[1.0, 2.0, 4.0]]), alpha=0.5, temperature=1.0)
    w0 = 1.0 / (1.0 + math.exp(-1.0))  # e^-1 / (e^-1 + e^-2) = 0.7310586
    assert result.median_index.tolist() == [1]
    assert result.weights[0].tolist() == pytest.approx([w0, 0.0, 1.0 - w0], abs=1e-6)
    rest = w0 * 1.0 + (1.0 - w0) * 4.0  # 1.8068243
    assert result.value.item() == pytest.approx(0.5 * 2.0 + 0.5 * rest, abs=1e-6)
    assert result.value.item() == pytest.approx(1.9034121, abs=1e-6)


def test_alpha_extremes():
    q = th.tensor([[1.0, 2.0, 4.0]])
    assert sera_aggregate(q, alpha=1.0).value.item() == pytest.approx(2.0)
    rest = (math.exp(-1) * 1 + math.exp(-2) * 4) / (math.exp(-1) + math.exp(-2))
    assert sera_aggregate(q, alpha=0.0).value.item() == pytest.approx(rest, abs=1e-6)


def test_temperature_sharpens_weights():
    q = th.tensor([[1.0, 2.0, 4.0]])
    cold = sera_aggregate(q, temperature=0.01).weights[0]
    hot = sera_aggregate(q, temperature=100.0).weights[0]
    assert cold.tolist() == pytest.approx([1.0, 0.0, 0.0], abs=1e-6)
    assert hot.tolist() == pytest.approx([0.5, 0.0, 0.5], abs=1e-2)


def test_even_number_of_critics():
    # q = (1, 2, 3, 10): median 2 (index 1), deviations (1, 0, 1, 8)
    result = sera_aggregate(th.tensor([[1.0, 2.0, 3.0, 10.0]]), alpha=0.5, temperature=1.0)
    z = 2 * math.exp(-1) + math.exp(-8)
    expected = [math.exp(-1) / z, 0.0, math.exp(-1) / z, math.exp(-8) / z]
    assert result.weights[0].tolist() == pytest.approx(expected, abs=1e-6)
    rest = (math.exp(-1) * (1 + 3) + math.exp(-8) * 10) / z
    assert result.value.item() == pytest.approx(0.5 * 2 + 0.5 * rest, abs=1e-5)


def test_ties_exclude_only_the_median_index():
    result = sera_aggregate(th.tensor([[3.0, 3.0, 3.0]]))
    m = result.median_index.item()
    weights = result.weights[0]
    assert weights[m].item() == 0.0
    assert [weights[i].item() for i in range(3) if i != m] == pytest.approx([0.5, 0.5])
    assert result.value.item() == pytest.approx(3.0)
    # A tie between the median and another critic: the twin (deviation 0) keeps a weight of its own
    result = sera_aggregate(th.tensor([[1.0, 5.0, 5.0]]), alpha=0.0)
    m = result.median_index.item()
    twin = 3 - m  # the other index holding 5
    assert m in (1, 2)
    assert result.weights[0, twin].item() == pytest.approx(1.0 / (1.0 + math.exp(-4.0)), abs=1e-6)


def test_include_median_ablation():
    # SERA-Median: the median critic (deviation 0) enters the softmax
    result = sera_aggregate(th.tensor([[1.0, 2.0, 4.0]]), alpha=0.5, include_median=True)
    z = math.exp(-1) + 1.0 + math.exp(-2)
    assert result.weights[0].tolist() == pytest.approx([math.exp(-1) / z, 1 / z, math.exp(-2) / z], abs=1e-6)
    rest = (math.exp(-1) * 1 + 2 + math.exp(-2) * 4) / z  # 1.9353319
    assert result.value.item() == pytest.approx(0.5 * 2 + 0.5 * rest, abs=1e-6)


def test_relative_temperature_is_scale_free():
    q = th.tensor([[1.0, 2.0, 4.0]])
    result = sera_aggregate(q, temperature=1.0, temperature_mode="relative")
    # mean non-median deviation (1 + 2) / 2 = 1.5, so the effective tau is 1.5
    w0 = 1.0 / (1.0 + math.exp(-1.0 / 1.5))
    assert result.weights[0].tolist() == pytest.approx([w0, 0.0, 1.0 - w0], abs=1e-6)
    scaled = sera_aggregate(1000.0 * q, temperature=1.0, temperature_mode="relative")
    assert th.allclose(scaled.weights, result.weights, atol=1e-6)
    # An ensemble in full agreement does not divide by zero
    assert th.isfinite(sera_aggregate(th.ones(2, 5), temperature_mode="relative").value).all()


def test_weights_sum_to_one_and_follow_deviation_order():
    # Lemma 4.1: among non-median critics, a smaller deviation gets a larger weight
    generator = th.Generator().manual_seed(0)
    q = th.randn(512, 5, generator=generator) * 10
    result = sera_aggregate(q, temperature=3.0)
    assert th.allclose(result.weights.sum(dim=1), th.ones(512), atol=1e-6)
    deviations = (q - result.median.unsqueeze(1)).abs()
    for row in range(q.shape[0]):
        others = [i for i in range(5) if i != result.median_index[row]]
        order = sorted(others, key=lambda i: deviations[row, i].item())
        weights = [result.weights[row, i].item() for i in order]
        assert all(a >= b for a, b in itertools.pairwise(weights))
        assert result.weights[row, result.median_index[row]] == 0


@pytest.mark.parametrize("n_critics", [2, 3, 4, 5, 10])
def test_convex_combination_bound(n_critics):
    # Proposition 4.2: min_i q_i <= Q_SERA <= max_i q_i, for any alpha in [0, 1] and tau > 0
    generator = th.Generator().manual_seed(n_critics)
    q = th.randn(1000, n_critics, generator=generator) * 50
    for alpha in (0.0, 0.3, 1.0):
        for temperature in (0.01, 1.0, 100.0):
            for include_median in (False, True):
                value = sera_aggregate(q, alpha, temperature, include_median).value
                assert (value >= q.min(dim=1).values - 1e-4).all()
                assert (value <= q.max(dim=1).values + 1e-4).all()


def test_target_aggregation_modes():
    q = th.tensor([[1.0, 2.0, 4.0], [3.0, -1.0, 0.0]])
    assert aggregate_target(q, "mean").tolist() == pytest.approx([7 / 3, 2 / 3])
    assert aggregate_target(q, "median").tolist() == [2.0, 0.0]
    assert aggregate_target(q, "min").tolist() == [1.0, -1.0]
    options = SERAOptions(alpha=0.5, temperature=1.0)
    assert aggregate_target(q, "sera", options)[0].item() == pytest.approx(1.9034121, abs=1e-6)
    # The options reach the rule: alpha = 1 is the median anchor alone
    assert aggregate_target(q, "sera", SERAOptions(alpha=1.0)).tolist() == [2.0, 0.0]
    with pytest.raises(ValueError, match="max"):
        aggregate_target(q, "max")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="actor aggregation 'max'"):
        selected_critic(q, "max")  # type: ignore[arg-type]


def test_the_rule_tables_name_every_rule():
    # The names users pass, the Literal types and the dispatch come from one table per kind of rule
    assert TARGET_AGGREGATIONS == ("sera", "mean", "median", "min") == get_args(TargetAggregation)
    assert ACTOR_AGGREGATIONS == ("median", "mean", "min") == get_args(ActorAggregation)


def test_selected_critic_by_hand():
    # The critic the actor's value comes from, per sample: the median (the paper's Algorithm 2, line 24) or the min
    q = th.tensor([[1.0, 2.0, 4.0], [3.0, -1.0, 0.0]], requires_grad=True)
    median, minimum = selected_critic(q, "median"), selected_critic(q, "min")
    assert median is not None and minimum is not None
    assert q.gather(1, median.unsqueeze(1)).squeeze(1).tolist() == [2.0, 0.0]
    assert q.gather(1, minimum.unsqueeze(1)).squeeze(1).tolist() == [1.0, -1.0]
    assert selected_critic(q, "mean") is None
    # The median actor's gradient reaches the median critic only
    q.gather(1, median.unsqueeze(1)).sum().backward()
    assert q.grad is not None
    assert q.grad.tolist() == [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]


def test_disagreement_by_hand():
    # U = mean(|1 - 2|, 0, |4 - 2|) = 1 ; mean(|3 - 0|, |-1 - 0|, 0) = 4 / 3
    assert ensemble_disagreement(th.tensor([[1.0, 2.0, 4.0], [3.0, -1.0, 0.0]])).tolist() == pytest.approx([1.0, 4 / 3])


def test_critic_correlation_by_hand():
    # Columns (1, 2, 3), (2, 4, 6), (3, 2, 1): pair correlations 1, -1, -1, mean -1/3
    q = th.tensor([[1.0, 2.0, 3.0], [2.0, 4.0, 2.0], [3.0, 6.0, 1.0]])
    assert critic_correlation(q).item() == pytest.approx(-1 / 3, abs=1e-6)
    # A constant critic counts as uncorrelated instead of NaN
    constant = th.tensor([[1.0, 5.0], [2.0, 5.0], [3.0, 5.0]])
    assert critic_correlation(constant).item() == 0.0


def test_td_error_correlation_against_a_hand_computed_matrix():
    # TD errors of three critics over four samples; columns centred: a = (-1.5, -0.5, 0.5, 1.5),
    # b = (-1.5, 0.5, -0.5, 1.5) (sum a*b = 4, both norms^2 = 5: r = 0.8), c = -a (r = -1 with a, -0.8 with b)
    deltas = th.tensor([[1.0, 1.0, 4.0], [2.0, 3.0, 3.0], [3.0, 2.0, 2.0], [4.0, 4.0, 1.0]])
    expected = th.tensor([[1.0, 0.8, -1.0], [0.8, 1.0, -0.8], [-1.0, -0.8, 1.0]])
    assert th.allclose(correlation_matrix(deltas), expected, atol=1e-6)
    # Mean of the off-diagonal entries: 2 * (0.8 - 1 - 0.8) / 6 = -1/3
    assert td_error_correlation(deltas).item() == pytest.approx(-1 / 3, abs=1e-6)
    # torch.corrcoef's values bit for bit, computed without its checks on the data (the compiled step traces it)
    values = th.randn(64, 5, generator=th.Generator().manual_seed(0)) * th.tensor([1.0, 10.0, 100.0, 0.1, 3.0])
    assert th.equal(correlation_matrix(values), th.corrcoef(values.T))
