"""Run statistics on fixed inputs, against values computed by hand and by scipy."""

import pytest
from scipy import stats

from sb3_sera.experiments.compare import RunResult, summary_table
from sb3_sera.experiments.stats import improvement_percent, normalized_auc, welch_p_value


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


def test_summary_table_columns():
    def run(algo, seed, returns):
        return RunResult(algo, "Pendulum-v1", seed, 300, 10.0, returns[-1], [100, 200, 300], returns)

    results = [run("serasac", 0, [0.0, 10.0, 20.0]), run("serasac", 1, [0.0, 10.0, 30.0])]
    results += [run("sac", 0, [0.0, 5.0, 10.0]), run("sac", 1, [0.0, 5.0, 12.0])]
    table = summary_table(results).splitlines()
    assert "p vs serasac (Welch)" in table[0]
    # serasac: finals 20, 30 -> 25.0 ± 5.0; AUC of (0, 10, 20) = 10, of (0, 10, 30) = 12.5 -> 11.2 (11.25)
    assert table[2].startswith("| serasac | 2 | 25.0 ± 5.0 | 11.2 |  |")
    # sac: finals 10, 12 -> 11.0 ± 1.0; AUC of (0, 5, 10) = 5, of (0, 5, 12) = 5.5 -> 5.2 (5.25)
    p_value = stats.ttest_ind([10.0, 12.0], [20.0, 30.0], equal_var=False).pvalue
    assert table[3].startswith(f"| sac | 2 | 11.0 ± 1.0 | 5.2 | {p_value:.3f} |")
