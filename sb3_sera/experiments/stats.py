"""Statistics of learning runs: normalized AUC, Welch's t-test, relative improvement."""

from collections.abc import Sequence

import numpy as np
from scipy import stats


def normalized_auc(timesteps: Sequence[float], returns: Sequence[float]) -> float:
    """
    Area under a learning curve divided by its length in steps (trapezoid rule): the curve's average return.

    :param timesteps: evaluation steps, increasing
    :param returns: mean evaluation return at each step
    """
    steps, values = np.asarray(timesteps, dtype=float), np.asarray(returns, dtype=float)
    if steps.shape != values.shape or steps.size == 0:
        raise ValueError(f"Need one return per timestep, got {steps.size} timesteps and {values.size} returns")
    if steps.size == 1:
        return float(values[0])
    return float(np.trapezoid(values, steps) / (steps[-1] - steps[0]))


def welch_p_value(sample: Sequence[float], baseline: Sequence[float]) -> float | None:
    """Two-sided p-value of Welch's t-test (unequal variances); ``None`` with fewer than two values in a sample."""
    if len(sample) < 2 or len(baseline) < 2:
        return None
    return float(stats.ttest_ind(sample, baseline, equal_var=False).pvalue)


def improvement_percent(value: float, baseline: float) -> float:
    """How much ``value`` improves on ``baseline``, in percent of the baseline's magnitude (returns can be negative)."""
    if baseline == 0:
        raise ValueError("The improvement over a baseline of 0 is undefined")
    return (value - baseline) / abs(baseline) * 100.0
