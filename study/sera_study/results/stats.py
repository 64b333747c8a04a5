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
studentized permutation test (the Welch t statistic over every split of the pooled runs), and over a family of
claims Holm's step-down adjustment (family-wise error) or Benjamini and Hochberg's q-values (false discovery rate).
"""

import itertools
import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from sera_study.defaults import REPS

#: Coverage of every confidence interval the report prints
CONFIDENCE = 0.95
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
    from scipy import stats  # where it is used: SciPy's statistics take seconds to import

    return float(stats.ttest_ind(sample, baseline, equal_var=False).pvalue)


def welch_interval(sample: ArrayLike, baseline: ArrayLike) -> tuple[float, float, float]:
    """
    ``mean(sample) - mean(baseline)`` with its :data:`CONFIDENCE` Welch t-interval (unequal variances,
    Welch-Satterthwaite degrees of freedom: SciPy's ``ttest_ind(..., equal_var=False).confidence_interval``).

    :return: the difference, lower and upper bounds (the bounds are the difference itself where both samples are
        constant)
    :raises ValueError: with fewer than two values in a sample
    """
    x, y = np.asarray(sample, dtype=float), np.asarray(baseline, dtype=float)
    if x.size < 2 or y.size < 2:
        raise ValueError(f"a Welch interval needs two values a side, got {x.size} and {y.size}")
    difference = float(x.mean() - y.mean())
    if x.var() + y.var() == 0:
        return difference, difference, difference
    from scipy import stats  # where it is used: SciPy's statistics take seconds to import

    interval = stats.ttest_ind(x, y, equal_var=False).confidence_interval(CONFIDENCE)
    return difference, float(interval.low), float(interval.high)


def _welch_t(sums: np.ndarray, squares: np.ndarray, total: float, total_squares: float, k: int, n: int) -> np.ndarray:
    """The Welch t statistic of splits of ``n`` pooled values into ``k`` and ``n - k``, from each split's sums."""
    other_sums, other_squares = total - sums, total_squares - squares
    mean_x, mean_y = sums / k, other_sums / (n - k)
    var_x = np.maximum(squares - sums**2 / k, 0.0) / (k - 1)
    var_y = np.maximum(other_squares - other_sums**2 / (n - k), 0.0) / (n - k - 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        statistic = (mean_x - mean_y) / np.sqrt(var_x / k + var_y / (n - k))
    # Both sides constant: 0 where the means are equal, infinite where they differ
    return np.where(np.isnan(statistic), 0.0, statistic)


def _splits(n: int, k: int, permutations: int) -> tuple[np.ndarray, int]:
    """Every split of ``n`` runs into ``k`` and ``n - k`` (as the first side's indices), or ``permutations`` random
    ones seeded with :data:`BOOTSTRAP_SEED`; and 1 for a random draw (the observed split is counted in), else 0."""
    if math.comb(n, k) <= permutations:
        return np.array(list(itertools.combinations(range(n), k)), dtype=np.intp), 0
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    return np.argsort(rng.random((permutations, n)), axis=1)[:, :k], 1


def studentized_permutation_p_value(sample: ArrayLike, baseline: ArrayLike, permutations: int = PERMUTATIONS) -> float:
    """
    Two-sided studentized permutation test of ``mean(sample) - mean(baseline)``: the share of the pooled runs' splits
    into two sides of the same sizes whose Welch t statistic is at least as far from 0 as the observed one. Unlike
    the raw difference of means, the studentized statistic keeps the test about the means where the two sides'
    spreads differ (Janssen 1997; Chung and Romano 2013). Every split is enumerated while there are at most
    ``permutations`` of them; above that, ``permutations`` random splits seeded with :data:`BOOTSTRAP_SEED`, the
    observed split counted in (``(b + 1) / (m + 1)``).

    :raises ValueError: with fewer than two runs on a side
    """
    x, y = np.asarray(sample, dtype=float), np.asarray(baseline, dtype=float)
    if x.size < 2 or y.size < 2:
        raise ValueError(f"a studentized permutation test needs two runs a side, got {x.size} and {y.size}")
    pooled = np.concatenate([x, y])
    n, k = pooled.size, x.size
    chosen, extra = _splits(n, k, permutations)
    values = pooled[chosen]
    total, total_squares = float(pooled.sum()), float((pooled**2).sum())
    statistics = np.abs(_welch_t(values.sum(axis=1), (values**2).sum(axis=1), total, total_squares, k, n))
    observed = abs(float(_welch_t(np.array([x.sum()]), np.array([(x**2).sum()]), total, total_squares, k, n)[0]))
    # Statistics that equal the observed one up to rounding count as at least as far
    at_least = statistics >= observed * (1 - 1e-9) if np.isfinite(observed) else np.isinf(statistics)
    return float((np.count_nonzero(at_least) + extra) / (statistics.size + extra))


def raw_permutation_p_value(sample: ArrayLike, baseline: ArrayLike, permutations: int = PERMUTATIONS) -> float:
    """
    Two-sided permutation test of the raw difference of means, the test ``results/claims.yml`` first declared: the
    share of the pooled runs' splits whose difference of means is at least as far from 0 as the observed one (the
    splits of :func:`studentized_permutation_p_value`). Kept to report the verdicts of the rule first declared beside
    those of the rule that replaced it (its size drifts where the arms' spreads differ).

    :raises ValueError: with an empty side
    """
    x, y = np.asarray(sample, dtype=float), np.asarray(baseline, dtype=float)
    if x.size == 0 or y.size == 0:
        raise ValueError(f"a permutation test needs runs on both sides, got {x.size} and {y.size}")
    pooled = np.concatenate([x, y])
    n, k = pooled.size, x.size
    chosen, extra = _splits(n, k, permutations)
    sums = pooled[chosen].sum(axis=1)
    differences = np.abs(sums / k - (pooled.sum() - sums) / (n - k))
    # Differences that equal the observed one up to rounding count as at least as far
    observed = abs(x.mean() - y.mean()) - 1e-9 * max(1.0, float(np.abs(pooled).max()))
    return float((np.count_nonzero(differences >= observed) + extra) / (sums.size + extra))


def smallest_p_value(n_sample: int, n_baseline: int, permutations: int = PERMUTATIONS) -> float:
    """
    The smallest p-value :func:`studentized_permutation_p_value` can give at these sizes, whatever the runs: one
    split of all (two with sides of equal size, whose mirror split is as extreme), or one in ``permutations + 1``.
    """
    splits = math.comb(n_sample + n_baseline, n_sample)
    if splits > permutations:
        return 1 / (permutations + 1)
    return (2 if n_sample == n_baseline else 1) / splits


def decision_p_value(sample: ArrayLike, baseline: ArrayLike, permutations: int = PERMUTATIONS) -> tuple[float, float, float]:
    """
    The p-value a claim is decided on: the larger of the studentized permutation p and Welch's t-test p, so that a
    difference is declared only where the permutation test finds it and the 95% Welch interval excludes 0 (Welch's p
    is below 0.05 exactly when that interval excludes 0): the verdict never points where its interval does not.

    :return: the decision p, the studentized permutation p and Welch's p
    """
    permutation = studentized_permutation_p_value(sample, baseline, permutations)
    welch = welch_p_value(sample, baseline)
    assert welch is not None  # two runs a side, checked above
    if math.isnan(welch):
        # Two constant sides: a certain difference, or none
        welch = 0.0 if np.asarray(sample, dtype=float).mean() != np.asarray(baseline, dtype=float).mean() else 1.0
    return max(permutation, welch), permutation, welch


def welch_power(difference: float, std: float, baseline_std: float, n: int, n_baseline: int, alpha: float = 0.05) -> float:
    """
    The power of the two-sided Welch t-test at level ``alpha`` against a true difference of means ``difference``
    between normal arms of standard deviations ``std`` and ``baseline_std`` with ``n`` and ``n_baseline`` runs: the
    noncentral t distribution at the Welch-Satterthwaite degrees of freedom (the chance of rejecting on either side).
    """
    from scipy import stats  # where it is used: SciPy's statistics take seconds to import

    variance_a, variance_b = std**2 / n, baseline_std**2 / n_baseline
    scale = math.sqrt(variance_a + variance_b)
    df = (variance_a + variance_b) ** 2 / (variance_a**2 / (n - 1) + variance_b**2 / (n_baseline - 1))
    critical = stats.t.ppf(1 - alpha / 2, df)
    shift = difference / scale
    return float(stats.nct.sf(critical, df, shift) + stats.nct.cdf(-critical, df, shift))


def runs_for_power(difference: float, std: float, baseline_std: float, power: float = 0.8, alpha: float = 0.05) -> int:
    """The fewest runs an arm (the same in both) at which :func:`welch_power` reaches ``power``."""
    n = 2
    while welch_power(difference, std, baseline_std, n, n, alpha) < power:
        n += 1
    return n


class Decision(NamedTuple):
    """What :func:`decide` finds: the difference of means with its Welch interval, and the test where one can run."""

    difference: float
    low: float
    high: float
    #: The smallest p the arms' sizes allow (:func:`smallest_p_value`)
    smallest_p: float
    #: :func:`decision_p_value`'s three p-values; None where ``smallest_p`` is not below the threshold
    p: float | None
    permutation_p: float | None
    welch_p: float | None


def decide(sample: ArrayLike, baseline: ArrayLike, threshold: float) -> Decision:
    """
    ``mean(sample) - mean(baseline)`` with its Welch interval, and the decision p (:func:`decision_p_value`) only
    where the arms' sizes allow a p below ``threshold``: no test is run where none could reject.

    :raises ValueError: with fewer than two values in a sample (:func:`welch_interval`)
    """
    difference, low, high = welch_interval(sample, baseline)
    smallest = smallest_p_value(np.size(sample), np.size(baseline))
    if smallest >= threshold:
        return Decision(difference, low, high, smallest, None, None, None)
    return Decision(difference, low, high, smallest, *decision_p_value(sample, baseline))


def benjamini_hochberg(p_values: Sequence[float]) -> list[float]:
    """
    Benjamini and Hochberg's q-values (SciPy's ``false_discovery_control``): the i-th smallest of m p-values times
    ``m / i``, made monotone from the largest down and capped at 1. Declaring the claims whose q is below alpha keeps
    the expected share of false discoveries among them at most alpha (for independent or positively dependent tests).
    """
    return _false_discovery_control(p_values, "bh")


def benjamini_yekutieli(p_values: Sequence[float]) -> list[float]:
    """
    Benjamini and Yekutieli's q-values (SciPy's ``false_discovery_control``): Benjamini-Hochberg's times
    ``c(m) = 1 + 1/2 + ... + 1/m``, capped at 1. Declaring the claims whose q is below alpha keeps the expected share
    of false discoveries at most alpha whatever the dependence between the tests (claims that share runs, or come in
    near-duplicate pairs).
    """
    return _false_discovery_control(p_values, "by")


def _false_discovery_control(p_values: Sequence[float], method: str) -> list[float]:
    if not p_values:
        return []
    from scipy import stats

    return [float(value) for value in stats.false_discovery_control(np.asarray(p_values, dtype=float), method=method)]


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
    from scipy import stats

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
    from scipy import stats

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
