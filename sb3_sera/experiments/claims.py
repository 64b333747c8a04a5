"""
The paper's mechanism claims (Fig. 4a, 4b, 4c and 5) tested on run records: each claim compares one per-run summary
between SERA and a baseline, as the difference of the means with its 95% bootstrap interval and a verdict.

Every summary is computed per run first, then compared across runs: a critic's index means nothing across seeds
(critic i of one run is not critic i of another), so no matrix is averaged entry by entry. The summaries:

- Fig. 5 (critics that share a step size synchronise), at the last evaluation. The values' own correlation is near
  1 for any trained ensemble (values differ most between states), so four measures that can move:

  - ``td_error_corr``: the mean off-diagonal correlation of the critics' TD errors on replayed transitions (the
    quantity the ensemble's variance reduction depends on: the variance of a mean of K errors is
    ``sigma^2 (1 + (K-1) rho) / K``);
  - ``mc_error_corr``: the same for the critics' errors against the Monte Carlo returns of the evaluation episodes;
    every error shares whatever separates the critics' soft values from the deterministic policy's returns, so
    this one can saturate too;
  - ``relative_disagreement``: the critics' mean variance about their ensemble mean over the variance of the
    ensemble mean, ``tr(P C P) / K`` over ``1' C 1 / K^2`` with ``C`` the critics' value covariance on replayed
    transitions and ``P = I - 11'/K``: how much of what the critics say is their own. It is blind to the shared part
    of their errors, which is what saturates the correlations. Synchronised critics drive it to 0;
  - ``closest_pair``: the smallest pairwise distance ``Var(Q_i - Q_j)`` over the mean pairwise distance: 1 when
    every pair of critics is as far apart as the average pair, near 0 when two critics are near duplicates (the
    pattern the paper's Fig. 5 describes for a fixed learning rate).
- ``target_relative_variance``: the TD target's batch variance over its mean square, ``Var(y) / mean(y^2)`` (the
  variance normalised by the targets' scale, so that a policy that earns more is not penalised for its larger
  values; unlike ``Var(y) / mean(y)^2`` it stays in [0, 1] where the targets' mean passes zero), averaged over the
  evaluations of the second half of training (Fig. 4c).
- ``relative_bias``: the initial-state bias ``|V(s0) - G|`` (``G`` the discounted return) relative to the returns'
  scale, over the evaluations after ``learning_starts`` (Fig. 4a): values and their errors grow with what a policy
  earns, so the raw bias would favour the policy that learns least.
- ``auc``: the normalized area under the learning curve (Fig. 4b).

Verdicts: *supported* when the interval lies wholly on the side the paper claims, *not supported* when it lies wholly
on the other side, *inconclusive at this n* when it contains zero, and *too few runs* when a side has fewer than
:data:`MIN_RUNS` runs (no interval is computed then).
"""

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sb3_sera.experiments import stats
from sb3_sera.experiments.evaluation import BIAS_FILE, DIAGNOSTICS_FILE
from sb3_sera.experiments.records import NPZ_ERRORS, RunResult

#: Runs each side needs before an interval or a verdict is given
MIN_RUNS = 3
#: The variant the claims are about
SERA = "serasac"


def load_diagnostics(run: RunResult) -> dict[str, np.ndarray] | None:
    """
    A run's critic diagnostics (``critic_diagnostics.npz``, SAC family), or None (no record, or a damaged one); with
    ``td_target_relative_var``, the TD target's variance over its mean square, where the run recorded the mean.
    """
    path = Path(run.folder) / DIAGNOSTICS_FILE
    if not path.exists():
        return None
    try:
        with np.load(path) as records:
            diagnostics = {key: records[key] for key in records.files}
    except NPZ_ERRORS:
        return None
    if "td_target_mean" in diagnostics:
        variance, mean = diagnostics["td_target_var"], diagnostics["td_target_mean"]
        diagnostics["td_target_relative_var"] = variance / (variance + mean**2)
    return diagnostics


def last_diagnostic(key: str) -> Callable[[RunResult], float | None]:
    """A summary: the diagnostic ``key`` at the run's last evaluation (None where the run did not record it)."""

    def summary(run: RunResult) -> float | None:
        records = load_diagnostics(run)
        if records is None or key not in records or not np.isfinite(records[key][-1]):
            return None
        return float(records[key][-1])

    return summary


def _last_matrix(run: RunResult, key: str) -> np.ndarray | None:
    records = load_diagnostics(run)
    if records is None or key not in records or not np.isfinite(records[key][-1]).all():
        return None
    return np.asarray(records[key][-1], dtype=float)


def relative_disagreement(run: RunResult) -> float | None:
    """``tr(P C P) / K`` over ``1' C 1 / K^2`` of the critics' value covariance ``C`` at the last evaluation."""
    cov = _last_matrix(run, "critic_cov_matrix")
    if cov is None or len(cov) < 2:
        return None
    k = len(cov)
    centering = np.eye(k) - np.full((k, k), 1.0 / k)
    ensemble_var = cov.sum() / k**2
    return float(np.trace(centering @ cov @ centering) / k / ensemble_var) if ensemble_var > 0 else None


def closest_pair(run: RunResult) -> float | None:
    """The smallest ``Var(Q_i - Q_j)`` over the mean of all pairs', from the value covariance at the last evaluation."""
    cov = _last_matrix(run, "critic_cov_matrix")
    if cov is None or len(cov) < 3:
        return None
    i, j = np.triu_indices(len(cov), k=1)
    distances = cov[i, i] + cov[j, j] - 2 * cov[i, j]
    return float(distances.min() / distances.mean()) if distances.mean() > 0 else None


def target_relative_variance(run: RunResult) -> float | None:
    """The TD target's ``Var(y) / mean(y^2)`` averaged over the evaluations of the second half of training."""
    records = load_diagnostics(run)
    if records is None or "td_target_relative_var" not in records:
        return None
    late = records["timesteps"] >= run.n_timesteps / 2
    return float(np.mean(records["td_target_relative_var"][late]))


def relative_bias(run: RunResult) -> float | None:
    """
    The initial-state bias relative to the returns' scale, over the evaluations after ``learning_starts``:
    ``sum_t |mean V(s0) - mean G|`` over ``sum_t |mean G|`` (a policy that earns more has larger values and larger
    errors in the same units; a ratio of sums stays defined where a return crosses zero).
    """
    path = Path(run.folder) / BIAS_FILE
    if not path.exists():
        return None
    try:
        with np.load(path) as records:
            steps, values, returns = records["timesteps"], records["values"], records["discounted_returns"]
    except NPZ_ERRORS:
        return None
    after = steps > float(run.hyperparams.get("learning_starts", 0))
    scale = np.abs(returns[after].mean(axis=1)).sum()
    if not after.any() or scale == 0:
        return None
    return float(np.abs(values[after].mean(axis=1) - returns[after].mean(axis=1)).sum() / scale)


def auc(run: RunResult) -> float | None:
    """The run's normalized AUC."""
    return stats.normalized_auc(run.timesteps, run.returns)


@dataclass(frozen=True)
class Claim:
    """One of the paper's claims: SERA's ``summary`` is lower (``lower=True``) or higher than each baseline's."""

    figure: str
    text: str
    summary_name: str
    summary: Callable[[RunResult], float | None]
    lower: bool
    baselines: tuple[str, ...]


#: The baselines of the adaptive step size: a fixed critic rate, at ``learning_rate`` and at SERA's mean rate
NO_LR = ("sera_nolr", "sera_nolr_matched")

CLAIMS = (
    Claim(
        figure="Fig. 5",
        text="the adaptive step size decorrelates the critics' TD errors",
        summary_name="td_error_corr at the last evaluation",
        summary=last_diagnostic("td_error_corr"),
        lower=True,
        baselines=NO_LR,
    ),
    Claim(
        figure="Fig. 5",
        text="the adaptive step size decorrelates the critics' errors against Monte Carlo returns",
        summary_name="mc_error_corr at the last evaluation",
        summary=last_diagnostic("mc_error_corr"),
        lower=True,
        baselines=NO_LR,
    ),
    Claim(
        figure="Fig. 5",
        text="the adaptive step size keeps the critics apart",
        summary_name="relative_disagreement at the last evaluation",
        summary=relative_disagreement,
        lower=False,
        baselines=NO_LR,
    ),
    Claim(
        figure="Fig. 5",
        text="with a fixed step size some critics become near duplicates",
        summary_name="closest_pair at the last evaluation",
        summary=closest_pair,
        lower=False,
        baselines=NO_LR,
    ),
    Claim(
        figure="Fig. 4c",
        text="SERA's TD target has the lowest normalised variance",
        summary_name="Var(y) / mean(y^2), second half of training",
        summary=target_relative_variance,
        lower=True,
        baselines=("sac", "ensemble_mean", "masac"),
    ),
    Claim(
        figure="Fig. 4a",
        text="SERA has the smallest initial-state bias",
        summary_name="sum abs(V(s0) - G) / sum abs(G) after learning_starts",
        summary=relative_bias,
        lower=True,
        baselines=("sac", "ensemble_mean", "sera_nolr", "masac", "matd3", "maddpg"),
    ),
    Claim(
        figure="Fig. 4b",
        text="each part of SERA adds to its learning",
        summary_name="normalized AUC",
        summary=auc,
        lower=False,
        baselines=("sera_nolr", "sera_nolr_matched", "sera_median", "ensemble_mean"),
    ),
)


def mean_difference_interval(sample: np.ndarray, baseline: np.ndarray, reps: int = stats.REPS) -> tuple[float, float, float]:
    """
    ``mean(sample) - mean(baseline)`` with its 95% percentile bootstrap interval (runs resampled within each side,
    seeded with :data:`stats.BOOTSTRAP_SEED`).

    :return: the difference, lower and upper bounds
    """
    rng = np.random.default_rng(stats.BOOTSTRAP_SEED)
    resampled = sample[rng.integers(0, len(sample), (reps, len(sample)))].mean(axis=1) - baseline[
        rng.integers(0, len(baseline), (reps, len(baseline)))
    ].mean(axis=1)
    tail = (1.0 - stats.CONFIDENCE) / 2 * 100
    low, high = np.percentile(resampled, [tail, 100 - tail])
    return float(sample.mean() - baseline.mean()), float(low), float(high)


def verdict(low: float, high: float, lower: bool) -> str:
    """*supported*, *not supported* or *inconclusive at this n* for an interval of SERA minus a baseline."""
    if (high < 0) if lower else (low > 0):
        return "supported"
    if (low > 0) if lower else (high < 0):
        return "not supported"
    return "inconclusive at this n"


def _format(value: float) -> str:
    return f"{value:.3g}" if abs(value) < 1000 else f"{value:.0f}"


def claims_table(groups: dict[str, list[RunResult]], reps: int = stats.REPS) -> list[str]:
    """
    The claims whose variants are present in one task and budget: a Markdown table with a row per (claim, baseline).

    :param groups: the section's runs by variant (one settings group each)
    :return: the table's lines (empty when SERA or every baseline is missing)
    """
    if SERA not in groups:
        return []
    lines = [
        "| claim | measure (per run) | SERA vs | n | SERA mean | baseline mean | difference [95% CI] | verdict |",
        "|---|---|---|---|---|---|---|---|",
    ]
    rows = 0
    for claim in CLAIMS:
        sera = np.array([v for v in map(claim.summary, groups[SERA]) if v is not None])
        for baseline_name in claim.baselines:
            if baseline_name not in groups or len(sera) == 0:
                continue
            baseline = np.array([v for v in map(claim.summary, groups[baseline_name]) if v is not None])
            if len(baseline) == 0:
                continue
            direction = "lower" if claim.lower else "higher"
            if min(len(sera), len(baseline)) < MIN_RUNS:
                difference, result = f"{_format(float(sera.mean() - baseline.mean()))}", f"too few runs (< {MIN_RUNS})"
            else:
                point, low, high = mean_difference_interval(sera, baseline, reps)
                difference = f"{_format(point)} [{_format(low)}, {_format(high)}]"
                result = verdict(low, high, claim.lower)
            lines.append(
                f"| {claim.figure}: {claim.text} (SERA {direction}) | {claim.summary_name} | {baseline_name} "
                f"| {len(sera)} vs {len(baseline)} | {_format(float(sera.mean()))} | {_format(float(baseline.mean()))} "
                f"| {difference} | {result} |"
            )
            rows += 1
    if rows == 0:
        return []
    return [
        *lines,
        "",
        f"Difference: SERA's mean minus the baseline's, over per-run summaries; [a, b]: 95% percentile bootstrap "
        f"interval, runs resampled within each side, {reps} resamples. Verdict: supported when the interval lies "
        "wholly on the claimed side of zero, not supported when wholly on the other, inconclusive when it holds zero; "
        f"no interval with fewer than {MIN_RUNS} runs a side. See `sb3_sera/experiments/claims.py` for each measure.",
    ]


def claims_section(variants_runs: Sequence[tuple[str, list[RunResult]]], reps: int = stats.REPS) -> list[str]:
    """:func:`claims_table` from ``(variant, runs)`` pairs, keeping variants with one settings group only."""
    counts: dict[str, int] = {}
    for variant, _ in variants_runs:
        counts[variant] = counts.get(variant, 0) + 1
    return claims_table({variant: runs for variant, runs in variants_runs if counts[variant] == 1}, reps)
