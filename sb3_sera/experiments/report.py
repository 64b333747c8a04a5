"""
A Markdown report from rl-zoo3-style run folders (``<root>/<variant>/<env_name>_<id>/``, as written by
``sb3-sera train``, ``compare`` and ``bench``), read from each run's records (``<env_name>/args.yml`` and
``config.yml``), never from folder names.

Runs are grouped by variant, task, budget and hyperparameters; runs that differ in any of these are never averaged
together: each task and budget has its own section, and a variant run with several settings gets a row per setting,
with a note that says what differs. Per section: a table with the interquartile mean (IQM) of the final evaluation
returns and its 95% stratified-bootstrap confidence interval (``rliable``), the mean ± sample standard deviation
beside the paper's values, the normalized AUC (IQM and interval), the probability that SERASAC improves on each
baseline (with interval), Welch's p-value and SERASAC's improvement in percent; learning curves (IQM and interval
per evaluation); the initial-state value bias over training (paper Fig. 4a); the normalized AUC as bars (Fig. 4b);
the TD-target variance and the critics' value and TD-error correlations over training (Fig. 4c); and the critics'
K x K correlation matrices at one evaluation (Fig. 5). Several sections together add min-max normalized scores
aggregated over tasks and performance profiles.
"""

import json
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import ArrayLike

from sb3_sera.experiments import stats
from sb3_sera.experiments.claims import claims_section, load_diagnostics
from sb3_sera.experiments.runs import RESULT_FILE, RunResult, env_name, load_result, read_record

#: Paper Table 1 (multi-agent, 300K steps) and Table 2 (single-agent): (mean, std) of the team return
PAPER_RESULTS: dict[str, dict[str, tuple[float, float]]] = {
    "sb3_sera/HalfCheetah-6x1-v0": {
        "SERA": (5520, 711), "Ensemble Mean": (4831, 721), "IET": (4608, 783),
        "MASAC": (4500, 802), "MATD3": (3815, 912), "MAPPO": (3623, 812),
    },
    "sb3_sera/Pusher-3p-v0": {
        "SERA": (-27, 8), "Ensemble Mean": (-30, 7), "IET": (-29, 9),
        "MASAC": (-31, 8), "MATD3": (-50, 11), "MAPPO": (-57, 13),
    },
    "sb3_sera/Hopper-3x1-v0": {
        "SERA": (2380, 519), "Ensemble Mean": (2190, 611), "IET": (1701, 600),
        "MASAC": (1530, 200), "MATD3": (840, 400), "MAPPO": (790, 100),
    },
    "sb3_sera/Multiwalker-v0": {
        "SERA": (-27.4, 5), "Ensemble Mean": (-39, 5), "IET": (-46.5, 5),
        "MASAC": (-51, 10), "MATD3": (-56, 10), "MAPPO": (-60.3, 10),
    },
    "sb3_sera/SimpleSpread-v0": {
        "SERA": (-9, 2), "Ensemble Mean": (-13, 2.3), "IET": (-14, 4),
        "MASAC": (-16, 5.1), "MATD3": (-17.5, 6), "MAPPO": (-18, 2),
    },
    "Ant-v5": {"SERA": (1983.7, 602), "SUNRISE": (1530, 605), "ACE": (890, 654)},
    "HalfCheetah-v5": {"SERA": (6056, 439), "SUNRISE": (5613, 570), "ACE": (3923, 480)},
    "Humanoid-v5": {"SERA": (4982.6, 510), "SUNRISE": (4515.3, 600), "ACE": (3908.6, 582)},
}  # fmt: skip
#: Our variant names for the paper's columns
PAPER_NAMES = {
    "serasac": "SERA", "ensemble_mean": "Ensemble Mean", "masac": "MASAC", "matd3": "MATD3", "mappo": "MAPPO",
    "sera_nolr": "SERA-NoLR", "sera_median": "SERA-Median", "sunrise": "SUNRISE", "ace": "ACE", "iet": "IET",
}  # fmt: skip
REFERENCE = "serasac"
#: Variants in the order tables list them and colours are given (others follow, alphabetically)
VARIANT_ORDER = (
    "serasac", "sera_nolr", "sera_nolr_matched", "sera_median", "ensemble_mean", "sac", "masac", "sunrise", "ace", "iet",
    "matd3", "maddpg", "mappo",
)  # fmt: skip
#: Points of the common grid onto which curves evaluated at different steps are interpolated
GRID_POINTS = 50
#: What every interval in the report is
INTERVAL = "95% stratified-bootstrap confidence interval (rliable, percentile method)"


@dataclass
class Skipped:
    """A folder the report did not read, and why."""

    folder: str
    reason: str


@dataclass
class RunGroup:
    """Runs of one variant on one task with one budget and one set of hyperparameters."""

    variant: str
    env_id: str
    n_timesteps: int
    hyperparams: dict[str, Any]
    runs: list[RunResult] = field(default_factory=list)
    #: The variant's name, with the settings that set this group apart from the variant's other groups
    label: str = ""
    #: The algorithm the variant runs
    algo: str = ""

    @property
    def finals(self) -> np.ndarray:
        """Final evaluation returns, one per run."""
        return np.array([run.final_return for run in self.runs])

    @property
    def aucs(self) -> np.ndarray:
        """Normalized AUC of each run's learning curve, on its own evaluation steps."""
        return np.array([stats.normalized_auc(run.timesteps, run.returns) for run in self.runs])


def is_finished(folder: Path, args: dict[str, Any]) -> bool:
    """A run of ``compare``/``bench`` wrote ``result.json``; one of ``sb3-sera train`` saved its final model."""
    if (folder / RESULT_FILE).exists():
        return True
    return "variant" not in args and (folder / f"{env_name(str(args.get('env', '')))}.zip").exists()


def run_folders(root: Path) -> list[Path]:
    """
    The run folders at any depth under ``root``: folders holding ``evaluations.npz`` or a ``<env_name>/args.yml``
    record (so ``make demo``'s ``logs/compare`` and a zoo's ``logs/<algo>/<env>_<id>`` are found alike); hidden
    folders (an interrupted ledger copy) are not.
    """
    found = {path.parent for path in root.rglob("evaluations.npz")} | {path.parent.parent for path in root.rglob("args.yml")}
    return sorted(
        folder
        for folder in found
        if folder.is_dir() and not any(part.startswith(".") for part in folder.relative_to(root).parts)
    )


def load_runs(roots: Sequence[str | Path]) -> tuple[list[RunResult], list[Skipped]]:
    """
    Every finished run under the roots (see :func:`run_folders`), and the folders left out with why: no record of
    the run's settings, no evaluations, not finished, or damaged records (each named with what is wrong).

    :raises FileNotFoundError: naming a root that does not exist
    """
    missing = [str(root) for root in roots if not Path(root).is_dir()]
    if missing:
        raise FileNotFoundError(f"no such folder: {', '.join(missing)}")
    runs, skipped = [], []
    for root in roots:
        for folder in run_folders(Path(root)):
            evaluated = (folder / "evaluations.npz").exists()
            records = sorted(folder.glob("*/args.yml"))
            if not records:
                skipped.append(
                    Skipped(str(folder), "no <env_name>/args.yml record: its seed, budget and settings are unknown")
                )
                continue
            if not evaluated:
                skipped.append(Skipped(str(folder), "no evaluations.npz (train with --eval-freq)"))
                continue
            try:
                args = read_record(records[0])
                if not isinstance(args, dict):
                    raise ValueError(f"{folder}: args.yml is not a mapping")
                if not is_finished(folder, args):
                    skipped.append(Skipped(str(folder), "unfinished: no result.json (compare, bench) or final model (train)"))
                    continue
                runs.append(load_result(folder))
            except (ValueError, yaml.YAMLError) as error:
                reason = " ".join(str(error).split())
                skipped.append(Skipped(str(folder), reason.removeprefix(f"{folder}: ")))
    return runs, skipped


def variant_rank(variant: str) -> tuple[int, str]:
    """Sort key: the known variants in :data:`VARIANT_ORDER`, then the others alphabetically."""
    return (VARIANT_ORDER.index(variant) if variant in VARIANT_ORDER else len(VARIANT_ORDER), variant)


def run_settings(run: RunResult) -> dict[str, Any]:
    """What sets a run's results apart beside its variant, task and budget: its hyperparameters and evaluations."""
    evaluation = {"eval_freq": run.eval_freq, "eval_episodes": run.eval_episodes}
    return {**run.hyperparams, **{key: value for key, value in evaluation.items() if value is not None}}


def group_runs(runs: Sequence[RunResult]) -> list[RunGroup]:
    """
    Runs grouped by (variant, task, budget, hyperparameters and evaluation settings), ordered by task, budget and
    variant; a variant with several groups in one task and budget gets labels that name the settings that differ.
    """
    groups: dict[tuple[str, str, int, str], RunGroup] = {}
    for run in runs:
        settings = run_settings(run)
        key = (run.variant, run.env_id, run.n_timesteps, json.dumps(settings, sort_keys=True, default=str))
        group = groups.setdefault(key, RunGroup(run.variant, run.env_id, run.n_timesteps, settings, algo=run.algo))
        group.runs.append(run)
    ordered = sorted(
        groups.values(),
        key=lambda g: (
            g.env_id,
            g.n_timesteps,
            variant_rank(g.variant),
            json.dumps(g.hyperparams, sort_keys=True, default=str),
        ),
    )
    for group in ordered:
        siblings = [
            g for g in ordered if (g.variant, g.env_id, g.n_timesteps) == (group.variant, group.env_id, group.n_timesteps)
        ]
        differing = differing_keys([g.hyperparams for g in siblings])
        group.label = (
            group.variant
            if len(siblings) == 1
            else f"{group.variant} ({settings_text(group.hyperparams, differing, group.algo)})"
        )
    return ordered


def differing_keys(settings: Sequence[dict[str, Any]]) -> list[str]:
    """The keys whose values are not the same in all of ``settings`` (a missing key counts as a value)."""
    keys = sorted(set().union(*settings)) if settings else []
    return [key for key in keys if len({json.dumps(s.get(key, "unset"), default=str) for s in settings}) > 1]


def settings_text(hyperparams: dict[str, Any], keys: Sequence[str], algo: str = "") -> str:
    """``key=value`` for each of ``keys``; a key the run did not set shows the algorithm's default, marked so."""
    return ", ".join(
        f"{key}={hyperparams[key]}" if key in hyperparams else f"{key}={algorithm_default(algo, key)} (default)"
        for key in keys
    )


def algorithm_default(algo: str, key: str) -> Any:
    """The default of ``key`` in the constructor of ``algo`` (rl-zoo3's name), or "unknown"."""
    import inspect

    from sb3_sera.experiments.runs import algorithm_classes

    model_class = algorithm_classes().get(algo)
    if model_class is None:
        return "unknown"
    parameter = inspect.signature(model_class).parameters.get(key)
    return "unknown" if parameter is None or parameter.default is inspect.Parameter.empty else parameter.default


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
        paper_value = paper.get(PAPER_NAMES.get(group.variant, ""))
        paper_cell = "" if paper_value is None else f"{paper_value[0]:g} ± {paper_value[1]:g}"
        improvement_cell = p_cell = poi_cell = ""
        if reference is not None and group is not reference:
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
        f"n: runs (seeds) per row, {budget:,} steps each. IQM: interquartile mean over the runs (†: n <= 3, where it "
        f"trims nothing and is the mean); [a, b]: its {INTERVAL}, {reps} resamples, printed from {MIN_RUNS} runs on. "
        f"mean ± std: sample standard deviation (ddof 1). Normalized AUC: the area under the run's learning curve "
        f"divided by its length in steps (its average evaluation return). P({REFERENCE} > variant): probability that a "
        f"run of {REFERENCE} ends higher than a run of the variant, with its interval, and {REFERENCE}'s improvement in "
        f"percent of the variant's mean, both from {MIN_RUNS} runs a side on. Welch p: two-sided Welch's t-test on the "
        "final returns. Initial-state bias: mean V(s0) minus the mean discounted return at the last evaluation.",
    ]
    if reference_note:
        lines += ["", reference_note]
    others = [name for name in paper if name not in {PAPER_NAMES.get(group.variant) for group in groups}]
    if others:
        lines += ["", "Paper only: " + ", ".join(f"{name} {paper[name][0]:g} ± {paper[name][1]:g}" for name in others)]
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


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: Path) -> None:
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    _pyplot().close(fig)


def _draw_band(
    ax: Any, series: Sequence[tuple[ArrayLike, ArrayLike]], reps: int, label: str, color: Any, linestyle: str = "-"
) -> str:
    """IQM over runs with its bootstrap interval as a band; returns the grid's sentence (empty for shared steps)."""
    grid, matrix, note = aligned(series)
    point, low, high = stats.iqm_interval(matrix[:, None, :], reps)
    ax.plot(grid, point, color=color, linestyle=linestyle, label=f"{label} (n={len(series)})")
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
    zero_line: bool = False,
) -> list[str]:  # fmt: skip
    """
    A per-run list (``returns`` or ``initial_state_bias``) against steps: IQM over each group's runs and its interval.

    :return: sentences on interpolated grids
    """
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    styles, notes = _linestyles(groups), []
    for group in groups:
        series = [
            (run.timesteps[: len(getattr(run, attribute))], getattr(run, attribute))
            for run in group.runs
            if getattr(run, attribute)
        ]
        if series:
            note = _draw_band(ax, series, reps, group.label, colors[group.variant], styles[id(group)])
            if note:
                notes.append(f"{group.label}: {note}")
    if zero_line:
        ax.axhline(0.0, color="black", linewidth=0.8)
    ax.set_xlabel("environment steps")
    ax.set_ylabel(ylabel)
    ax.set_title(f"{title}\nIQM over runs, band: 95% stratified-bootstrap CI", fontsize=10)
    ax.legend(fontsize="small")
    _save(fig, path)
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


def plot_diagnostics(groups: Sequence[RunGroup], path: Path, colors: dict[str, Any], reps: int) -> bool:
    """
    One panel per quantity of :data:`DIAGNOSTIC_PANELS`, IQM over runs and interval per group; per-critic learning
    rates summarized by their mean (line and band) and their smallest and largest (dotted). Returns whether any
    group had diagnostics.
    """
    records = {id(group): [d for d in map(load_diagnostics, group.runs) if d is not None] for group in groups}
    if not any(records.values()):
        return False
    plt = _pyplot()
    fig, axes_grid = plt.subplots(2, 3, figsize=(15, 8.4))
    axes = axes_grid.ravel()
    styles = _linestyles(groups)
    for group in groups:
        runs = records[id(group)]
        if not runs:
            continue
        color = colors[group.variant]
        for ax, (key, _, _) in zip(axes, DIAGNOSTIC_PANELS, strict=True):
            having = [r for r in runs if key in r]
            if not having:
                continue
            # Evaluations without a value (no Monte Carlo sample kept, say) are left out of the run's curve
            series = []
            for r in having:
                values = r[key] if r[key].ndim == 1 else r[key].mean(axis=1)
                finite = np.isfinite(values)
                if finite.any():
                    series.append((r["timesteps"][finite], values[finite]))
            if not series:
                continue
            _draw_band(ax, series, reps, group.label, color, styles[id(group)])
            if having[0][key].ndim == 2:
                for reduce in (np.min, np.max):
                    grid, matrix, _ = aligned([(r["timesteps"], reduce(r[key], axis=1)) for r in having])
                    ax.plot(grid, stats.iqm(matrix[:, None, :]), color=color, linestyle=":", linewidth=0.9)
    for ax, (key, title, ylabel) in zip(axes, DIAGNOSTIC_PANELS, strict=True):
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("environment steps")
        ax.set_ylabel(ylabel)
        if key in ("td_target_var", "td_target_relative_var"):
            ax.set_yscale("log")
        if ax.lines:
            ax.legend(fontsize="x-small")
    fig.suptitle(
        "Critic diagnostics at each evaluation (1024 replayed transitions; Monte Carlo errors: the evaluation episodes' "
        "steps); IQM over runs, band: 95% bootstrap CI",
        fontsize=10,
    )
    _save(fig, path)
    return True


def plot_auc_bars(groups: Sequence[RunGroup], path: Path, colors: dict[str, Any], reps: int) -> None:
    """
    Normalized AUC per group (paper Fig. 4b): IQM over runs as a marker with its interval, runs as dots, on an axis
    fitted to the values (not drawn from zero, so that differences between groups show whatever the sign).
    """
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(1.6 * len(groups) + 2, 4.6))
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
        f"Normalized AUC (Fig. 4b)\nsquare: IQM over runs, bar: 95% stratified-bootstrap CI (n >= {MIN_RUNS}), dots: runs",
        fontsize=9,
    )
    _save(fig, path)


#: The correlation matrices drawn (paper Fig. 5), one row each: record key and what it correlates
MATRIX_ROWS = (
    ("mc_error_corr_matrix", "errors vs Monte Carlo returns"),
    ("td_error_corr_matrix", "TD errors δ_i"),
    ("critic_corr_matrix", "values Q_i"),
)


def _off_diagonal_mean(matrix: np.ndarray) -> float:
    return float(matrix[~np.eye(len(matrix), dtype=bool)].mean())


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
    panels: list[tuple[RunGroup, dict[str, tuple[np.ndarray, int, int, int]]]] = []
    for group in groups:
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
        if chosen:
            panels.append((group, chosen))
    if not panels:
        return None
    plt = _pyplot()
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
    chosen_step = "the last evaluation" if step is None else f"the evaluation nearest {step:,} steps"
    return (
        f"Correlation matrices at {chosen_step}: each panel is the group's median run by mean off-diagonal r "
        "(a critic's index means nothing across runs, so matrices are not averaged)."
    )


def paper_reference(env_id: str) -> tuple[float, float] | None:
    """
    Fixed reference scores of a task for normalizing across tasks: the lowest mean of the paper's columns and SERA's
    mean at 300K (None for a task the paper does not report). Fixed, so that adding a variant changes no score.
    """
    paper = PAPER_RESULTS.get(env_id)
    if not paper or "SERA" not in paper:
        return None
    return min(mean for mean, _ in paper.values()), paper["SERA"][0]


def aggregate_section(
    sections: Sequence[list[RunGroup]], folder: Path, colors: dict[str, Any], reps: int, budget: int
) -> list[str]:
    """
    Scores aggregated over the task sections of one budget: each final return normalized by its task's fixed
    reference scores (:func:`paper_reference`: 0 at the paper's lowest column, 1 at the paper's SERA), then per
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
    plt = _pyplot()
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
    _save(fig, folder / name)
    return [*lines, "", f"![performance profiles]({name})", ""]


def write_report(
    runs: Sequence[RunResult],
    out: str | Path,
    skipped: Sequence[Skipped] = (),
    reps: int = stats.REPS,
    matrix_step: int | None = None,
    sources: Sequence[str] = (),
    log: Callable[[str], None] | None = None,
) -> Path:
    """
    Write ``report.md`` and its figures into the folder ``out`` (see the module's docstring).

    :param runs: finished runs (:func:`load_runs`, or what ``compare``/``bench`` ran)
    :param skipped: folders left out, listed at the end with their reasons
    :param reps: bootstrap resamples of every interval
    :param matrix_step: the step whose correlation matrices are drawn (None: each run's last evaluation)
    :param sources: where the runs were read from, for the report's first line
    :param log: called with a line saying what the report is doing, section by section (None: silent)
    :return: the path of ``report.md``
    """
    if not runs:
        raise ValueError("no finished runs to report")
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    all_groups = group_runs(runs)
    colors = variant_colors([group.variant for group in all_groups])
    sections_by_key: dict[tuple[str, int], list[RunGroup]] = defaultdict(list)
    for group in all_groups:
        sections_by_key[(group.env_id, group.n_timesteps)].append(group)
    lines = ["# Results", ""]
    if sources:
        lines += [f"Runs read from: {', '.join(sources)}.", ""]
    for number, ((env_id, budget), groups) in enumerate(sections_by_key.items(), start=1):
        stem = f"{env_name(env_id)}_{budget}"
        if log is not None:
            log(f"report: section {number}/{len(sections_by_key)}, {env_id} at {budget:,} steps: table, claims, figures")
        lines += [f"## {env_id}, {budget:,} steps", "", *section_table(groups, reps), ""]
        claims = claims_section([(group.variant, group.runs) for group in groups], reps)
        if claims:
            lines += ["### The paper's mechanism claims", "", *claims, ""]
        notes = section_notes(groups, all_groups)
        if notes:
            lines += ["Notes:", *notes, ""]
        grid_notes = plot_curves(
            groups, "returns", "evaluation return", f"{env_id}, {budget:,} steps", folder / f"{stem}_curves.png", colors, reps
        )
        lines += [f"![{env_id} learning curves]({stem}_curves.png)", ""]
        lines += [f"- {note}" for note in grid_notes] + ([""] if grid_notes else [])
        if any(run.initial_state_bias for group in groups for run in group.runs):
            plot_curves(
                groups, "initial_state_bias", "V(s0) - discounted return", f"Initial-state bias (Fig. 4a), {env_id}",
                folder / f"{stem}_bias.png", colors, reps, zero_line=True,
            )  # fmt: skip
            lines += [f"![{env_id} initial-state bias]({stem}_bias.png)", ""]
        if len(groups) > 1:
            plot_auc_bars(groups, folder / f"{stem}_auc.png", colors, reps)
            lines += [f"![{env_id} normalized AUC]({stem}_auc.png)", ""]
        if plot_diagnostics(groups, folder / f"{stem}_diagnostics.png", colors, reps):
            lines += [f"![{env_id} critic diagnostics]({stem}_diagnostics.png)", ""]
        matrices = plot_correlation_matrices(groups, folder / f"{stem}_correlations.png", matrix_step)
        if matrices is not None:
            lines += [f"![{env_id} critic correlation matrices]({stem}_correlations.png)", "", matrices, ""]
    for budget in sorted({budget for _, budget in sections_by_key}):
        same_budget = [groups for (_, b), groups in sections_by_key.items() if b == budget]
        if len(same_budget) > 1:
            lines += aggregate_section(same_budget, folder, colors, reps, budget)
    if skipped:
        lines += ["## Left out", "", *(f"- {s.folder}: {s.reason}" for s in skipped), ""]
    report = folder / "report.md"
    report.write_text("\n".join(lines))
    return report


def report_roots(
    roots: Sequence[str | Path],
    out: str | Path,
    overwrite: bool = False,
    reps: int = stats.REPS,
    matrix_step: int | None = None,
    log: Callable[[str], None] | None = None,
) -> Path:
    """
    :func:`write_report` for every run under ``roots`` (see :func:`load_runs`); refuses to overwrite an earlier
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
    return write_report(runs, out, skipped, reps, matrix_step, sources=[str(root) for root in roots], log=log)


def next_report_folder(parent: str | Path, name: str) -> Path:
    """``<parent>/<name>_<n>`` with the next free ``n`` (from 1), so that a report never replaces another."""
    parent = Path(parent)
    taken = [int(p.name.rpartition("_")[2]) for p in parent.glob(f"{name}_*") if p.name.rpartition("_")[2].isdigit()]
    return parent / f"{name}_{max(taken, default=0) + 1}"
