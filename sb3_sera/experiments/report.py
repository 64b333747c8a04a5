"""
A Markdown report from rl-zoo3-style run folders (``<root>/<algo>/<env_name>_<id>/evaluations.npz``, as written by
``sb3-sera train``, ``compare`` and ``bench``) and, optionally, the TensorBoard logs of the same runs.

Per task: the paper's Table 1/2 layout with our final evaluation returns beside the paper's, the normalized AUC,
Welch's t-test p-value against SERASAC and SERASAC's improvement in percent; learning curves; the initial-state
value bias over training (from ``initial_state_bias.npz``, written by the evaluations of ``train``, ``compare`` and
``bench``); and, from
TensorBoard, the TD-target variance, the inter-critic correlation and each critic's kappa over training.
"""

import json
import math
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path

import gymnasium as gym
import numpy as np

from sb3_sera.common.callbacks import BIAS_FILE, initial_state_bias
from sb3_sera.experiments.compare import (
    RunResult,
    env_name,
    plot_initial_state_bias,
    plot_learning_curves,
    summarize,
)
from sb3_sera.experiments.stats import improvement_percent

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
#: Our run names for the paper's columns
PAPER_NAMES = {"serasac": "SERA", "ensemble_mean": "Ensemble Mean", "masac": "MASAC", "matd3": "MATD3", "mappo": "MAPPO"}
REFERENCE = "serasac"
DIAGNOSTICS = ("train/td_target_var", "train/critic_corr")


def _env_ids() -> dict[str, str]:
    """Folder names back to env ids (rl-zoo3 writes slashes as dashes)."""
    return {env_name(env_id): env_id for env_id in gym.registry}


def load_runs(roots: Sequence[str | Path]) -> list[RunResult]:
    """
    Every run under the roots: ``<root>/<algo>/<env_name>_<id>/evaluations.npz``, with the initial-state bias of
    its ``initial_state_bias.npz`` where there is one.
    """
    ids = _env_ids()
    runs = []
    for root in roots:
        for evaluations_file in sorted(Path(root).glob("*/*/evaluations.npz")):
            folder = evaluations_file.parent
            name, _, run_id = folder.name.rpartition("_")
            evaluations = np.load(evaluations_file)
            returns = evaluations["results"].mean(axis=1)
            result_file = folder / "result.json"
            wall_time = json.loads(result_file.read_text())["wall_time_s"] if result_file.exists() else math.nan
            timesteps = [int(t) for t in evaluations["timesteps"]]
            bias: list[float] = []
            if (folder / BIAS_FILE).exists():
                records = np.load(folder / BIAS_FILE)
                bias = initial_state_bias(records["values"], records["discounted_returns"])
            runs.append(
                RunResult(
                    algo=folder.parent.name,
                    env_id=ids.get(name, name),
                    seed=int(run_id) if run_id.isdigit() else 0,
                    n_timesteps=timesteps[-1],
                    wall_time_s=wall_time,
                    final_return=float(returns[-1]),
                    timesteps=timesteps,
                    returns=[float(r) for r in returns],
                    initial_state_bias=bias,
                )
            )
    return runs


def task_table(env_id: str, runs: Sequence[RunResult]) -> str:
    """One task's rows: ours beside the paper's, normalized AUC, Welch p and SERASAC's improvement."""
    paper = PAPER_RESULTS.get(env_id, {})
    summaries = summarize(runs, REFERENCE)
    algos = sorted(summaries, key=lambda algo: (algo != REFERENCE, algo))
    budget = max(run.n_timesteps for run in runs)
    lines = [
        f"### {env_id} (our runs: {budget:,} steps)",
        "",
        f"| algorithm | runs | final return (mean ± std) | paper at 300K (mean ± std) | normalized AUC "
        f"| p vs {REFERENCE} (Welch) | {REFERENCE} improvement % | initial-state bias (last evaluation) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for algo in algos:
        summary = summaries[algo]
        values, p_value = summary.finals, summary.p_value
        paper_value = paper.get(PAPER_NAMES.get(algo, ""))
        paper_cell = "" if paper_value is None else f"{paper_value[0]:g} ± {paper_value[1]:g}"
        improvement = None
        if algo != REFERENCE and REFERENCE in summaries and values.mean() != 0:
            improvement = improvement_percent(float(summaries[REFERENCE].finals.mean()), float(values.mean()))
        biases = [run.initial_state_bias[-1] for run in runs if run.algo == algo and run.initial_state_bias]
        lines.append(
            f"| {algo} | {len(values)} | {values.mean():.1f} ± {values.std():.1f} | {paper_cell} | {summary.auc:.1f} "
            f"| {'' if p_value is None else f'{p_value:.3f}'} | {'' if improvement is None else f'{improvement:+.1f}'} "
            f"| {f'{np.mean(biases):.1f}' if biases else ''} |"
        )
    others = [name for name in paper if name not in {PAPER_NAMES.get(algo) for algo in algos}]
    if others:
        lines += ["", "Paper only: " + ", ".join(f"{name} {paper[name][0]:g} ± {paper[name][1]:g}" for name in others)]
    return "\n".join(lines)


def load_scalars(tensorboard_dirs: Sequence[str | Path]) -> dict[str, dict[str, list[tuple[np.ndarray, np.ndarray]]]]:
    """
    Training diagnostics from TensorBoard event files: ``{run group: {tag: [(steps, values) per run]}}``, the run
    group being the event folder's name without its ``_<n>`` suffix (SB3 names it ``<ALGO>_<n>``), prefixed by
    its parent folder when that is an env name (rl-zoo3's ``<tb>/<env_name>/<ALGO>_<n>``).
    """
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    ids = _env_ids()
    scalars: dict[str, dict[str, list[tuple[np.ndarray, np.ndarray]]]] = defaultdict(lambda: defaultdict(list))
    for directory in tensorboard_dirs:
        for events in sorted(Path(directory).rglob("events.out.tfevents.*")):
            run_folder = events.parent
            group = run_folder.name.rpartition("_")[0] or run_folder.name
            if run_folder.parent.name in ids:
                group = f"{ids[run_folder.parent.name]} {group}"
            accumulator = EventAccumulator(str(events), size_guidance={"scalars": 0})
            accumulator.Reload()
            for tag in accumulator.Tags()["scalars"]:
                if tag in DIAGNOSTICS or tag.startswith("train/kappa_"):
                    points = accumulator.Scalars(tag)
                    scalars[group][tag].append((np.array([p.step for p in points]), np.array([p.value for p in points])))
    return scalars


def plot_diagnostics(scalars: dict[str, dict[str, list[tuple[np.ndarray, np.ndarray]]]], path: str | Path) -> None:
    """TD-target variance, inter-critic correlation and per-critic kappa over training, one line per run group."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    for group, tags in scalars.items():
        for ax, tag in zip(axes[:2], DIAGNOSTICS, strict=True):
            for index, (steps, values) in enumerate(tags.get(tag, [])):
                ax.plot(steps, values, color=f"C{list(scalars).index(group)}", label=group if index == 0 else None)
        kappas = sorted(tag for tag in tags if tag.startswith("train/kappa_"))
        for tag in kappas:
            steps, values = tags[tag][0]
            axes[2].plot(steps, values, label=f"{group} {tag.removeprefix('train/')}")
    for ax, title in zip(axes, ("TD-target variance", "inter-critic correlation", "per-critic kappa"), strict=True):
        ax.set_title(title)
        ax.set_xlabel("environment steps")
        if ax.lines:
            ax.legend(fontsize="small")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def split_by_task(
    scalars: dict[str, dict[str, list[tuple[np.ndarray, np.ndarray]]]],
) -> dict[str | None, dict[str, dict[str, list[tuple[np.ndarray, np.ndarray]]]]]:
    """The run groups of :func:`load_scalars` by task (``"<env id> <group>"``), None for groups without a task."""
    ids = set(_env_ids().values())
    tasks: dict[str | None, dict[str, dict[str, list[tuple[np.ndarray, np.ndarray]]]]] = defaultdict(dict)
    for group, tags in scalars.items():
        task, _, name = group.partition(" ")
        if name and task in ids:
            tasks[task][name] = tags
        else:
            tasks[None][group] = tags
    return tasks


def write_report(roots: Sequence[str | Path], out: str | Path, tensorboard_dirs: Sequence[str | Path] = ()) -> Path:
    """
    Write the report to the folder ``out``: ``report.md``, per task a learning-curve figure, an initial-state bias
    figure (runs that recorded it) and a diagnostics figure (TensorBoard logs under ``<tb>/<env_name>/``), and
    ``diagnostics.png`` for TensorBoard runs of no known task.

    :return: the path of ``report.md``
    """
    runs = load_runs(roots)
    if not runs:
        raise ValueError(
            f"No run folders (<root>/<algo>/<env>_<id>/evaluations.npz) under {list(map(str, roots))}: "
            "train with evaluations (sb3-sera train --eval-freq N, compare and bench always evaluate)"
        )
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    by_task: dict[str, list[RunResult]] = defaultdict(list)
    for run in runs:
        by_task[run.env_id].append(run)
    diagnostics = split_by_task(load_scalars(tensorboard_dirs)) if tensorboard_dirs else {}
    sections = ["# Results", "", f"Runs read from: {', '.join(map(str, roots))}.", ""]
    for env_id, task_runs in by_task.items():
        figure = folder / f"{env_name(env_id)}_curves.png"
        plot_learning_curves(task_runs, figure)
        sections += [task_table(env_id, task_runs), "", f"![{env_id}]({figure.name})", ""]
        if any(run.initial_state_bias for run in task_runs):
            bias_figure = folder / f"{env_name(env_id)}_bias.png"
            plot_initial_state_bias(task_runs, bias_figure)
            sections += [f"![{env_id} initial-state bias]({bias_figure.name})", ""]
        if env_id in diagnostics:
            diagnostics_figure = folder / f"{env_name(env_id)}_diagnostics.png"
            plot_diagnostics(diagnostics[env_id], diagnostics_figure)
            sections += [f"![{env_id} training diagnostics]({diagnostics_figure.name})", ""]
    if None in diagnostics:
        plot_diagnostics(diagnostics[None], folder / "diagnostics.png")
        sections += ["## Training diagnostics", "", "![diagnostics](diagnostics.png)", ""]
    report = folder / "report.md"
    report.write_text("\n".join(sections))
    return report
