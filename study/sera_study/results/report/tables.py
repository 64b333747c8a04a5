"""
The Markdown of one task-and-budget section: its table (per group: the final returns' IQM with its interval, mean
± std beside the paper's values, normalized AUC, probability that the reference variant improves on the group,
Welch's p-value, improvement in percent, initial-state bias, wall time) and the notes the reader must know.
"""

from collections import defaultdict
from collections.abc import Sequence

import numpy as np

from sera_study.records import FINAL_EVALUATIONS
from sera_study.registry import unmatched_settings, unmatched_text
from sera_study.results import stats
from sera_study.results.claims import group_settings, groups_unmatched
from sera_study.results.groups import RunGroup, differing_keys
from sera_study.results.report.paper import PAPER_NAMES, PAPER_RESULTS, paper_value

#: The variant every other row is compared against
REFERENCE = "serasac"
#: What every interval in the report is
INTERVAL = "95% stratified-bootstrap confidence interval (rliable, percentile method)"
#: Runs a group needs before an interval, a probability of improvement or a percentage is printed for it
MIN_RUNS = 3


def iqm_cell(values: np.ndarray, reps: int) -> str:
    """
    ``IQM [low, high]`` of one value per run; with fewer than :data:`MIN_RUNS` runs no interval (a bootstrap of one
    or two runs says nothing), and a dagger where the IQM trims nothing (n <= 3: it is the mean).
    """
    point, low, high = (float(v[0]) for v in stats.iqm_interval(values[:, None], reps))
    mark = "†" if len(values) <= 3 else ""
    if len(values) < MIN_RUNS:
        return f"{point:.1f}{mark} (n < {MIN_RUNS}: no interval)"
    return f"{point:.1f}{mark} [{low:.1f}, {high:.1f}]"


def reference_group(groups: Sequence[RunGroup]) -> tuple[RunGroup | None, str]:
    """
    The group every other row is compared against: the reference variant's, or with several settings its group of
    most runs (the first of those in table order); and a sentence saying which, when there was a choice.
    """
    references = [group for group in groups if group.variant == REFERENCE]
    if not references:
        return None, ""
    chosen = max(references, key=lambda group: len(group.runs))
    if len(references) == 1:
        return chosen, ""
    return chosen, f"{REFERENCE} has {len(references)} settings here: every row is compared against {chosen.label}."


def section_table(groups: Sequence[RunGroup], reps: int) -> list[str]:
    """One task and budget: a row per group (see the module's docstring), and what its columns are."""
    env_id, budget = groups[0].env_id, groups[0].n_timesteps
    paper = PAPER_RESULTS.get(env_id, {})
    reference, reference_note = reference_group(groups)
    lines = [
        f"| variant | n | final return IQM [95% CI] | final return mean ± std | paper at 300K (mean ± std) "
        f"| normalized AUC IQM [95% CI] | P({REFERENCE} > variant) [95% CI] | Welch p vs {REFERENCE} "
        f"| {REFERENCE} improvement % | initial-state bias (last) | wall time s |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for group in groups:
        finals, aucs = group.finals, group.aucs
        published = paper_value(env_id, group.variant)
        paper_cell = "" if published is None else f"{published[0]:g} ± {published[1]:g}"
        improvement_cell = p_cell = poi_cell = ""
        unmatched = groups_unmatched(reference, group) if reference is not None and group is not reference else {}
        if unmatched:
            poi_cell = p_cell = improvement_cell = f"unmatched ({', '.join(unmatched)})"
        elif reference is not None and group is not reference:
            p_value = stats.welch_p_value(reference.finals, finals)
            p_cell = "" if p_value is None else f"{p_value:.3f}"
            if min(len(reference.finals), len(finals)) < MIN_RUNS:
                poi_cell = improvement_cell = f"n < {MIN_RUNS}"
            else:
                poi = stats.probability_of_improvement(reference.finals[:, None], finals[:, None], reps)
                poi_cell = f"{poi[0]:.2f} [{poi[1]:.2f}, {poi[2]:.2f}]"
                if finals.mean() != 0:
                    improvement = stats.improvement_percent(float(reference.finals.mean()), float(finals.mean()))
                    improvement_cell = f"{improvement:+.1f}"
        biases = [run.initial_state_bias[-1] for run in group.runs if run.initial_state_bias]
        walls = [run.wall_time_s for run in group.runs if np.isfinite(run.wall_time_s)]
        std = stats.sample_std(finals)
        lines.append(
            f"| {group.label} | {len(finals)} | {iqm_cell(finals, reps)} "
            f"| {finals.mean():.1f} ± {'n/a' if np.isnan(std) else f'{std:.1f}'} | {paper_cell} "
            f"| {iqm_cell(aucs, reps)} | {poi_cell} | {p_cell} | {improvement_cell} "
            f"| {f'{np.mean(biases):.1f}' if biases else ''} | {f'{np.mean(walls):.0f}' if walls else ''} |"
        )
    lines += [
        "",
        f"n: runs (seeds) per row, {budget:,} steps each. Final return: the mean of a run's last {FINAL_EVALUATIONS} "
        f"evaluations' mean returns. IQM: interquartile mean over the runs (†: n <= 3, where it "
        f"trims nothing and is the mean); [a, b]: its {INTERVAL}, {reps} resamples, printed from {MIN_RUNS} runs on. "
        f"mean ± std: sample standard deviation (ddof 1). Normalized AUC: the area under the run's learning curve "
        f"divided by its length in steps (its average evaluation return). P({REFERENCE} > variant): probability that a "
        f"run of {REFERENCE} ends higher than a run of the variant, with its interval, and {REFERENCE}'s improvement in "
        f"percent of the variant's mean, both from {MIN_RUNS} runs a side on. Welch p: two-sided Welch's t-test on the "
        "final returns. Initial-state bias: mean V(s0) minus the mean discounted return at the last evaluation. "
        f"unmatched: the group trained with other shared settings than {REFERENCE}'s (below), so no comparison is "
        "printed.",
        "",
        *settings_lines(groups),
    ]
    if reference_note:
        lines += ["", reference_note]
    others = [name for name in paper if name not in {PAPER_NAMES.get(group.variant) for group in groups}]
    if others:
        lines += ["", "Paper only: " + ", ".join(f"{name} {paper[name][0]:g} ± {paper[name][1]:g}" for name in others)]
    return lines


def settings_lines(groups: Sequence[RunGroup]) -> list[str]:
    """
    The shared settings every group of the section trains with, and per group any that differ from the reference
    group's (such a row is no comparison of algorithms).
    """
    settings = {group.label: group_settings(group) for group in groups}
    keys = list(dict.fromkeys(key for group_settings_ in settings.values() for key in group_settings_))
    common = {}
    for key in keys:
        values = {repr(s[key]): s[key] for s in settings.values() if key in s}
        if len(values) == 1:
            common[key] = next(iter(values.values()))
    shared = ", ".join(f"{key}={value}" for key, value in common.items())
    lines = [f"Shared settings of every group that has them: {shared}."]
    for label, group_settings_ in settings.items():
        missing = [key for key in common if key not in group_settings_]
        if missing:
            lines.append(f"{label} has no {', '.join(missing)} (another kind of algorithm); its own are in its runs.")
    reference, _ = reference_group(groups)
    if reference is not None:
        for group in groups:
            if group is reference:
                continue
            pair = {reference.label: settings[reference.label], group.label: settings[group.label]}
            declared = unmatched_settings(pair)
            differing = groups_unmatched(reference, group)
            if differing:
                lines.append(f"Not matched to {reference.label}: {group.label} differs in {unmatched_text(differing)}.")
            elif declared:
                lines.append(
                    f"Declared difference (the comparison studies it): {group.label} differs from {reference.label} in "
                    f"{unmatched_text(declared)}."
                )
    return lines


def section_notes(groups: Sequence[RunGroup], all_groups: Sequence[RunGroup]) -> list[str]:
    """What the reader must know: variants split by settings, variants also run at other budgets, repeated seeds."""
    notes = []
    env_id, budget = groups[0].env_id, groups[0].n_timesteps
    by_variant: dict[str, list[RunGroup]] = defaultdict(list)
    for group in groups:
        by_variant[group.variant].append(group)
    for variant, siblings in by_variant.items():
        if len(siblings) > 1:
            keys = differing_keys([g.hyperparams for g in siblings])
            notes.append(
                f"- {variant}: {len(siblings)} sets of hyperparameters, differing in {', '.join(keys)}: listed apart, "
                "never averaged together."
            )
        other_budgets = sorted({g.n_timesteps for g in all_groups if (g.variant, g.env_id) == (variant, env_id)} - {budget})
        if other_budgets:
            notes.append(
                f"- {variant} also has runs of {', '.join(f'{b:,}' for b in other_budgets)} steps on this task, in their "
                "own section: runs of different budgets are never averaged together."
            )
        for group in siblings:
            seeds = [run.seed for run in group.runs]
            repeated = sorted({seed for seed in seeds if seeds.count(seed) > 1})
            if repeated:
                notes.append(f"- {group.label}: seed(s) {repeated} appear more than once (each run counts).")
    return notes


def resumed_lines(groups: Sequence[RunGroup]) -> list[str]:
    """The runs of ``groups`` resumed from a checkpoint, each with the steps it resumed from (and how that is known)."""
    lines = []
    for group in groups:
        for run in sorted(group.runs, key=lambda run: run.seed):
            for resume in run.resumes:
                how = f"; {resume['reconstructed']}" if resume.get("reconstructed") else ""
                lines.append(f"- {group.label}, seed {run.seed}: resumed from step {resume['from_step']:,}{how}")
    return ["Runs resumed from a checkpoint:", "", *lines] if lines else []
