"""
Statistics of learning runs, as reported since "Deep RL at the Edge of the Statistical Precipice" (Agarwal et al.,
2021) with its library ``rliable``: interquartile means (IQM) with stratified-bootstrap confidence intervals,
probability of improvement and performance profiles; beside them the paper's layout (mean ± sample standard
deviation, Welch's t-test), the normalized AUC of a learning curve and min-max normalized scores.

The bootstraps are rliable's (runs resampled with replacement within each task, percentile intervals), vectorized:
every resample is drawn at once from a generator seeded with :data:`BOOTSTRAP_SEED`, so an interval takes
milliseconds where rliable's resample-by-resample loop takes seconds; the tests check them against rliable's.

A claim about two arms is decided with tests whose size holds at five runs a side, where a percentile bootstrap of
the difference covers the truth well under 95% of the time: the Welch t-interval of the difference of means, the
exact permutation test of that difference, and Holm's step-down adjustment over a family of claims.
"""

import itertools
import math
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
#: Splits a permutation test enumerates exactly; above this many it draws this many at random (seeded)
PERMUTATIONS = 200_000


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


def welch_interval(sample: ArrayLike, baseline: ArrayLike) -> tuple[float, float, float]:
    """
    ``mean(sample) - mean(baseline)`` with its :data:`CONFIDENCE` Welch t-interval (unequal variances,
    Welch-Satterthwaite degrees of freedom).

    :return: the difference, lower and upper bounds (the bounds are the difference itself where both samples are
        constant)
    :raises ValueError: with fewer than two values in a sample
    """
    x, y = np.asarray(sample, dtype=float), np.asarray(baseline, dtype=float)
    if x.size < 2 or y.size < 2:
        raise ValueError(f"a Welch interval needs two values a side, got {x.size} and {y.size}")
    difference = float(x.mean() - y.mean())
    vx, vy = x.var(ddof=1) / x.size, y.var(ddof=1) / y.size
    if vx + vy == 0:
        return difference, difference, difference
    dof = (vx + vy) ** 2 / (vx**2 / (x.size - 1) + vy**2 / (y.size - 1))
    half = float(stats.t.ppf(0.5 + CONFIDENCE / 2, dof) * math.sqrt(vx + vy))
    return difference, difference - half, difference + half


def permutation_p_value(sample: ArrayLike, baseline: ArrayLike, permutations: int = PERMUTATIONS) -> float:
    """
    Two-sided permutation test of ``mean(sample) - mean(baseline)``: the share of the pooled runs' splits into two
    sides of the same sizes whose difference of means is at least as far from 0 as the observed one. Every split is
    enumerated while there are at most ``permutations`` of them (exact: at 5 against 5 the smallest p is 2/252);
    above that, ``permutations`` random splits seeded with :data:`BOOTSTRAP_SEED`, the observed split counted in
    (Phipson and Smyth's ``(b + 1) / (m + 1)``).

    :raises ValueError: with an empty side
    """
    x, y = np.asarray(sample, dtype=float), np.asarray(baseline, dtype=float)
    if x.size == 0 or y.size == 0:
        raise ValueError(f"a permutation test needs runs on both sides, got {x.size} and {y.size}")
    pooled = np.concatenate([x, y])
    n, k = pooled.size, x.size
    observed = abs(x.mean() - y.mean())
    # Differences that equal the observed one up to rounding count as at least as far
    tolerance = 1e-9 * max(1.0, float(np.abs(pooled).max()))
    if math.comb(n, k) <= permutations:
        chosen = np.array(list(itertools.combinations(range(n), k)), dtype=np.intp)
        sums = pooled[chosen].sum(axis=1)
        extra = 0
    else:
        rng = np.random.default_rng(BOOTSTRAP_SEED)
        chosen = np.argsort(rng.random((permutations, n)), axis=1)[:, :k]
        sums = pooled[chosen].sum(axis=1)
        extra = 1
    differences = np.abs(sums / k - (pooled.sum() - sums) / (n - k))
    return float((np.count_nonzero(differences >= observed - tolerance) + extra) / (sums.size + extra))


def holm_adjusted(p_values: Sequence[float]) -> list[float]:
    """
    Holm's step-down adjustment: the i-th smallest of m p-values times ``m - i + 1`` (i from 1), made monotone and
    capped at 1. A claim is rejected at level alpha when its adjusted p is below alpha; the family-wise error rate is
    then at most alpha whatever the dependence between the claims.
    """
    p = np.asarray(p_values, dtype=float)
    m = p.size
    order = np.argsort(p, kind="stable")
    adjusted = np.empty(m)
    running = 0.0
    for rank, index in enumerate(order):
        running = max(running, min(1.0, (m - rank) * p[index]))
        adjusted[index] = running
    return [float(value) for value in adjusted]


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
