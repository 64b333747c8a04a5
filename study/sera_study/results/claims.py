"""
The claims the ledger tests and how each is decided.

A claim (:class:`Claim`) names a task, a budget, a measure, two arms and the claimed direction, and whether it is
primary; a ledger declares its claims in ``results/claims.yml`` (:func:`load_claims`), and a report of other runs
tests :func:`default_claims`, all exploratory. :func:`evaluate` decides them: only arms whose shared settings match
are compared; the size is the difference of means with its 95% Welch t-interval; the test's p is the larger of the
studentized permutation p and Welch's p (:func:`~sera_study.results.stats.decision_p_value`), so that no verdict
points where its interval does not. The primary claims' p-values are Holm-adjusted within their family (a declared
primary claim not yet tested counts with p = 1), the exploratory claims' turned into Benjamini-Hochberg q-values over
their exploratory family (all of them, but for claims declared in a family of their own; untested ones count with
p = 1). Verdicts at :data:`ALPHA`, read from the adjusted p: *supported* when it
is below alpha and the difference lies on the claimed side, *contradicted* when below it on the other side,
*inconclusive* otherwise; *too few runs to decide* where the arms' sizes cannot give a p below the claim's threshold
(alpha over the family's size for a primary claim, Holm's first; alpha for an exploratory one), and *interim* while a
claim with runs planned has fewer.

Beside them, for the readings: each exploratory claim's Benjamini-Yekutieli q-value (valid under any dependence
between the claims, which share runs), and each claim's verdict under the rule ``results/claims.yml`` first declared
(:func:`declared_rule_verdict`: the raw-difference permutation test, Holm within a primary family, exploratory claims
unadjusted, no test below three runs an arm), which the rule above replaced after the runs had been seen.
"""

import math
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from sera_study.records import RunResult
from sera_study.registry import SHARED_SETTINGS, shared_settings, unmatched_settings, unmatched_text
from sera_study.results import stats
from sera_study.results.groups import RunGroup
from sera_study.results.measures import MEASURES

#: Runs each arm needs before its interval is given (a test needs as many as can give a p below its threshold)
MIN_RUNS = 2
#: The variant the claims are about
SERA = "serasac"
#: Level of every test
ALPHA = 0.05
#: The family of a primary claim that names none
PRIMARY_FAMILY = "paper"
#: The family of an exploratory claim that names none (the claims declared before exploratory families existed)
EXPLORATORY_FAMILY = "exploratory"


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
    #: The claim's family, each adjusted on its own: Holm for a primary claim, Benjamini-Hochberg for an exploratory one
    #: (empty: :data:`PRIMARY_FAMILY` or :data:`EXPLORATORY_FAMILY`)
    family: str = ""
    #: Runs an arm the claim plans; with fewer it is interim and not decided (0: decided from MIN_RUNS on)
    planned: int = 0
    #: Shared settings the arms may differ in (systems compared each at its own settings)
    studies: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not self.family:
            object.__setattr__(self, "family", PRIMARY_FAMILY if self.primary else EXPLORATORY_FAMILY)

    def reads(self, run: RunResult) -> bool:
        """Whether the claim reads ``run``: its task and budget, one of its arms, a seed within :attr:`seeds`."""
        return self.reads_run(run.env_id, run.n_timesteps, run.variant, run.seed)

    def reads_run(self, env_id: Any, n_timesteps: Any, variant: str, seed: int) -> bool:
        """Whether the claim reads a run of ``variant`` on ``env_id`` at ``n_timesteps`` steps with ``seed``."""
        seeds = self.seeds or (seed, seed)
        return (
            (env_id, n_timesteps) == (self.task, self.n_timesteps)
            and variant in (self.arm, self.baseline)
            and seeds[0] <= seed <= seeds[1]
        )

    def shares_runs(self, other: "Claim") -> bool:
        """Whether the two claims can read a run in common (a variant, task, budget and seed they both read)."""
        same_runs = (self.task, self.n_timesteps) == (other.task, other.n_timesteps)
        common_variant = {self.arm, self.baseline} & {other.arm, other.baseline}
        first, last = self.seeds or (-math.inf, math.inf)
        other_first, other_last = other.seeds or (-math.inf, math.inf)
        return same_runs and bool(common_variant) and max(first, other_first) <= min(last, other_last)


def waits_for(claim: Claim, interim: Claim, lacking: Collection[str]) -> bool:
    """
    Whether ``claim`` is withheld while ``interim`` waits for runs (``lacking``: its arms below their planned count):
    it is that claim, or shares runs with it and belongs to its family (a family is decided together), or shares runs
    of an arm it lacks (whose runs are new). A claim of another family that shares only an arm ``interim`` has whole
    (runs printed before, such as a baseline's) is not: it tells nothing of ``interim``.
    """
    if claim is interim:
        return True
    if not claim.shares_runs(interim):
        return False
    return claim.family == interim.family or bool({claim.arm, claim.baseline} & set(lacking))


def _claims_document(path: str | Path) -> dict[str, Any]:
    """A claims file read: a mapping whose ``claims`` is a list; ``ValueError`` naming the file otherwise."""
    try:
        document = yaml.safe_load(Path(path).read_text())
    except yaml.YAMLError as error:
        raise ValueError(f"{path}: not YAML: {' '.join(str(error).split())}") from None
    if not isinstance(document, dict) or not isinstance(document.get("claims"), list):
        raise ValueError(f"{path}: a claims file is a mapping whose 'claims' is a list of claims")
    return document


def load_claims(path: str | Path) -> list[Claim]:
    """
    The claims a file declares (``results/claims.yml``: a mapping with ``claims``, a list of mappings with
    :data:`CLAIM_FIELDS`); ``ValueError`` naming the claim and the field for anything else.
    """
    document = _claims_document(path)
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
        primary = entry.get("primary", False)
        if not isinstance(primary, bool):
            raise ValueError(f"{where}: primary {primary!r} is not true or false")
        family = entry.get("family", PRIMARY_FAMILY if primary else EXPLORATORY_FAMILY)
        if not isinstance(family, str) or not family:
            raise ValueError(f"{where}: family {family!r} is not a name")
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
                primary=primary,
                source=str(entry.get("source", "")),
                seeds=(seeds[0], seeds[1]) if seeds is not None else None,
                family=family,
                planned=planned,
                studies=tuple(studies),
            )
        )
    _check_planned(claims, document.get("planned_after"), path)
    return claims


def _check_planned(claims: Sequence[Claim], planned_after: Any, path: str | Path) -> None:
    """
    ``ValueError`` naming a claim after ``planned_after`` (a claim's id: the file's ``planned_after``) that declares no
    planned runs: from that claim on, each is decided once its arms have the runs it plans, never as runs arrive.
    """
    if planned_after is None:
        return
    ids = [claim.id for claim in claims]
    if planned_after not in ids:
        raise ValueError(f"{path}: planned_after {planned_after!r} is not the id of one of its claims")
    for claim in claims[ids.index(planned_after) + 1 :]:
        if not claim.planned:
            raise ValueError(
                f"{path}: claim {claim.id!r} plans no runs: every claim declared after {planned_after!r} says how "
                "many runs an arm it waits for (planned: N), so that it is decided once, not as runs arrive"
            )


@dataclass(frozen=True)
class Seen:
    """
    Runs of an arm that were seen, under another variant's name, before the claims that read them were declared
    (``seen`` in a claims file): the same configuration, seeds and code, so the same bits. Each claim on the arm is
    also given without them (:func:`~sera_study.results.declared.unseen_lines`); nothing of the claims changes.
    """

    #: The arm whose runs were seen, and the task they ran on
    arm: str
    task: str
    #: Their seeds
    seeds: tuple[int, ...]
    #: The variant they were seen as
    seen_as: str


#: The fields of a ``seen`` entry
SEEN_FIELDS = ("arm", "task", "seeds", "as")


def load_seen(path: str | Path) -> list[Seen]:
    """
    The ``seen`` entries of a claims file (none where it has no ``seen``): each a mapping with :data:`SEEN_FIELDS`,
    the seeds a list of integers; ``ValueError`` naming the entry and the field for anything else.
    """
    entries = _claims_document(path).get("seen", [])
    if not isinstance(entries, list):
        raise ValueError(f"{path}: 'seen' is not a list of mappings with {list(SEEN_FIELDS)}")
    seen = []
    for index, entry in enumerate(entries):
        where = f"{path}: seen entry {index + 1}"
        if not isinstance(entry, dict) or sorted(entry) != sorted(SEEN_FIELDS):
            raise ValueError(f"{where}: {entry!r} is not a mapping with exactly {list(SEEN_FIELDS)}")
        seeds = entry["seeds"]
        if not isinstance(seeds, list) or not seeds or not all(isinstance(seed, int) for seed in seeds):
            raise ValueError(f"{where}: seeds {seeds!r} is not a list of integers")
        seen.append(Seen(str(entry["arm"]), str(entry["task"]), tuple(seeds), str(entry["as"])))
    return seen


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


def default_claims(groups: Sequence[RunGroup]) -> list[Claim]:
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


def group_settings(group: RunGroup) -> dict[str, Any]:
    """A report group's shared settings: :func:`~sera_study.registry.shared_settings` and evaluations."""
    evaluation: dict[str, Any] = {
        key: group.hyperparams[key] for key in ("eval_freq", "eval_episodes") if key in group.hyperparams
    }
    return {**shared_settings(group.algo, group.hyperparams), **evaluation}


def group_studies(group: RunGroup) -> set[str]:
    """The shared settings every run of a report group recorded as studied by its comparison."""
    return set.intersection(*(set(run.studies) for run in group.runs)) if group.runs else set()


def groups_unmatched(first: RunGroup, second: RunGroup, studied: Sequence[str] = ()) -> dict[str, dict[str, Any]]:
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
    #: An exploratory claim's Benjamini-Yekutieli q-value (any dependence between the claims)
    by_q: float | None = None
    #: The raw-difference permutation p of the rule first declared (:func:`declared_rule_verdict`)
    declared_p: float | None = None
    #: The verdict under the rule first declared
    declared_verdict: str = ""
    verdict: str = "waiting for runs"
    #: Why there is no test, or which settings group was used
    note: str = ""
    #: Its arms' means are not shown: the claim is interim, or reads runs of an interim claim
    withheld: bool = False


def _matched_groups(claim: Claim, groups: Sequence[RunGroup]) -> tuple[RunGroup | None, RunGroup | None, str]:
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


def evaluate(claims: Sequence[Claim], groups: Sequence[RunGroup], alpha: float = ALPHA) -> list[ClaimResult]:
    """
    Decide every claim on the report groups (:func:`~sera_study.results.groups.group_runs`): see the
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
    _declared_rule(results, alpha)
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
    Withhold every number of a claim that waits for an interim claim (:func:`waits_for`: it would tell the interim
    state): its difference, interval, p-values and arms' means; it enters the multiplicity adjustments as untested
    (p = 1).
    """
    interim = {
        result.claim.id: (result.claim, _lacking(result))
        for result in results
        if result.claim.planned and result.verdict.startswith("interim")
    }
    for result in results:
        holding = [
            claim.id
            for claim, lacking in interim.values()
            if claim is not result.claim and waits_for(result.claim, claim, lacking)
        ]
        if holding and not result.withheld:
            result.difference = result.low = result.high = None
            result.p_value = result.permutation_p = result.welch_p = None
            result.verdict, result.withheld = f"withheld while {', '.join(holding)} is interim", True


def _lacking(result: ClaimResult) -> set[str]:
    """The arms of ``result``'s claim with fewer runs than it plans."""
    claim = result.claim
    counts = {claim.arm: len(result.arm_values), claim.baseline: len(result.baseline_values)}
    return {arm for arm, count in counts.items() if count < claim.planned}


def _adjust(results: Sequence[ClaimResult]) -> None:
    """Each tested claim's adjusted p: Holm within its primary family, or its q-value within its exploratory family."""
    for family in families(results):
        adjusted = stats.holm_adjusted([1.0 if r.p_value is None else r.p_value for r in family])
        for result, p_adjusted in zip(family, adjusted, strict=True):
            if result.p_value is not None:
                result.adjusted_p = p_adjusted
    for exploratory in families(results, primary=False):
        p_values = [1.0 if r.p_value is None else r.p_value for r in exploratory]
        q_values = zip(stats.benjamini_hochberg(p_values), stats.benjamini_yekutieli(p_values), strict=True)
        for result, (q, by_q) in zip(exploratory, q_values, strict=True):
            if result.p_value is not None:
                result.adjusted_p, result.by_q = q, by_q


#: The fewest runs an arm the rule first declared tested
DECLARED_MIN_RUNS = 3


def _declared_rule(results: Sequence[ClaimResult], alpha: float) -> None:
    """Each tested claim's verdict under the rule first declared (:func:`declared_rule_verdict`)."""
    for result in results:
        if result.p_value is not None and min(len(result.arm_values), len(result.baseline_values)) >= DECLARED_MIN_RUNS:
            result.declared_p = stats.raw_permutation_p_value(result.arm_values, result.baseline_values)
    for family in families(results):
        tested = [result for result in family if result.declared_p is not None]
        holm = stats.holm_adjusted([result.declared_p for result in tested if result.declared_p is not None])
        for result, adjusted in zip(tested, holm, strict=True):
            result.declared_verdict = declared_rule_verdict(result, adjusted, alpha)
    for result in results:
        if not result.claim.primary and result.declared_p is not None:
            result.declared_verdict = declared_rule_verdict(result, result.declared_p, alpha)


def declared_rule_verdict(result: ClaimResult, p_value: float, alpha: float = ALPHA) -> str:
    """
    The verdict of the rule ``results/claims.yml`` first declared, from ``p_value``: the raw-difference permutation
    test's p (:func:`~sera_study.results.stats.raw_permutation_p_value`), Holm-adjusted over the family's tested
    claims for a primary claim, unadjusted for an exploratory one; supported below alpha on the claimed side,
    contradicted below alpha on the other, inconclusive otherwise.
    """
    assert result.difference is not None
    claimed_side = result.difference < 0 if result.claim.direction == "lower" else result.difference > 0
    return ("supported" if claimed_side else "contradicted") if p_value < alpha else "inconclusive"


def families(results: Sequence[ClaimResult], primary: bool = True) -> list[list[ClaimResult]]:
    """
    The primary claims' results by Holm family (``primary=False``: the exploratory claims' by Benjamini-Hochberg
    family), in the order the families are first declared.
    """
    grouped: dict[str, list[ClaimResult]] = {}
    for result in results:
        if result.claim.primary == primary:
            grouped.setdefault(result.claim.family, []).append(result)
    return list(grouped.values())
