"""
Writing ``report.md`` with its figures: a section per task and budget (table, the paper's mechanism claims, notes,
figures), the across-tasks section of each budget, and the folders left out; :func:`report_roots` is
``sb3-sera report``, and :func:`next_report_folder` gives a report a folder that no other report holds.
"""

from collections import defaultdict
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from sera_study.records import RunResult, env_name
from sera_study.results import stats
from sera_study.results.claims import ClaimResult, default_claims, evaluate
from sera_study.results.claims_text import bias_lines, claims_section, family_sizes
from sera_study.results.groups import RunGroup, group_runs
from sera_study.results.identity import IDENTITY_CHECK, identity_lines
from sera_study.results.report.aggregate import aggregate_section
from sera_study.results.report.figures import (
    plot_auc_bars,
    plot_correlation_matrices,
    plot_curves,
    plot_diagnostics,
    variant_colors,
)
from sera_study.results.report.load import Skipped, load_runs
from sera_study.results.report.paper import PAPER_STEPS, paper_value
from sera_study.results.report.tables import section_notes, section_table


def _curves_title(env_id: str, budget: int, groups: Sequence[RunGroup]) -> str:
    """The learning curves' title: the task and the runs' budget, and the last evaluation where the curves end before it."""
    last = max((run.timesteps[-1] for group in groups for run in group.runs if run.timesteps), default=budget)
    return f"{env_id}, {budget:,}-step runs" + (f" (last evaluation at {last:,})" if last < budget else "")


def _paper_points(env_id: str, budget: int, groups: Sequence[RunGroup]) -> dict[str, tuple[float, float]]:
    """
    The paper's value of each variant drawn on the learning curves, where the runs reach the paper's budget (below
    it, a point at 300K would squeeze the curves into a sixth of the axis).
    """
    if budget < PAPER_STEPS:
        return {}
    values = {group.variant: paper_value(env_id, group.variant) for group in groups}
    return {variant: value for variant, value in values.items() if value is not None}


def write_report(
    runs: Sequence[RunResult],
    out: str | Path,
    skipped: Sequence[Skipped] = (),
    reps: int = stats.REPS,
    matrix_step: int | None = None,
    sources: Sequence[str] = (),
    log: Callable[[str], None] | None = None,
    code_hashes: dict[str, dict[str, str]] | None = None,
    decided: Sequence[ClaimResult] | None = None,
    groups: Sequence[RunGroup] | None = None,
) -> Path:
    """
    Write ``report.md`` and its figures into the folder ``out`` (see the module's docstring).

    :param runs: finished runs (:func:`.load_runs`, or what ``compare``/``bench`` ran)
    :param skipped: folders left out, listed at the end with their reasons
    :param reps: bootstrap resamples of every interval
    :param matrix_step: the step whose correlation matrices are drawn (None: each run's last evaluation)
    :param sources: where the runs were read from, for the report's first line
    :param log: called with a line saying what the report is doing, section by section (None: silent)
    :param code_hashes: a ledger's code hashes per commit (:mod:`~sera_study.results.identity`): each section says
        whether its groups' runs from several commits train the same
    :param decided: claims decided elsewhere (a ledger's, :func:`~sera_study.results.ledger.read_ledger`), shown as
        they are; None: each section's :func:`~sera_study.results.claims.default_claims`, all exploratory, decided here
    :param groups: ``runs`` grouped already (:func:`~sera_study.results.groups.group_runs`), so that they are grouped
        once; None: grouped here
    :return: the path of ``report.md``
    """
    if not runs:
        raise ValueError("no finished runs to report")
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    all_groups = list(groups) if groups is not None else group_runs(runs)
    colors = variant_colors([group.variant for group in all_groups])
    sections_by_key: dict[tuple[str, int], list[RunGroup]] = defaultdict(list)
    for group in all_groups:
        sections_by_key[(group.env_id, group.n_timesteps)].append(group)
    lines = ["# Results", ""]
    if sources:
        lines += [f"Runs read from: {', '.join(sources)}.", ""]
    decided = list(decided) if decided is not None else evaluate(default_claims(all_groups), all_groups)
    sizes = family_sizes(decided)
    if sizes:
        lines += ["## Primary claims", "", *claims_section([r for r in decided if r.claim.primary], sizes), ""]
    for number, ((env_id, budget), groups) in enumerate(sections_by_key.items(), start=1):
        if log is not None:
            log(f"report: section {number}/{len(sections_by_key)}, {env_id} at {budget:,} steps: table, claims, figures")
        lines += section_text(groups, all_groups, section_claims(decided, env_id, budget), sizes, code_hashes, reps)
        lines += _section_figures(groups, folder, (env_id, budget), colors, reps, matrix_step)
    for budget in sorted({budget for _, budget in sections_by_key}):
        same_budget = [groups for (_, b), groups in sections_by_key.items() if b == budget]
        if len(same_budget) > 1:
            lines += aggregate_section(same_budget, folder=folder, colors=colors, reps=reps, budget=budget)
    waiting = [r for r in decided if (r.claim.task, r.claim.n_timesteps) not in sections_by_key]
    if waiting:
        lines += [
            "## Claims waiting for runs",
            "",
            *(f"- {r.claim.id} ({r.claim.task}, {r.claim.n_timesteps:,} steps): {r.note}" for r in waiting),
            "",
        ]
    if skipped:
        lines += ["## Left out", "", *(f"- {s.folder}: {s.reason}" for s in skipped), ""]
    report = folder / "report.md"
    report.write_text("\n".join(lines))
    return report


def _section_figures(
    groups: Sequence[RunGroup],
    folder: Path,
    section: tuple[str, int],
    colors: dict[str, Any],
    reps: int,
    matrix_step: int | None,
) -> list[str]:
    """
    A section's figures, drawn into ``folder``, and its lines that show them: the learning curves, the initial-state
    bias, the curves' areas, the critic diagnostics and the correlation matrices, each where the runs have it.
    """
    env_id, budget = section
    stem = f"{env_name(env_id)}_{budget}"
    lines: list[str] = []
    grid_notes = plot_curves(
        groups,
        attribute="returns",
        ylabel="evaluation return",
        title=_curves_title(env_id, budget, groups),
        path=folder / f"{stem}_curves.png",
        colors=colors,
        reps=reps,
        paper=_paper_points(env_id, budget, groups),
    )
    lines += [f"![{env_id} learning curves]({stem}_curves.png)", ""]
    lines += [f"- {note}" for note in grid_notes] + ([""] if grid_notes else [])
    if any(run.initial_state_bias for group in groups for run in group.runs):
        plot_curves(
            groups,
            attribute="initial_state_bias",
            ylabel="V(s0) - discounted return",
            title=f"Initial-state bias (Fig. 4a), {env_id}",
            path=folder / f"{stem}_bias.png",
            colors=colors,
            reps=reps,
            zero_line=True,
        )
        lines += [f"![{env_id} initial-state bias]({stem}_bias.png)", ""]
    if len(groups) > 1:
        plot_auc_bars(groups, path=folder / f"{stem}_auc.png", colors=colors, reps=reps)
        lines += [f"![{env_id} normalized AUC]({stem}_auc.png)", ""]
    lines += _diagnostics_lines(groups, folder / f"{stem}_diagnostics.png", env_id, colors, reps)
    matrices = plot_correlation_matrices(groups, folder / f"{stem}_correlations.png", matrix_step)
    if (folder / f"{stem}_correlations.png").exists():
        lines += [f"![{env_id} critic correlation matrices]({stem}_correlations.png)", ""]
    if matrices is not None:
        lines += [matrices, ""]
    return lines


def section_text(
    groups: Sequence[RunGroup],
    all_groups: Sequence[RunGroup],
    decided: Sequence[ClaimResult],
    sizes: dict[str, int],
    code_hashes: dict[str, dict[str, str]] | None,
    reps: int,
) -> list[str]:
    """One section's Markdown before its figures: the table, the claims, the bias table, code identity and notes."""
    env_id, budget = groups[0].env_id, groups[0].n_timesteps
    lines = [f"## {env_id}, {budget:,} steps", "", *section_table(groups, reps), ""]
    claims_lines = claims_section(decided, sizes)
    if claims_lines:
        lines += ["### The paper's claims", "", *claims_lines, ""]
    bias_table = bias_lines(groups)
    if bias_table:
        lines += ["### Initial-state bias", "", *bias_table, ""]
    identity = identity_lines(groups, code_hashes) if code_hashes is not None else []
    if identity:
        lines += [f"Code identity of groups run at several commits ({IDENTITY_CHECK}):", "", *identity, ""]
    notes = section_notes(groups, all_groups)
    if notes:
        lines += ["Notes:", *notes, ""]
    return lines


def section_claims(decided: Sequence[ClaimResult], env_id: str, budget: int) -> list[ClaimResult]:
    """The decided claims about one task and budget."""
    return [result for result in decided if (result.claim.task, result.claim.n_timesteps) == (env_id, budget)]


def report_roots(
    roots: Sequence[str | Path],
    out: str | Path,
    overwrite: bool = False,
    reps: int = stats.REPS,
    matrix_step: int | None = None,
    log: Callable[[str], None] | None = None,
) -> Path:
    """
    :func:`write_report` for every run under ``roots`` (see :func:`.load_runs`); refuses to overwrite an earlier
    report unless ``overwrite``.
    """
    if (Path(out) / "report.md").exists():
        if not overwrite:
            raise ValueError(f"{out} already holds a report.md: choose another --out, or pass --overwrite to replace it")
        # The earlier report's figures go with it: a figure it drew that this one does not would otherwise stay
        for stale in Path(out).glob("*.png"):
            stale.unlink()
    if log is not None:
        log(f"report: reading the runs under {', '.join(str(root) for root in roots)}")
    runs, skipped = load_runs(roots)
    if log is not None:
        log(f"report: {len(runs)} finished runs, {len(skipped)} folders left out")
    if not runs:
        reasons = "".join(f"; {s.folder}: {s.reason}" for s in skipped)
        raise ValueError(
            f"no finished runs (<root>/<variant>/<env_name>_<id>/ with its <env_name>/args.yml record and evaluations.npz) "
            f"under {[str(root) for root in roots]}{reasons}"
        )
    return write_report(
        runs, out, skipped=skipped, reps=reps, matrix_step=matrix_step, sources=[str(root) for root in roots], log=log
    )


def next_report_folder(parent: str | Path, name: str) -> Path:
    """``<parent>/<name>_<n>`` with the next free ``n`` (from 1), so that a report never replaces another."""
    parent = Path(parent)
    taken = [int(p.name.rpartition("_")[2]) for p in parent.glob(f"{name}_*") if p.name.rpartition("_")[2].isdigit()]
    return parent / f"{name}_{max(taken, default=0) + 1}"


def _diagnostics_lines(groups: Sequence[RunGroup], path: Path, env_id: str, colors: dict[str, Any], reps: int) -> list[str]:
    """The critic diagnostics' figure (:func:`.plot_diagnostics`) as Markdown, and what it left out, if anything."""
    not_drawn = plot_diagnostics(groups, path=path, colors=colors, reps=reps)
    lines = [f"![{env_id} critic diagnostics]({path.name})", ""] if path.exists() else []
    return lines + ([not_drawn, ""] if not_drawn else [])
