"""
Statistics of learning runs, as reported since "Deep RL at the Edge of the Statistical Precipice" (Agarwal et al.,
2021) with its library ``rliable``: interquartile means (IQM) with stratified-bootstrap confidence intervals,
probability of improvement and performance profiles; beside them the paper's layout (mean ± sample standard
deviation, Welch's t-test), the normalized AUC of a learning curve and min-max normalized scores.

The bootstraps are rliable's (runs resampled with replacement within each task, percentile intervals), vectorized:
every resample is drawn at once from a generator seeded with :data:`BOOTSTRAP_SEED`, so an interval takes
milliseconds where rliable's resample-by-resample loop takes seconds; the tests check them against rliable's.
"""

from collections.abc import Sequence

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


def stratified_resamples(scores: np.ndarray, reps: int, rng: np.random.Generator) -> np.ndarray:
    """
    ``reps`` stratified-bootstrap resamples of ``scores``: in each, every task's runs drawn with replacement from
    that task's runs (a run keeps all its trailing values, the points of its curve).

    :param scores: shape ``(runs, tasks, ...)``
    :return: shape ``(reps, runs, tasks, ...)``
    """
    n_runs, n_tasks = scores.shape[:2]
    indices = rng.integers(0, n_runs, size=(reps, n_runs, n_tasks))
    return scores[indices, np.arange(n_tasks)]


def percentile_interval(resampled: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The :data:`CONFIDENCE` percentile interval of bootstrap statistics (first axis: the resamples)."""
    tail = (1.0 - CONFIDENCE) / 2 * 100
    low, high = np.percentile(resampled, [tail, 100 - tail], axis=0)
    return low, high


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
    IQM with its 95% stratified-bootstrap confidence interval (runs resampled within each task, percentile method:
    rliable's ``get_interval_estimates``).

    :param scores: shape ``(runs, tasks)`` or ``(runs, tasks, points)``
    :return: point estimate, lower and upper bounds (one value, or one per point)
    """
    scores = np.asarray(scores, dtype=float)
    resampled = stratified_resamples(scores, reps, np.random.default_rng(BOOTSTRAP_SEED))
    flat = resampled.reshape(reps, scores.shape[0] * scores.shape[1], -1)
    low, high = percentile_interval(stats.trim_mean(flat, proportiontocut=0.25, axis=1))
    return iqm(scores), low, high


def _improvement(scores_x: np.ndarray, scores_y: np.ndarray) -> np.ndarray:
    """P(X > Y) + P(X = Y) / 2 averaged over tasks, for arrays ``(..., runs, tasks)``: one value per leading index."""
    x, y = scores_x[..., :, None, :], scores_y[..., None, :, :]
    pairs = (x > y) + 0.5 * (x == y)
    return pairs.mean(axis=(-3, -2)).mean(axis=-1)


def probability_of_improvement(scores_x: np.ndarray, scores_y: np.ndarray, reps: int = REPS) -> tuple[float, float, float]:
    """
    ``P(X > Y)``: the probability that a run of X scores higher than a run of Y on a task (ties count half),
    averaged over tasks, with its 95% stratified-bootstrap interval (X's and Y's runs resampled independently within
    each task: rliable's ``probability_of_improvement``).

    :param scores_x: shape ``(runs of X, tasks)``
    :param scores_y: shape ``(runs of Y, tasks)``
    :return: point estimate, lower and upper bounds
    """
    scores_x, scores_y = np.asarray(scores_x, dtype=float), np.asarray(scores_y, dtype=float)
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    resampled = _improvement(stratified_resamples(scores_x, reps, rng), stratified_resamples(scores_y, reps, rng))
    low, high = percentile_interval(resampled)
    return float(_improvement(scores_x, scores_y)), float(low), float(high)


def performance_profile(
    score_dict: dict[str, np.ndarray], thresholds: np.ndarray, reps: int = REPS
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """
    Performance profiles: per method, the fraction of runs (over all tasks) whose score exceeds each threshold, with
    95% stratified-bootstrap bands (rliable's ``create_performance_profile`` with score distributions).

    :param score_dict: per method, normalized scores of shape ``(runs, tasks)``
    :return: the profiles and their bands (shape ``(2, len(thresholds))``)
    """
    thresholds = np.asarray(thresholds, dtype=float)
    profiles, bands = {}, {}
    for method, scores in score_dict.items():
        scores = np.asarray(scores, dtype=float)
        profiles[method] = (scores[..., None] > thresholds).mean(axis=(0, 1))
        resampled = stratified_resamples(scores, reps, np.random.default_rng(BOOTSTRAP_SEED))
        bands[method] = np.stack(percentile_interval((resampled[..., None] > thresholds).mean(axis=(1, 2))))
    return profiles, bands


def min_max_normalized(values: np.ndarray, low: float, high: float) -> np.ndarray:
    """``(values - low) / (high - low)``: 0 at ``low``, 1 at ``high`` (all zeros when ``high == low``)."""
    span = high - low
    return np.zeros_like(values, dtype=float) if span == 0 else (np.asarray(values, dtype=float) - low) / span
