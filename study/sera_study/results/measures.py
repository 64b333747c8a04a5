"""
The per-run measures the claims compare (:data:`MEASURES`): the paper's mechanism claims (Fig. 4a, 4b, 4c and 5) and
the final return, each a summary of one run's records.

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

- ``final_return``: the mean of the last :data:`~sera_study.records.FINAL_EVALUATIONS` evaluations'
  mean returns; ``abs_bias`` and ``signed_bias``: ``|V(s0) - G|`` and ``V(s0) - G`` in return units (the paper's
  Fig. 4a), ``target_var``: the raw ``Var(y)`` (the paper's Fig. 4c), ``value_corr``: the critics' mean off-diagonal
  value correlation (the paper's Fig. 5).
"""

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sb3_sera.common.evaluation import BIAS_FILE, DIAGNOSTICS_FILE
from sera_study.records import NPZ_ERRORS, RunResult
from sera_study.results import stats


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


def late_mean(key: str) -> Callable[[RunResult], float | None]:
    """A summary: the diagnostic ``key`` averaged over the evaluations of the second half of training."""

    def summary(run: RunResult) -> float | None:
        records = load_diagnostics(run)
        if records is None or key not in records:
            return None
        late = records["timesteps"] >= run.n_timesteps / 2
        return float(np.mean(records[key][late])) if late.any() else None

    return summary


#: The TD target's ``Var(y) / mean(y^2)`` averaged over the evaluations of the second half of training
target_relative_variance = late_mean("td_target_relative_var")
#: The TD target's batch variance ``Var(y)`` averaged over the evaluations of the second half of training
target_variance = late_mean("td_target_var")


def _bias_after_start(run: RunResult) -> tuple[np.ndarray, np.ndarray] | None:
    """Per evaluation after ``learning_starts``: the mean ``V(s0)`` and the mean discounted return ``G``."""
    path = Path(run.folder) / BIAS_FILE
    if not path.exists():
        return None
    try:
        with np.load(path) as records:
            steps, values, returns = records["timesteps"], records["values"], records["discounted_returns"]
    except NPZ_ERRORS:
        return None
    after = steps > float(run.hyperparams.get("learning_starts", 0))
    if not after.any():
        return None
    return values[after].mean(axis=1), returns[after].mean(axis=1)


def relative_bias(run: RunResult) -> float | None:
    """
    The initial-state bias relative to the returns' scale, over the evaluations after ``learning_starts``:
    ``sum_t |mean V(s0) - mean G|`` over ``sum_t |mean G|`` (a policy that earns more has larger values and larger
    errors in the same units; a ratio of sums stays defined where a return crosses zero).
    """
    bias = _bias_after_start(run)
    if bias is None or np.abs(bias[1]).sum() == 0:
        return None
    values, returns = bias
    return float(np.abs(values - returns).sum() / np.abs(returns).sum())


def abs_bias(run: RunResult) -> float | None:
    """``|mean V(s0) - mean G|`` averaged over the evaluations after ``learning_starts``, in return units."""
    bias = _bias_after_start(run)
    return None if bias is None else float(np.abs(bias[0] - bias[1]).mean())


def signed_bias(run: RunResult) -> float | None:
    """``mean V(s0) - mean G`` averaged over the evaluations after ``learning_starts`` (below 0: underestimation)."""
    bias = _bias_after_start(run)
    return None if bias is None else float((bias[0] - bias[1]).mean())


def final_return(run: RunResult) -> float | None:
    """The run's final return (the mean of its last evaluations: :attr:`.RunResult.final_return`)."""
    return run.final_return


def auc(run: RunResult) -> float | None:
    """The run's normalized AUC."""
    return stats.normalized_auc(run.timesteps, run.returns)


@dataclass(frozen=True)
class Measure:
    """A per-run summary a claim compares."""

    summary: Callable[[RunResult], float | None]
    #: What it is, for the tables
    text: str
    #: In the units the paper plots (True) or a scale-free form of ours (False)
    paper_units: bool


#: Every measure a claim can compare, by the name a claims file gives it
MEASURES: dict[str, Measure] = {
    "final_return": Measure(final_return, "final return (mean of the last 3 evaluations)", True),
    "auc": Measure(auc, "normalized AUC", True),
    "abs_bias": Measure(abs_bias, "abs(V(s0) - G) after learning_starts", True),
    "relative_bias": Measure(relative_bias, "sum abs(V(s0) - G) / sum abs(G) after learning_starts", False),
    "target_var": Measure(target_variance, "Var(y), second half of training", True),
    "target_relative_var": Measure(target_relative_variance, "Var(y) / mean(y^2), second half of training", False),
    "value_corr": Measure(last_diagnostic("critic_corr"), "critics' value correlation, last evaluation", True),
    "td_error_corr": Measure(last_diagnostic("td_error_corr"), "critics' TD-error correlation, last evaluation", False),
    "mc_error_corr": Measure(last_diagnostic("mc_error_corr"), "critics' MC-error correlation, last evaluation", False),
    "relative_disagreement": Measure(relative_disagreement, "relative disagreement, last evaluation", False),
    "closest_pair": Measure(closest_pair, "closest pair, last evaluation", False),
}


def bias_sign_line(runs: Sequence[RunResult]) -> str:
    """
    One sentence of how many runs with a bias record overestimate ``V(s0)`` (:func:`signed_bias` above 0), in all and
    on the HalfCheetah tasks, so that no page keeps such a count by hand.
    """
    signed = [(run.env_id, value) for run in runs if (value := signed_bias(run)) is not None]
    cheetah = [value for env_id, value in signed if "HalfCheetah" in env_id]
    over = sum(value > 0 for _, value in signed)
    return (
        f"Of the {len(signed)} published runs with an initial-state bias record, {over} overestimate `V(s0)` (a mean "
        f"signed bias above 0 after learning_starts); on the HalfCheetah tasks {sum(value > 0 for value in cheetah)} of "
        f"{len(cheetah)}."
    )
