"""
Statistics of learning runs, as reported since "Deep RL at the Edge of the Statistical Precipice" (Agarwal et al.,
2021) with its library ``rliable``: interquartile means (IQM) with stratified-bootstrap confidence intervals,
probability of improvement and performance profiles; beside them the paper's layout (mean ± sample standard
deviation, Welch's t-test), the normalized AUC of a learning curve and min-max normalized scores.
"""

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy import stats

#: Coverage of every confidence interval the report prints
CONFIDENCE = 0.95
#: Bootstrap replications by default
REPS = 5000
#: Seed of the bootstrap, so that a report made twice from the same runs prints the same intervals
BOOTSTRAP_SEED = 0


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


def welch_p_value(sample: ArrayLike, baseline: ArrayLike) -> float | None:
    """Two-sided p-value of Welch's t-test (unequal variances); ``None`` with fewer than two values in a sample."""
    sample, baseline = np.asarray(sample, dtype=float), np.asarray(baseline, dtype=float)
    if sample.size < 2 or baseline.size < 2:
        return None
    return float(stats.ttest_ind(sample, baseline, equal_var=False).pvalue)


def improvement_percent(value: float, baseline: float) -> float:
    """How much ``value`` improves on ``baseline``, in percent of the baseline's magnitude (returns can be negative)."""
    if baseline == 0:
        raise ValueError("The improvement over a baseline of 0 is undefined")
    return (value - baseline) / abs(baseline) * 100.0


def sample_std(values: ArrayLike) -> float:
    """Sample standard deviation (ddof 1); NaN for fewer than two values."""
    array = np.asarray(values, dtype=float)
    return float(np.std(array, ddof=1)) if array.size > 1 else float("nan")


def _bootstrap(func: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    """
    Call one of rliable's bootstraps with numpy's global generator seeded by :data:`BOOTSTRAP_SEED` (rliable draws
    its resamples from it, whatever ``random_state`` says), then put the generator's state back.
    """
    state = np.random.get_state()
    np.random.seed(BOOTSTRAP_SEED)
    try:
        return func(*args, **kwargs)
    finally:
        np.random.set_state(state)


def iqm(scores: np.ndarray) -> np.ndarray:
    """
    Interquartile mean over runs and tasks (rliable's ``aggregate_iqm``: the mean of the middle 50% of the scores,
    25% trimmed from each end), per trailing index.

    :param scores: shape ``(runs, tasks)`` or ``(runs, tasks, points)``
    :return: one value, or one per point
    """
    flat = scores.reshape(scores.shape[0] * scores.shape[1], -1)
    return np.atleast_1d(stats.trim_mean(flat, proportiontocut=0.25, axis=0))


def iqm_interval(scores: np.ndarray, reps: int = REPS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    IQM with its 95% stratified-bootstrap confidence interval (runs resampled within each task; rliable's
    ``get_interval_estimates``, percentile method).

    :param scores: shape ``(runs, tasks)`` or ``(runs, tasks, points)``
    :return: point estimate, lower and upper bounds (one value, or one per point)
    """
    from rliable import library as rly

    points, intervals = _bootstrap(
        rly.get_interval_estimates, {"scores": scores}, iqm, reps=reps, confidence_interval_size=CONFIDENCE
    )
    return points["scores"], intervals["scores"][0], intervals["scores"][1]


def probability_of_improvement(scores_x: np.ndarray, scores_y: np.ndarray, reps: int = REPS) -> tuple[float, float, float]:
    """
    ``P(X > Y)``: the probability that a run of X scores higher than a run of Y on a task (ties count half),
    averaged over tasks, with its 95% stratified-bootstrap interval (rliable's ``probability_of_improvement``).

    :param scores_x: shape ``(runs of X, tasks)``
    :param scores_y: shape ``(runs of Y, tasks)``
    :return: point estimate, lower and upper bounds
    """
    from rliable import library as rly
    from rliable import metrics

    points, intervals = _bootstrap(
        rly.get_interval_estimates,
        {"pair": (scores_x, scores_y)},
        metrics.probability_of_improvement,
        reps=reps,
        confidence_interval_size=CONFIDENCE,
    )
    low, high = np.ravel(intervals["pair"])
    return float(points["pair"]), float(low), float(high)


def performance_profile(
    score_dict: dict[str, np.ndarray], thresholds: np.ndarray, reps: int = REPS
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """
    Performance profiles: per method, the fraction of runs (over all tasks) whose score exceeds each threshold, with
    95% stratified-bootstrap bands (rliable's ``create_performance_profile``).

    :param score_dict: per method, normalized scores of shape ``(runs, tasks)``
    :return: the profiles and their bands (shape ``(2, len(thresholds))``)
    """
    from rliable import library as rly

    return _bootstrap(rly.create_performance_profile, score_dict, thresholds, reps=reps, confidence_interval_size=CONFIDENCE)


def min_max_normalized(values: np.ndarray, low: float, high: float) -> np.ndarray:
    """``(values - low) / (high - low)``: 0 at ``low``, 1 at ``high`` (all zeros when ``high == low``)."""
    span = high - low
    return np.zeros_like(values, dtype=float) if span == 0 else (np.asarray(values, dtype=float) - low) / span
