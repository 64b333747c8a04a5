"""
The paper's mechanism claims (Fig. 4a, 4b, 4c and 5) tested on run records: each claim compares one per-run summary
between SERA and a baseline, as the difference of the means with its 95% Welch t-interval and a verdict.

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

- ``final_return``: the mean of the last :data:`~sb3_sera.experiments.records.FINAL_EVALUATIONS` evaluations'
  mean returns; ``abs_bias`` and ``signed_bias``: ``|V(s0) - G|`` and ``V(s0) - G`` in return units (the paper's
  Fig. 4a), ``target_var``: the raw ``Var(y)`` (the paper's Fig. 4c), ``value_corr``: the critics' mean off-diagonal
  value correlation (the paper's Fig. 5).

A claim (:class:`Claim`) names a task, a budget, a measure, two arms and the claimed direction, and whether it is
primary; a ledger declares its claims in ``results/claims.yml`` (:func:`load_claims`), and a report of other runs
tests :func:`default_claims`, all exploratory. :func:`evaluate` decides them: only arms whose shared settings match
are compared; the size is the difference of means with its 95% Welch t-interval; the test's p is the larger of the
studentized permutation p and Welch's p (:func:`~sb3_sera.experiments.stats.decision_p_value`), so that no verdict
points where its interval does not. The primary claims' p-values are Holm-adjusted within their family (a declared
primary claim not yet tested counts with p = 1), the exploratory claims' turned into Benjamini-Hochberg q-values over
all of them (untested ones count with p = 1). Verdicts at :data:`ALPHA`, read from the adjusted p: *supported* when it
is below alpha and the difference lies on the claimed side, *contradicted* when below it on the other side,
*inconclusive* otherwise; *too few runs to decide* where the arms' sizes cannot give a p below the claim's threshold
(alpha over the family's size for a primary claim, Holm's first; alpha for an exploratory one), and *interim* while a
claim with runs planned has fewer.
"""

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from sb3_sera.experiments import stats
from sb3_sera.experiments.evaluation import BIAS_FILE, DIAGNOSTICS_FILE
from sb3_sera.experiments.records import NPZ_ERRORS, RunResult
from sb3_sera.experiments.registry import SHARED_SETTINGS, shared_settings, unmatched_settings, unmatched_text

#: Runs each arm needs before its interval is given (a test needs as many as can give a p below its threshold)
MIN_RUNS = 2
#: The variant the claims are about
SERA = "serasac"
#: Level of every test
ALPHA = 0.05
#: The family of a primary claim that names none
PRIMARY_FAMILY = "paper"


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
#: The claim fields of a claims file, and which must be given
CLAIM_FIELDS = (
    "id",
    "source",
    "task",
    "n_timesteps",
    "seeds",
    "measure",
    "arm",
    "baseline",
    "direction",
    "primary",
    "family",
    "planned",
    "studies",
)
REQUIRED_FIELDS = ("id", "task", "n_timesteps", "measure", "arm", "baseline", "direction")
DIRECTIONS = ("higher", "lower")


@dataclass(frozen=True)
class Claim:
    """That ``arm``'s ``measure`` is ``direction`` than ``baseline``'s on ``task`` at ``n_timesteps`` steps."""

    id: str
    task: str
    n_timesteps: int
    measure: str
    arm: str
    baseline: str
    direction: str
    primary: bool = False
    #: Where the paper makes the claim (a figure or table)
    source: str = ""
    #: The first and last seed (both included) whose runs the claim reads; None: every seed
    seeds: tuple[int, int] | None = None
    #: The Holm family of a primary claim (each family adjusted on its own)
    family: str = PRIMARY_FAMILY
    #: Runs an arm the claim plans; with fewer it is interim and not decided (0: decided from MIN_RUNS on)
    planned: int = 0
    #: Shared settings the arms may differ in (systems compared each at its own settings)
    studies: tuple[str, ...] = ()

    def reads(self, run: RunResult) -> bool:
        """Whether the claim reads ``run`` (its seed within :attr:`seeds`)."""
        return self.reads_seed(run.seed)

    def reads_seed(self, seed: int) -> bool:
        """Whether the claim reads runs of ``seed`` (within :attr:`seeds`)."""
        return self.seeds is None or self.seeds[0] <= seed <= self.seeds[1]

    def shares_runs(self, other: "Claim") -> bool:
        """Whether the two claims can read a run in common (a variant, task, budget and seed they both read)."""
        same_runs = (self.task, self.n_timesteps) == (other.task, other.n_timesteps)
        common_variant = {self.arm, self.baseline} & {other.arm, other.baseline}
        first, last = self.seeds or (-math.inf, math.inf)
        other_first, other_last = other.seeds or (-math.inf, math.inf)
        return same_runs and bool(common_variant) and max(first, other_first) <= min(last, other_last)


def load_claims(path: str | Path) -> list[Claim]:
    """
    The claims a file declares (``results/claims.yml``: a mapping with ``claims``, a list of mappings with
    :data:`CLAIM_FIELDS`); ``ValueError`` naming the claim and the field for anything else.
    """
    try:
        document = yaml.safe_load(Path(path).read_text())
    except yaml.YAMLError as error:
        raise ValueError(f"{path}: not YAML: {' '.join(str(error).split())}") from None
    if not isinstance(document, dict) or not isinstance(document.get("claims"), list):
        raise ValueError(f"{path}: a claims file is a mapping whose 'claims' is a list of claims")
    claims, seen = [], set()
    for index, entry in enumerate(document["claims"]):
        where = f"{path}: claim {index + 1}"
        if not isinstance(entry, dict):
            raise ValueError(f"{where}: {entry!r} is not a mapping with {list(CLAIM_FIELDS)}")
        where = f"{path}: claim {entry.get('id', index + 1)!r}"
        unknown = sorted(set(entry) - set(CLAIM_FIELDS))
        missing = [key for key in REQUIRED_FIELDS if key not in entry]
        if unknown or missing:
            raise ValueError(f"{where}: unknown field(s) {unknown}, missing {missing}; fields: {list(CLAIM_FIELDS)}")
        if entry["measure"] not in MEASURES:
            raise ValueError(f"{where}: unknown measure {entry['measure']!r}; measures: {sorted(MEASURES)}")
        if entry["direction"] not in DIRECTIONS:
            raise ValueError(f"{where}: direction {entry['direction']!r} is not one of {list(DIRECTIONS)}")
        seeds = entry.get("seeds")
        if seeds is not None and not (
            isinstance(seeds, list) and len(seeds) == 2 and all(isinstance(s, int) for s in seeds) and seeds[0] <= seeds[1]
        ):
            raise ValueError(f"{where}: seeds {seeds!r} is not [first, last], two integers with first <= last")
        planned = entry.get("planned", 0)
        if not isinstance(planned, int) or planned < 0:
            raise ValueError(f"{where}: planned {planned!r} is not a number of runs (an integer >= 0)")
        studies = entry.get("studies", [])
        if not isinstance(studies, list) or sorted(set(studies) - set(SHARED_SETTINGS)):
            allowed = list(SHARED_SETTINGS)
            raise ValueError(f"{where}: studies {studies!r} is not a list of shared settings; allowed: {allowed}")
        if "family" in entry and not entry.get("primary", False):
            raise ValueError(f"{where}: a family is for primary claims (primary: true); exploratory claims have none")
        if entry["id"] in seen:
            raise ValueError(f"{where}: the id is declared twice")
        seen.add(entry["id"])
        claims.append(
            Claim(
                id=str(entry["id"]),
                task=str(entry["task"]),
                n_timesteps=int(entry["n_timesteps"]),
                measure=str(entry["measure"]),
                arm=str(entry["arm"]),
                baseline=str(entry["baseline"]),
                direction=str(entry["direction"]),
                primary=bool(entry.get("primary", False)),
                source=str(entry.get("source", "")),
                seeds=(seeds[0], seeds[1]) if seeds is not None else None,
                family=str(entry.get("family", PRIMARY_FAMILY)),
                planned=planned,
                studies=tuple(studies),
            )
        )
    return claims


#: The claims a report of any runs tests where they have the variants (all exploratory): measure, direction of
#: SERA's against each baseline, the baselines, the paper's figure
DEFAULT_CLAIMS = (
    ("final_return", "higher", ("sac", "ensemble_mean", "masac", "sera_nolr", "sera_median"), "Tables 1-2"),
    ("auc", "higher", ("sera_nolr", "sera_nolr_matched", "sera_median", "ensemble_mean"), "Fig. 4b"),
    ("abs_bias", "lower", ("sac", "ensemble_mean", "sera_nolr", "masac", "matd3", "maddpg"), "Fig. 4a"),
    ("relative_bias", "lower", ("sac", "ensemble_mean", "sera_nolr", "masac", "matd3", "maddpg"), "Fig. 4a"),
    ("target_var", "lower", ("sac", "ensemble_mean", "masac"), "Fig. 4c"),
    ("target_relative_var", "lower", ("sac", "ensemble_mean", "masac"), "Fig. 4c"),
    ("value_corr", "lower", ("sera_nolr", "sera_nolr_matched"), "Fig. 5"),
    ("td_error_corr", "lower", ("sera_nolr", "sera_nolr_matched"), "Fig. 5"),
    ("mc_error_corr", "lower", ("sera_nolr", "sera_nolr_matched"), "Fig. 5"),
    ("relative_disagreement", "higher", ("sera_nolr", "sera_nolr_matched"), "Fig. 5"),
    ("closest_pair", "higher", ("sera_nolr", "sera_nolr_matched"), "Fig. 5"),
)


def default_claims(groups: Sequence[Any]) -> list[Claim]:
    """The :data:`DEFAULT_CLAIMS` whose two variants have runs at one task and budget among ``groups``."""
    present = {(group.variant, group.env_id, group.n_timesteps) for group in groups}
    claims = []
    for env_id, budget in dict.fromkeys((group.env_id, group.n_timesteps) for group in groups):
        if (SERA, env_id, budget) not in present:
            continue
        for measure, direction, baselines, source in DEFAULT_CLAIMS:
            claims += [
                Claim(f"{measure}-{baseline}", env_id, budget, measure, SERA, baseline, direction, source=source)
                for baseline in baselines
                if (baseline, env_id, budget) in present
            ]
    return claims


def group_settings(group: Any) -> dict[str, Any]:
    """A report group's shared settings: :func:`~sb3_sera.experiments.registry.shared_settings` and evaluations."""
    evaluation = {key: group.hyperparams[key] for key in ("eval_freq", "eval_episodes") if key in group.hyperparams}
    return {**shared_settings(group.algo, group.hyperparams), **evaluation}


def group_studies(group: Any) -> set[str]:
    """The shared settings every run of a report group recorded as studied by its comparison."""
    return set.intersection(*(set(run.studies) for run in group.runs)) if group.runs else set()


def groups_unmatched(first: Any, second: Any, studied: Sequence[str] = ()) -> dict[str, dict[str, Any]]:
    """The shared settings two report groups differ in, but those both their comparisons studied and ``studied``."""
    settings = {first.label: group_settings(first), second.label: group_settings(second)}
    return unmatched_settings(settings, sorted(group_studies(first) & group_studies(second) | set(studied)))


@dataclass
class ClaimResult:
    """What the runs say of one claim."""

    claim: Claim
    arm_values: np.ndarray
    baseline_values: np.ndarray
    difference: float | None = None
    low: float | None = None
    high: float | None = None
    #: The decision p: the larger of :attr:`permutation_p` and :attr:`welch_p`
    p_value: float | None = None
    #: The studentized permutation test's p
    permutation_p: float | None = None
    #: Welch's t-test p (below 0.05 exactly when the 95% interval excludes 0)
    welch_p: float | None = None
    #: Holm-adjusted within the claim's family (primary claims), or its Benjamini-Hochberg q-value (exploratory)
    adjusted_p: float | None = None
    verdict: str = "waiting for runs"
    #: Why there is no test, or which settings group was used
    note: str = ""
    #: Its arms' means are not shown: the claim is interim, or reads runs of an interim claim
    withheld: bool = False


def _matched_groups(claim: Claim, groups: Sequence[Any]) -> tuple[Any, Any, str]:
    """The claim's two arms as report groups with the same shared settings, or (None, None, why not)."""
    arms = [g for g in groups if (g.variant, g.env_id, g.n_timesteps) == (claim.arm, claim.task, claim.n_timesteps)]
    baselines = [g for g in groups if (g.variant, g.env_id, g.n_timesteps) == (claim.baseline, claim.task, claim.n_timesteps)]
    if not arms or not baselines:
        missing = [name for name, found in ((claim.arm, arms), (claim.baseline, baselines)) if not found]
        return None, None, f"no runs of {' or '.join(missing)}"
    pairs = [(a, b) for a in arms for b in baselines if not groups_unmatched(a, b, claim.studies)]
    if not pairs:
        return None, None, f"unmatched: {unmatched_text(groups_unmatched(arms[0], baselines[0], claim.studies))}"
    arm, baseline = max(pairs, key=lambda pair: (len(pair[0].runs), len(pair[1].runs)))
    others = len(arms) + len(baselines) - 2
    return arm, baseline, (f"matched settings groups ({others} other group(s) left out)" if others else "")


def evaluate(claims: Sequence[Claim], groups: Sequence[Any], alpha: float = ALPHA) -> list[ClaimResult]:
    """
    Decide every claim on the report groups (:func:`~sb3_sera.experiments.report.groups.group_runs`): see the
    module's docstring.
    """
    sizes: dict[str, int] = {}
    for claim in claims:
        if claim.primary:
            sizes[claim.family] = sizes.get(claim.family, 0) + 1
    results = []
    for claim in claims:
        arm, baseline, note = _matched_groups(claim, groups)
        summary = MEASURES[claim.measure].summary
        values = [
            np.array([v for v in (summary(run) for run in group.runs if claim.reads(run)) if v is not None], dtype=float)
            if group is not None
            else np.array([])
            for group in (arm, baseline)
        ]
        result = ClaimResult(claim, values[0], values[1], note=note)
        results.append(result)
        if arm is None:
            continue
        _test(result, alpha / sizes[claim.family] if claim.primary else alpha)
    _withhold(results)
    _adjust(results)
    for result in results:
        if result.adjusted_p is None or result.difference is None:
            continue
        claimed_side = result.difference < 0 if result.claim.direction == "lower" else result.difference > 0
        result.verdict = ("supported" if claimed_side else "contradicted") if result.adjusted_p < alpha else "inconclusive"
    return results


def _test(result: ClaimResult, threshold: float) -> None:
    """
    Fill ``result``'s difference, interval and p-values, unless its arms have fewer runs than it plans or too few
    to give a p below ``threshold`` (its verdict then says so).
    """
    values, claim = (result.arm_values, result.baseline_values), result.claim
    n_arm, n_baseline = len(values[0]), len(values[1])
    if min(n_arm, n_baseline) < claim.planned:
        result.verdict, result.withheld = f"interim ({n_arm} and {n_baseline} of {claim.planned} runs)", True
        return
    if min(n_arm, n_baseline) < MIN_RUNS:
        result.verdict = f"too few runs to decide (fewer than {MIN_RUNS} an arm)"
        if n_arm and n_baseline:
            result.difference = float(values[0].mean() - values[1].mean())
        return
    decision = stats.decide(values[0], values[1], threshold)
    result.difference, result.low, result.high = decision.difference, decision.low, decision.high
    if decision.p is None:
        result.verdict = f"too few runs to decide (smallest possible p {decision.smallest_p:.3g})"
        return
    result.p_value, result.permutation_p, result.welch_p = decision.p, decision.permutation_p, decision.welch_p


def _withhold(results: Sequence[ClaimResult]) -> None:
    """
    Withhold every number of a claim that reads runs of an interim claim (it would tell the interim state): its
    difference, interval, p-values and arms' means; it enters the multiplicity adjustments as untested (p = 1).
    """
    interim = [result.claim for result in results if result.claim.planned and result.verdict.startswith("interim")]
    for result in results:
        holding = [claim.id for claim in interim if claim is not result.claim and claim.shares_runs(result.claim)]
        if holding and not result.withheld:
            result.difference = result.low = result.high = None
            result.p_value = result.permutation_p = result.welch_p = None
            result.verdict, result.withheld = f"withheld while {', '.join(holding)} is interim", True


def _adjust(results: Sequence[ClaimResult]) -> None:
    """Each tested claim's adjusted p: Holm within its primary family, or its q-value over the exploratory claims."""
    for family in families(results):
        adjusted = stats.holm_adjusted([1.0 if r.p_value is None else r.p_value for r in family])
        for result, p_adjusted in zip(family, adjusted, strict=True):
            if result.p_value is not None:
                result.adjusted_p = p_adjusted
    exploratory = [result for result in results if not result.claim.primary]
    if exploratory:
        q_values = stats.benjamini_hochberg([1.0 if r.p_value is None else r.p_value for r in exploratory])
        for result, q in zip(exploratory, q_values, strict=True):
            if result.p_value is not None:
                result.adjusted_p = q


def families(results: Sequence[ClaimResult]) -> list[list[ClaimResult]]:
    """The primary claims' results by Holm family, in the order the families are first declared."""
    grouped: dict[str, list[ClaimResult]] = {}
    for result in results:
        if result.claim.primary:
            grouped.setdefault(result.claim.family, []).append(result)
    return list(grouped.values())


def _format(value: float | None) -> str:
    if value is None:
        return ""
    return f"{value:.3g}" if abs(value) < 1000 else f"{value:.0f}"


def _p_text(value: float | None) -> str:
    return "" if value is None else f"{value:.4f}" if value >= 0.0001 else "< 0.0001"


def claims_table(results: Sequence[ClaimResult], primary: bool) -> list[str]:
    """
    A Markdown table of ``results``: each claim's difference with its interval, Welch's and the studentized
    permutation p, and the p its verdict reads (Holm-adjusted for primary claims, the q-value for exploratory ones).
    """
    if not results:
        return []
    adjusted = "Holm p" if primary else "BH q"
    lines = [
        "| claim | source | measure (per run) | units | SERA vs | n | SERA mean | baseline mean "
        f"| difference [95% Welch CI] | Welch p | permutation p | {adjusted} | verdict |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for result in results:
        claim, measure = result.claim, MEASURES[result.claim.measure]
        interval = (
            f"{_format(result.difference)} [{_format(result.low)}, {_format(result.high)}]"
            if result.low is not None
            else _format(result.difference)
        )
        shown = not result.withheld
        arm_mean = _format(float(result.arm_values.mean())) if shown and len(result.arm_values) else ""
        base_mean = _format(float(result.baseline_values.mean())) if shown and len(result.baseline_values) else ""
        verdict = result.verdict + (f" ({result.note})" if result.note else "")
        lines.append(
            f"| {claim.id}: SERA {claim.direction} | {claim.source} | {measure.text} "
            f"| {'paper' if measure.paper_units else 'scale-free'} | {claim.baseline} "
            f"| {len(result.arm_values)} vs {len(result.baseline_values)} | {arm_mean} | {base_mean} | {interval} "
            f"| {_p_text(result.welch_p)} | {_p_text(result.permutation_p)} | {_p_text(result.adjusted_p)} | {verdict} |"
        )
    return lines


def family_sizes(results: Sequence[ClaimResult]) -> dict[str, int]:
    """How many primary claims each Holm family of ``results`` holds."""
    return {family[0].claim.family: len(family) for family in families(results)}


def claims_legend(sizes: dict[str, int]) -> str:
    """What the claims tables' columns and verdicts are; ``sizes``: each primary family's number of claims."""
    family = (
        " Primary claims are Holm-adjusted within their family ("
        + ", ".join(f"'{name}': {size}" for name, size in sizes.items())
        + " claims; a primary claim not yet tested counts with p = 1); a claim with runs planned is interim, and not "
        "decided, until each arm has them."
        if sizes
        else ""
    )
    return (
        "Difference: SERA's mean minus the baseline's over per-run measures, with its 95% Welch t-interval. Welch p: "
        "Welch's two-sided t-test (below 0.05 exactly when the interval excludes 0). Permutation p: the studentized "
        "permutation test, Welch's t statistic over every split of the pooled runs (200,000 random splits where there "
        "are more). A claim is decided on the larger of the two, so that no verdict points where its interval does "
        "not, adjusted for multiplicity: Holm within a primary family, Benjamini-Hochberg q-values over all the "
        "exploratory claims (untested ones count with p = 1). Units: 'paper' is the measure the paper plots, "
        "'scale-free' our form of it normalised by the returns' or targets' scale. Verdict at alpha "
        f"{ALPHA}, from the adjusted p: supported when below alpha with the difference on the claimed side, "
        "contradicted when below alpha on the other side, inconclusive otherwise; too few runs to decide where the "
        "arms' sizes cannot give a p below the claim's threshold (alpha over its family's size for a primary claim, "
        f"alpha for an exploratory one). Only arms whose shared settings match are compared.{family} See "
        "`sb3_sera/experiments/claims.py` for each measure."
    )


def claims_section(results: Sequence[ClaimResult], sizes: dict[str, int] | None = None) -> list[str]:
    """
    The primary claims' tables, one a Holm family, then the exploratory claims' (labelled so), and the legend;
    ``sizes``: each family's number of claims (default: as many as ``results`` hold).
    """
    exploratory = [r for r in results if not r.claim.primary]
    lines: list[str] = []
    for family in families(results):
        lines += [
            f"Primary claims, family '{family[0].claim.family}' (Holm-adjusted within the family):",
            "",
            *claims_table(family, True),
            "",
        ]
    if exploratory:
        lines += [
            "Exploratory claims (Benjamini-Hochberg q-values over all of them):",
            "",
            *claims_table(exploratory, False),
            "",
        ]
    return [*lines, claims_legend(family_sizes(results) if sizes is None else sizes)] if lines else []


def bias_lines(groups: Sequence[Any]) -> list[str]:
    """Per group, the initial-state bias in the paper's signed form and in magnitude, after ``learning_starts``."""
    rows = []
    for group in groups:
        signed = [v for v in map(signed_bias, group.runs) if v is not None]
        if not signed:
            continue
        magnitude = [v for v in map(abs_bias, group.runs) if v is not None]
        relative = [v for v in map(relative_bias, group.runs) if v is not None]
        spread = stats.sample_std(signed)
        rows.append(
            f"| {group.label} | {len(signed)} | {np.mean(signed):.1f} ± {'n/a' if np.isnan(spread) else f'{spread:.1f}'} "
            f"| {np.mean(magnitude):.1f} | {np.mean(relative):.3f} | {sum(v < 0 for v in signed)} of {len(signed)} |"
        )
    if not rows:
        return []
    return [
        "| variant | n | V(s0) - G (mean ± std) | abs(V(s0) - G) | relative bias | runs underestimating |",
        "|---|---|---|---|---|---|",
        *rows,
        "",
        "Initial-state bias per run, averaged over the evaluations after learning_starts: V(s0) - G is what the paper's "
        "Fig. 4a plots (below 0: the critics underestimate the discounted return G of the evaluation episodes), its "
        "magnitude in return units, and the magnitude over the returns' scale.",
    ]
