"""
The report's figures: learning curves and the initial-state bias over training (paper Fig. 4a), the normalized AUC
(Fig. 4b), the critic diagnostics over training (Fig. 4c) and the critics' correlation matrices (Fig. 5). Each curve
is the IQM over a group's runs with its interval, on one grid when runs were evaluated at different steps; a variant
has the same colour in every figure.
"""

import warnings
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from sera_study.results import stats
from sera_study.results.groups import RunGroup
from sera_study.results.measures import load_diagnostics
from sera_study.results.report.paper import PAPER_NAMES, PAPER_STEPS
from sera_study.results.report.tables import MIN_RUNS

#: Points of the common grid onto which curves evaluated at different steps are interpolated
GRID_POINTS = 50


def aligned(series: Sequence[tuple[ArrayLike, ArrayLike]]) -> tuple[np.ndarray, np.ndarray, str]:
    """
    Curves of several runs on one grid: their own steps when all share them, else ``GRID_POINTS`` points over the
    steps all of them cover, each curve interpolated linearly.

    :param series: per run, its steps and values
    :return: the grid, the values (runs x points) and a sentence saying which grid it is
    """
    steps = [np.asarray(t, dtype=float) for t, _ in series]
    values = [np.asarray(v, dtype=float) for _, v in series]
    if all(s.shape == steps[0].shape and np.array_equal(s, steps[0]) for s in steps):
        return steps[0], np.stack(values), ""
    start, stop = max(s[0] for s in steps), min(s[-1] for s in steps)
    if stop <= start:
        stop = start
    grid = np.linspace(start, stop, GRID_POINTS)
    matrix = np.stack([np.interp(grid, s, v) for s, v in zip(steps, values, strict=True)])
    return (
        grid,
        matrix,
        f"runs evaluated at different steps: interpolated onto {GRID_POINTS} points from {start:,.0f} to {stop:,.0f}",
    )


#: The known variants' colours, the same in every report (SAC and MASAC share one: never in the same section)
VARIANT_COLORS = {
    "serasac": "C0", "sac": "C1", "masac": "C1", "ensemble_mean": "C2", "matd3": "C3", "sera_nolr": "C4",
    "sera_median": "C5", "sera_nolr_matched": "olive", "sunrise": "C6", "maddpg": "C7", "ace": "C8", "iet": "C9",
    "mappo": "black",
}  # fmt: skip


def variant_colors(variants: Sequence[str]) -> dict[str, Any]:
    """One colour per variant for every figure: the known variants' own, then the others from another palette."""
    from matplotlib import colormaps

    others = sorted(set(variants) - set(VARIANT_COLORS))
    palette = colormaps["Dark2"]
    return {**VARIANT_COLORS, **{variant: palette(index % palette.N) for index, variant in enumerate(others)}}


def pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, path: Path) -> None:
    """
    Save ``fig`` at ``path`` and close it, laid out by matplotlib's tight layout, or, where that layout cannot fit
    the axes (a grid of many panels under a title), cropped to what it draws.
    """
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fig.tight_layout()
    fitted = True
    for warning in caught:
        if "Tight layout not applied" in str(warning.message):
            fitted = False
        else:
            warnings.warn_explicit(warning.message, warning.category, warning.filename, warning.lineno)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, **({} if fitted else {"bbox_inches": "tight"}))
    pyplot().close(fig)


def _draw_band(
    ax: Any, series: Sequence[tuple[ArrayLike, ArrayLike]], reps: int, label: str, color: Any, linestyle: str = "-"
) -> str:
    """
    IQM over runs with its bootstrap interval as a band (from :data:`MIN_RUNS` runs on, as the tables print
    intervals); returns the grid's sentence (empty for shared steps).
    """
    grid, matrix, note = aligned(series)
    point, low, high = stats.iqm_interval(matrix[:, None, :], reps)
    ax.plot(grid, point, color=color, linestyle=linestyle, label=f"{label} (n={len(series)})")
    if len(series) < MIN_RUNS:
        return note
    if linestyle == "-":
        ax.fill_between(grid, low, high, color=color, alpha=0.2)
    else:
        # A second settings group of the same variant: its band hatched, so that the two bands stay apart
        ax.fill_between(grid, low, high, facecolor="none", edgecolor=color, hatch="///", linewidth=0.0, alpha=0.6)
    return note


def _linestyles(groups: Sequence[RunGroup]) -> dict[int, str]:
    """Groups of one variant share its colour and differ by line style."""
    styles = ("-", "--", ":", "-.")
    seen: dict[str, int] = defaultdict(int)
    result = {}
    for group in groups:
        result[id(group)] = styles[seen[group.variant] % len(styles)]
        seen[group.variant] += 1
    return result


def plot_curves(
    groups: Sequence[RunGroup], attribute: str, ylabel: str, title: str, path: Path, colors: dict[str, Any], reps: int,
    zero_line: bool = False, paper: dict[str, tuple[float, float]] | None = None,
) -> list[str]:  # fmt: skip
    """
    A per-run list (``returns`` or ``initial_state_bias``) against steps: IQM over each group's runs and its interval.

    :param paper: per variant, the paper's (mean, std) at :data:`~sera_study.results.report.paper.PAPER_STEPS`, drawn there
        as a marker with its std as a bar in the variant's colour
    :return: sentences on interpolated grids
    """
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    styles, notes = _linestyles(groups), []
    for group in groups:
        series = [
            (run.timesteps[: len(getattr(run, attribute))], getattr(run, attribute))
            for run in group.runs
            if getattr(run, attribute)
        ]
        if series:
            note = _draw_band(
                ax, series, reps=reps, label=group.label, color=colors[group.variant], linestyle=styles[id(group)]
            )
            if note:
                notes.append(f"{group.label}: {note}")
    if zero_line:
        ax.axhline(0.0, color="black", linewidth=0.8)
    paper = paper or {}
    for index, (variant, (mean, std)) in enumerate(paper.items()):
        # Side by side about the paper's budget, a step apart of 1.5% of it, so that no bar hides another
        dodge = (index - (len(paper) - 1) / 2) * 0.015 * PAPER_STEPS
        ax.errorbar(
            PAPER_STEPS + dodge, mean, yerr=std, color=colors[variant], marker="D", capsize=4, linestyle="none",
            label=f"paper, {PAPER_NAMES[variant]} (mean ± std)",
        )  # fmt: skip
    ax.set_xlabel("environment steps")
    ax.set_ylabel(ylabel)
    ax.set_title(f"{title}\nIQM over runs, band: 95% stratified-bootstrap CI (n >= {MIN_RUNS})", fontsize=10)
    ax.legend(fontsize="small")
    save_figure(fig, path)
    return notes


#: The diagnostics figure's panels: record key, title, y label
DIAGNOSTIC_PANELS = (
    ("td_target_var", "TD-target variance", "Var_batch(y) (return units²)"),
    ("td_target_relative_var", "normalised TD-target variance (Fig. 4c)", "Var_batch(y) / mean_batch(y²)"),
    ("critic_lr", "critic learning rate (adaptive: per critic)", "learning rate (mean over critics; dotted: min, max)"),
    ("critic_corr", "critics' value correlation", "mean off-diagonal Pearson r of Q_i"),
    ("td_error_corr", "critics' TD-error correlation", "mean off-diagonal Pearson r of δ_i"),
    (
        "mc_error_corr",
        "critics' error correlation vs Monte Carlo returns (Fig. 5)",
        "mean off-diagonal Pearson r of Q_i - G",
    ),
)


def _finite_series(runs: Sequence[dict[str, np.ndarray]], key: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each run's curve of ``key`` (a per-critic quantity: its mean over critics), evaluations without a value left out."""
    series = []
    for r in runs:
        if key not in r:
            continue
        values = r[key] if r[key].ndim == 1 else r[key].mean(axis=1)
        finite = np.isfinite(values)
        if finite.any():
            series.append((r["timesteps"][finite], values[finite]))
    return series


def plot_diagnostics(groups: Sequence[RunGroup], path: Path, colors: dict[str, Any], reps: int) -> str | None:
    """
    One panel per quantity of :data:`DIAGNOSTIC_PANELS` that some run recorded a value of, IQM over runs and interval
    per group; per-critic learning rates summarized by their mean (line and band) and their smallest and largest
    (dotted). A quantity without any value gets no panel.

    :return: None where no group had diagnostics (no figure); else a sentence naming the quantities not drawn and the
        variants without diagnostics, and why ("" where all were drawn)
    """
    records = {id(group): [d for d in map(load_diagnostics, group.runs) if d is not None] for group in groups}
    if not any(records.values()):
        return None
    panels = [panel for panel in DIAGNOSTIC_PANELS if any(_finite_series(runs, panel[0]) for runs in records.values())]
    left_out = [f"{panel[1]}, {_empty_reason(panel[0], records)}" for panel in DIAGNOSTIC_PANELS if panel not in panels]
    not_drawn = f"Critic diagnostics not drawn: {'; '.join(left_out)}." if left_out else ""
    without = sorted({group.variant for group in groups if not records[id(group)]})
    if without:
        not_drawn = (
            f"{not_drawn} Not drawn, with no critic diagnostics in any run: {', '.join(without)} (they are recorded for "
            "the algorithms built on SB3's SAC, SAC, SERASAC, MASAC and IET, whose soft Q critics they read)."
        ).strip()
    if not panels:
        path.unlink(missing_ok=True)  # a report written over an older one keeps no stale figure
        return not_drawn
    plt = pyplot()
    n_columns = min(3, len(panels))
    n_rows = -(-len(panels) // n_columns)
    fig, axes_grid = plt.subplots(n_rows, n_columns, figsize=(5 * n_columns, 4.2 * n_rows), squeeze=False)
    axes = axes_grid.ravel()
    for ax in axes[len(panels) :]:
        ax.axis("off")
    styles = _linestyles(groups)
    for group in groups:
        runs = records[id(group)]
        color = colors[group.variant]
        for ax, (key, _, _) in zip(axes, panels, strict=False):
            series = _finite_series(runs, key)
            if not series:
                continue
            _draw_band(ax, series, reps=reps, label=group.label, color=color, linestyle=styles[id(group)])
            having = [r for r in runs if key in r]
            if having[0][key].ndim == 2:
                for reduce in (np.min, np.max):
                    grid, matrix, _ = aligned([(r["timesteps"], reduce(r[key], axis=1)) for r in having])
                    ax.plot(grid, stats.iqm(matrix[:, None, :]), color=color, linestyle=":", linewidth=0.9)
    for ax, (key, title, ylabel) in zip(axes, panels, strict=False):
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("environment steps")
        ax.set_ylabel(ylabel)
        if key in ("td_target_var", "td_target_relative_var"):
            ax.set_yscale("log")
        ax.legend(fontsize="x-small")
    fig.suptitle(
        "Critic diagnostics at each evaluation (1024 replayed transitions; Monte Carlo errors: the evaluation episodes' "
        "steps); IQM over runs, band: 95% bootstrap CI",
        fontsize=10,
    )
    save_figure(fig, path)
    return not_drawn


def _empty_reason(key: str, records: dict[int, list[dict[str, np.ndarray]]]) -> str:
    """Why a diagnostic has no curve: no run recorded the quantity, or none recorded a finite value of it."""
    recorded = [r for runs in records.values() for r in runs if key in r]
    if not recorded:
        return f"no run recorded {key}: an older record, or an algorithm without this diagnostic"
    if key == "mc_error_corr":
        return (
            "no finite value: no evaluation state had a complete Monte Carlo return, which needs an episode that runs "
            "past the discount's horizon after it"
        )
    return f"no finite value of {key} at any evaluation"


def plot_auc_bars(groups: Sequence[RunGroup], path: Path, colors: dict[str, Any], reps: int) -> None:
    """
    Normalized AUC per group (paper Fig. 4b): IQM over runs as a marker with its interval, runs as dots, on an axis
    fitted to the values (not drawn from zero, so that differences between groups show whatever the sign).
    """
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(max(1.6 * len(groups) + 2, 6.0), 4.8))
    for index, group in enumerate(groups):
        aucs = group.aucs
        point, low, high = (value[0] for value in stats.iqm_interval(aucs[:, None], reps))
        # No interval below MIN_RUNS runs, as in the tables
        error = [[point - low], [high - point]] if len(aucs) >= MIN_RUNS else None
        ax.errorbar(
            index, point, yerr=error, color=colors[group.variant], marker="s", markersize=9, capsize=6, linewidth=2,
        )  # fmt: skip
        ax.scatter(np.full(len(aucs), index + 0.15), aucs, color="black", s=12, zorder=3)
    ax.set_xticks(range(len(groups)), [f"{g.label}\n(n={len(g.runs)})" for g in groups], fontsize=8)
    ax.set_xlim(-0.6, len(groups) - 0.4)
    ax.set_ylabel("normalized AUC (average evaluation return)")
    ax.grid(axis="y", alpha=0.3)
    ax.set_title(
        f"Normalized AUC (Fig. 4b)\nsquare: IQM over runs; bar: 95% stratified-bootstrap CI (n >= {MIN_RUNS})\ndots: runs",
        fontsize=9,
    )
    save_figure(fig, path)


#: The correlation matrices drawn (paper Fig. 5), one row each: record key and what it correlates
MATRIX_ROWS = (
    ("mc_error_corr_matrix", "errors vs Monte Carlo returns"),
    ("td_error_corr_matrix", "TD errors δ_i"),
    ("critic_corr_matrix", "values Q_i"),
)


def _off_diagonal_mean(matrix: np.ndarray) -> float:
    return float(matrix[~np.eye(len(matrix), dtype=bool)].mean())


def _off_diagonal_min(matrix: np.ndarray) -> float:
    return float(matrix[~np.eye(len(matrix), dtype=bool)].min())


#: A correlation that prints as 1.000: a matrix row whose every pair reaches it is not drawn
SATURATED = 0.9995


def _median_matrices(
    group: RunGroup, rows: Sequence[tuple[str, str]], step: int | None
) -> dict[str, tuple[np.ndarray, int, int, int]]:
    """
    Per matrix of ``rows`` that the group's runs recorded (K >= 3, finite) at the evaluation nearest ``step`` (None:
    the last): the median run's matrix by mean off-diagonal correlation, its seed, its step and the number of runs.
    """
    chosen: dict[str, tuple[np.ndarray, int, int, int]] = {}
    for key, _ in rows:
        candidates = []
        for run in group.runs:
            records = load_diagnostics(run)
            if records is None or key not in records or records[key].shape[-1] < 3:
                continue
            target = records["timesteps"][-1] if step is None else step
            index = int(np.argmin(np.abs(records["timesteps"] - target)))
            if np.isfinite(records[key][index]).all():
                candidates.append((records[key][index], run.seed, int(records["timesteps"][index])))
        if candidates:
            candidates.sort(key=lambda item: _off_diagonal_mean(item[0]))
            matrix, seed, at = candidates[(len(candidates) - 1) // 2]
            chosen[key] = (matrix, seed, at, len(candidates))
    return chosen


def plot_correlation_matrices(groups: Sequence[RunGroup], path: Path, step: int | None) -> str | None:
    """
    The K x K correlation matrices of the critics (paper Fig. 5) of each ensemble group (K >= 3) at the evaluation
    nearest ``step`` (None: the last). A critic's index means nothing across runs, so matrices are never averaged
    entry by entry: each panel shows the group's median run, the one whose mean off-diagonal correlation is the
    median of the group's.

    :return: a sentence saying which step was drawn, or None when no group has matrices
    """
    rows = [
        (key, name)
        for key, name in MATRIX_ROWS
        if any(
            d is not None and key in d and d[key].shape[-1] >= 3 and np.isfinite(d[key]).all()
            for g in groups
            for d in map(load_diagnostics, g.runs)
        )
    ]
    panels = [(group, chosen) for group in groups if (chosen := _median_matrices(group, rows, step))]
    if not panels:
        return None
    # A row whose every pair correlates at 1.000 as printed says nothing a sentence does not
    saturated = [
        (key, name)
        for key, name in rows
        if all(_off_diagonal_min(chosen[key][0]) >= SATURATED for _, chosen in panels if key in chosen)
    ]
    rows = [row for row in rows if row not in saturated]
    chosen_step = "the last evaluation" if step is None else f"the evaluation nearest {step:,} steps"
    note = "".join(f" Not drawn: {name}, every pair of critics at r >= {SATURATED} in every group." for _, name in saturated)
    if not rows:
        path.unlink(missing_ok=True)  # a report written over an older one keeps no stale figure
        return f"Correlation matrices at {chosen_step}:{note}"
    plt = pyplot()
    fig, axes = plt.subplots(
        len(rows), len(panels), figsize=(3.4 * len(panels) + 1.5, 3.5 * len(rows)), squeeze=False, layout="constrained"
    )
    for row, (key, name) in enumerate(rows):
        # One colour scale per row, from its smallest off-diagonal entry to 1, so that differences show
        off_diagonal = [chosen[key][0][~np.eye(len(chosen[key][0]), dtype=bool)] for _, chosen in panels if key in chosen]
        smallest = float(min(values.min() for values in off_diagonal))
        # From the smallest off-diagonal entry to 1 (to a thousandth for saturated rows), so that differences show
        low = np.floor(smallest * 1000) / 1000 if smallest >= 0.99 else min(np.floor(smallest * 20) / 20, 0.95)
        image = None
        for column, (group, chosen) in enumerate(panels):
            ax = axes[row][column]
            if key not in chosen:
                ax.axis("off")
                continue
            matrix, seed, at, n = chosen[key]
            image = ax.imshow(matrix, vmin=low, vmax=1.0, cmap="viridis")
            # Near-saturated rows (all above 0.95) get three decimals, so that their differences show
            decimals = 3 if low >= 0.95 else 2
            for (i, j), value in np.ndenumerate(matrix):
                shade = "black" if value > low + 0.6 * (1.0 - low) else "white"
                ax.text(j, i, f"{value:.{decimals}f}", ha="center", va="center", fontsize=7, color=shade)
            labels = [f"Q{i}" for i in range(len(matrix))]
            ax.set_xticks(range(len(matrix)), labels, fontsize=7)
            ax.set_yticks(range(len(matrix)), labels, fontsize=7)
            ax.set_title(
                f"{group.label}: {name}\nseed {seed} at {at:,} steps "
                f"(median of {n} runs, mean r {_off_diagonal_mean(matrix):.2f})",
                fontsize=8,
            )
        if image is not None:
            fig.colorbar(image, ax=axes[row], shrink=0.8, label="Pearson r")
    fig.suptitle("Inter-critic correlation matrices (Fig. 5), one run per panel", fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return (
        f"Correlation matrices at {chosen_step}: each panel is the group's median run by mean off-diagonal r "
        f"(a critic's index means nothing across runs, so matrices are not averaged).{note}"
    )
