"""
The across-tasks section of one budget: each final return normalized by its task's fixed reference scores (the
paper's), then per variant the IQM over runs and tasks with its interval, and performance profiles.
"""

from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sera_study.results import stats
from sera_study.results.groups import RunGroup, variant_rank
from sera_study.results.report.figures import pyplot, save_figure
from sera_study.results.report.paper import paper_reference
from sera_study.results.report.tables import INTERVAL


def aggregate_section(
    sections: Sequence[list[RunGroup]], folder: Path, colors: dict[str, Any], reps: int, budget: int
) -> list[str]:
    """
    Scores aggregated over the task sections of one budget: each final return normalized by its task's fixed
    reference scores (:func:`.paper_reference`: 0 at the paper's lowest column, 1 at the paper's SERA), then per
    variant (one settings group per section, the same number of runs in each) the IQM over runs and tasks with its
    interval, and performance profiles.
    """
    scores: dict[str, list[np.ndarray]] = defaultdict(list)
    counts: dict[str, set[int]] = defaultdict(set)
    referenced = [groups for groups in sections if paper_reference(groups[0].env_id) is not None]
    unreferenced = sorted({groups[0].env_id for groups in sections} - {groups[0].env_id for groups in referenced})
    lines = [f"## Across tasks, {budget:,} steps", ""]
    if unreferenced:
        lines += [f"Left out, with no reference scores in the paper: {', '.join(unreferenced)}.", ""]
    if len(referenced) < 2:
        return [*lines, "Fewer than two tasks with reference scores: nothing aggregated.", ""]
    for groups in referenced:
        low, high = paper_reference(groups[0].env_id)  # type: ignore[misc]
        variants = [group.variant for group in groups]
        for group in groups:
            if variants.count(group.variant) == 1:
                scores[group.variant].append(stats.min_max_normalized(group.finals, low, high))
                counts[group.variant].add(len(group.runs))
    kept = {v: np.stack(s, axis=1) for v, s in scores.items() if len(s) == len(referenced) and len(counts[v]) == 1}
    left_out = sorted(set(scores) - set(kept), key=variant_rank)
    tasks = ", ".join(groups[0].env_id for groups in referenced)
    lines += [
        f"Final returns normalized by fixed reference scores per task (0: the lowest mean of the paper's columns at "
        f"300K, 1: the paper's SERA), over {len(referenced)} tasks: {tasks}.",
        "",
    ]
    if not kept:
        return [
            *lines,
            "No variant has one settings group with the same number of runs in every task: nothing aggregated.",
            "",
        ]
    lines += ["| variant | runs x tasks | normalized score IQM [95% CI] |", "|---|---|---|"]
    for variant in sorted(kept, key=variant_rank):
        point, low, high = (v[0] for v in stats.iqm_interval(kept[variant], reps))
        lines.append(
            f"| {variant} | {kept[variant].shape[0]} x {kept[variant].shape[1]} | {point:.2f} [{low:.2f}, {high:.2f}] |"
        )
    lines += ["", f"IQM over runs and tasks; [a, b]: {INTERVAL}, runs resampled within each task, {reps} resamples."]
    if left_out:
        lines += [f"Left out (not in every task with one settings group and equal run counts): {', '.join(left_out)}."]
    all_scores = np.concatenate([values.ravel() for values in kept.values()])
    thresholds = np.linspace(min(0.0, float(all_scores.min())), max(1.0, float(all_scores.max())), 41)
    profiles, bands = stats.performance_profile(kept, thresholds, reps)
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    for variant in sorted(kept, key=variant_rank):
        ax.step(
            thresholds, profiles[variant], where="post", color=colors[variant], label=f"{variant} (n={kept[variant].size})"
        )
        ax.fill_between(thresholds, bands[variant][0], bands[variant][1], step="post", color=colors[variant], alpha=0.2)
    ax.set_xlabel("normalized score τ")
    ax.set_ylabel("fraction of runs with score > τ")
    ax.set_title(f"Performance profiles, {budget:,} steps; band: 95% stratified-bootstrap CI", fontsize=10)
    ax.legend(fontsize="small")
    name = f"performance_profiles_{budget}.png"
    save_figure(fig, folder / name)
    return [*lines, "", f"![performance profiles]({name})", ""]
