"""The claims' Markdown: their tables (one a Holm family, then the exploratory claims), the legend, the bias table."""

from collections.abc import Sequence
from typing import Any

import numpy as np

from sera_study.results import stats
from sera_study.results.claims import ALPHA, ClaimResult, families
from sera_study.results.measures import MEASURES, abs_bias, relative_bias, signed_bias


def format_number(value: float | None) -> str:
    """A number as the claims tables print it: 3 significant digits below 1000, whole above (empty for None)."""
    if value is None:
        return ""
    return f"{value:.3g}" if abs(value) < 1000 else f"{value:.0f}"


def p_text(value: float | None) -> str:
    """A p- or q-value as the claims tables print it: 4 decimals, or ``< 0.0001`` (empty for None)."""
    return "" if value is None else f"{value:.4f}" if value >= 0.0001 else "< 0.0001"


def interval_text(result: ClaimResult) -> str:
    """A claim's difference with its Welch interval, as the claims tables print it (the difference alone without one)."""
    difference = format_number(result.difference)
    if result.low is None:
        return difference
    return f"{difference} [{format_number(result.low)}, {format_number(result.high)}]"


def claims_table(results: Sequence[ClaimResult], primary: bool) -> list[str]:
    """
    A Markdown table of ``results``: each claim's difference with its interval, Welch's and the studentized
    permutation p, and the p its verdict reads (Holm-adjusted for primary claims, the q-value for exploratory ones).
    """
    if not results:
        return []
    adjusted = "Holm p" if primary else "BH q | BY q"
    lines = [
        "| claim | source | measure (per run) | units | SERA vs | n | SERA mean | baseline mean "
        f"| difference [95% Welch CI] | Welch p | permutation p | {adjusted} | verdict |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|" + ("" if primary else "---|"),
    ]
    for result in results:
        claim, measure = result.claim, MEASURES[result.claim.measure]
        interval = interval_text(result)
        shown = not result.withheld
        arm_mean = format_number(float(result.arm_values.mean())) if shown and len(result.arm_values) else ""
        base_mean = format_number(float(result.baseline_values.mean())) if shown and len(result.baseline_values) else ""
        verdict = result.verdict + (f" ({result.note})" if result.note else "")
        if rests_on_bh_alone(result):
            verdict += f" (BH alone: BY q {p_text(result.by_q)})"
        q_values = p_text(result.adjusted_p) + ("" if primary else f" | {p_text(result.by_q)}")
        lines.append(
            f"| {claim.id}: SERA {claim.direction} | {claim.source} | {measure.text} "
            f"| {'paper' if measure.paper_units else 'scale-free'} | {claim.baseline} "
            f"| {len(result.arm_values)} vs {len(result.baseline_values)} | {arm_mean} | {base_mean} | {interval} "
            f"| {p_text(result.welch_p)} | {p_text(result.permutation_p)} | {q_values} | {verdict} |"
        )
    return lines


def rests_on_bh_alone(result: ClaimResult) -> bool:
    """Whether an exploratory verdict (supported or contradicted) stands on its BH q-value but not on its BY q-value."""
    decided = result.verdict in ("supported", "contradicted")
    return decided and not result.claim.primary and result.by_q is not None and result.by_q >= ALPHA


def declared_rule_lines(results: Sequence[ClaimResult]) -> list[str]:
    """The tested claims whose verdict under the rule first declared differs from the verdict of the rule in force."""
    tested = [result for result in results if result.declared_verdict]
    differing = [result for result in tested if result.declared_verdict != result.verdict]
    if not tested:
        return []
    lines = [
        "Under the rule `results/claims.yml` first declared, which the rule above replaced after every run of the "
        "claims then declared had been seen (the raw-difference permutation test, Holm within a primary family, "
        "exploratory claims unadjusted, no test below three runs an arm; claims declared since were declared under the "
        f"rule above, and are read under both too), {len(tested) - len(differing)} of the {len(tested)} tested "
        "claims read the same" + (", and these differently:" if differing else "."),
    ]
    if differing:
        lines.append("")
        lines += [
            f"- {result.claim.id}: {result.declared_verdict} under the first rule (raw permutation p "
            f"{p_text(result.declared_p)}{'' if result.claim.primary else ', unadjusted'}), {result.verdict} under "
            "the rule in force"
            for result in differing
        ]
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
        "not, adjusted for multiplicity: Holm within a primary family, Benjamini-Hochberg (BH) q-values within an "
        "exploratory family (one, 'exploratory', unless the claims file declares others; untested claims count with "
        "p = 1); beside them each exploratory claim's Benjamini-Yekutieli "
        "(BY) q-value, valid whatever the dependence between claims that share runs, and a verdict that stands on BH "
        "alone is marked so. Units: 'paper' is the measure the paper plots, "
        "'scale-free' our form of it normalised by the returns' or targets' scale. Verdict at alpha "
        f"{ALPHA}, from the adjusted p: supported when below alpha with the difference on the claimed side, "
        "contradicted when below alpha on the other side, inconclusive otherwise; too few runs to decide where the "
        "arms' sizes cannot give a p below the claim's threshold (alpha over its family's size for a primary claim, "
        f"alpha for an exploratory one). Only arms whose shared settings match are compared.{family} See "
        "`study/sera_study/results/measures.py` for each measure."
    )


def claims_section(results: Sequence[ClaimResult], sizes: dict[str, int] | None = None) -> list[str]:
    """
    The primary claims' tables, one a Holm family, then the exploratory claims' (labelled so), and the legend;
    ``sizes``: each family's number of claims (default: as many as ``results`` hold).
    """
    lines: list[str] = []
    for family in families(results):
        lines += [
            f"Primary claims, family '{family[0].claim.family}' (Holm-adjusted within the family):",
            "",
            *claims_table(family, True),
            "",
        ]
    for exploratory in families(results, primary=False):
        lines += [
            f"Exploratory claims, family '{exploratory[0].claim.family}' (Benjamini-Hochberg q-values within the "
            "family, Benjamini-Yekutieli's beside them):",
            "",
            *claims_table(exploratory, False),
            "",
        ]
    declared = declared_rule_lines(results)
    if declared:
        lines += [*declared, ""]
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
