"""
Train several algorithms on one task for several seeds, then tabulate and plot the results.

Each run writes a folder in rl-zoo3's layout, ``<out>/<algo>/<env_name>_<seed>/`` (the env id with
slashes as dashes), holding the ``evaluations.npz`` of SB3's ``EvalCallback`` (and the ``initial_state_bias.npz`` of
:class:`~sb3_sera.common.callbacks.InitialStateBiasCallback`, which also evaluates), the training ``0.monitor.csv``,
the final model ``<env_name>.zip`` and ``result.json``
(wall time and final evaluation). A run whose ``result.json`` exists is not run again, so an interrupted
comparison resumes where it stopped.
"""

import json
import math
import os
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecEnv
from tqdm import tqdm

from sb3_sera.common.callbacks import InitialStateBiasCallback, initial_state_bias
from sb3_sera.ctde.env import STATE_KEY
from sb3_sera.experiments.stats import normalized_auc, welch_p_value

#: Default quick comparison: a task that SAC solves in a few thousand steps.
DEFAULT_ENV = "Pendulum-v1"
DEFAULT_ALGOS = ("serasac", "sac")
DEFAULT_SEEDS = (0, 1)
DEFAULT_TIMESTEPS = 6_000
#: Hyperparameters of the quick comparison on the default task: rl-zoo3's SAC entry for Pendulum-v1 (learning
#: rate 1e-3), for every algorithm; SERASAC's critics use the same rate as their largest step size.
DEFAULT_HYPERPARAMS: dict[str, dict[str, Any]] = {
    "sac": {"learning_rate": 1e-3},
    "serasac": {"learning_rate": 1e-3, "critic_lr_max": 1e-3},
}


def algorithm_classes() -> dict[str, type[BaseAlgorithm]]:
    """rl-zoo3's algorithms by lower-case name, with this package's added."""
    from rl_zoo3.utils import ALGOS

    from sb3_sera.experiments.zoo import ZOO_ALGOS

    return {**ALGOS, **ZOO_ALGOS}


def policy_for(env: VecEnv) -> str:
    """``"CTDEPolicy"`` for a multi-agent CTDE task (Dict observation with a state), else ``"MlpPolicy"``."""
    space = env.observation_space
    return "CTDEPolicy" if isinstance(space, spaces.Dict) and STATE_KEY in space.spaces else "MlpPolicy"


@dataclass
class RunResult:
    """What one training run measured."""

    algo: str
    env_id: str
    seed: int
    n_timesteps: int
    wall_time_s: float
    #: Mean return of the last evaluation
    final_return: float
    timesteps: list[int] = field(default_factory=list)
    #: Mean evaluation return at each of ``timesteps``
    returns: list[float] = field(default_factory=list)
    #: Initial-state value bias at each of ``timesteps``: mean ``V(s0)`` minus mean discounted return over the
    #: evaluation's episodes (empty for runs evaluated without :class:`InitialStateBiasCallback`)
    initial_state_bias: list[float] = field(default_factory=list)


def env_name(env_id: str) -> str:
    """``env_id`` as rl-zoo3 names folders and files: slashes become dashes (``sb3_sera-HalfCheetah-6x1-v0``)."""
    return env_id.replace("/", "-")


def run_dir(out_dir: str | Path, algo: str, env_id: str, seed: int) -> Path:
    """The folder of one run, in rl-zoo3's layout."""
    return Path(out_dir) / algo / f"{env_name(env_id)}_{seed}"


@dataclass
class RunSpec:
    """One training run: an algorithm (under a label, e.g. a variant's name) on one task and seed."""

    label: str
    algo: str
    env_id: str
    seed: int
    n_timesteps: int
    hyperparams: dict[str, Any] = field(default_factory=dict)
    eval_freq: int = 1000
    n_eval_episodes: int = 5


def train_one(spec: RunSpec, out_dir: str, threads: int = 1) -> RunResult:
    """
    Train one run, evaluating every ``spec.eval_freq`` steps, in ``run_dir(out_dir, spec.label, ...)``; a run whose
    ``result.json`` exists is not run again.

    :param spec: what to train
    :param out_dir: root of the run folders
    :param threads: torch threads for this run (1 when several runs share the cores)
    """
    folder = run_dir(out_dir, spec.label, spec.env_id, spec.seed)
    result_file = folder / "result.json"
    if result_file.exists():
        return RunResult(**json.loads(result_file.read_text()))
    th.set_num_threads(threads)
    folder.mkdir(parents=True, exist_ok=True)
    env = make_vec_env(spec.env_id, n_envs=1, seed=spec.seed, monitor_dir=str(folder))
    eval_env = make_vec_env(spec.env_id, n_envs=1, seed=spec.seed + 10_000)
    model = algorithm_classes()[spec.algo](policy_for(env), env, seed=spec.seed, verbose=0, **spec.hyperparams)
    callback = InitialStateBiasCallback(
        eval_env, eval_freq=spec.eval_freq, n_eval_episodes=spec.n_eval_episodes, log_path=str(folder), verbose=0
    )
    start = time.perf_counter()
    # With a tensorboard_log hyperparameter, the run's events go to <tensorboard_log>/<label>_<n>
    model.learn(spec.n_timesteps, callback=callback, tb_log_name=spec.label)
    wall_time = time.perf_counter() - start
    model.save(folder / env_name(spec.env_id))
    evaluations = np.load(folder / "evaluations.npz")
    returns = evaluations["results"].mean(axis=1)
    result = RunResult(
        algo=spec.label,
        env_id=spec.env_id,
        seed=spec.seed,
        n_timesteps=spec.n_timesteps,
        wall_time_s=wall_time,
        final_return=float(returns[-1]),
        timesteps=[int(t) for t in evaluations["timesteps"]],
        returns=[float(r) for r in returns],
        initial_state_bias=initial_state_bias(callback.bias_values, callback.bias_returns),
    )
    # Written last: its presence marks the run as finished
    result_file.write_text(json.dumps(asdict(result)))
    env.close()
    eval_env.close()
    return result


def execute(
    specs: Sequence[RunSpec],
    out_dir: str,
    n_jobs: int | None = None,
    ray_address: str | None = None,
    progress_bar: bool = True,
) -> list[RunResult]:
    """
    Run every spec, one torch thread per run when several run at once: on a local process pool of ``n_jobs``
    workers (default: one per core), or as Ray tasks of one CPU each on the cluster at ``ray_address``
    (``"auto"``: the one ``ray start`` made on this machine). Finished runs are read back, not run again.

    :return: the results, in the order of ``specs``
    """
    if ray_address is not None:
        return _execute_on_ray(specs, out_dir, ray_address, progress_bar)
    n_jobs = min(n_jobs or os.cpu_count() or 1, len(specs))
    threads = 1 if n_jobs > 1 else th.get_num_threads()
    results: dict[int, RunResult] = {}
    with (
        ProcessPoolExecutor(max_workers=n_jobs, mp_context=get_context("spawn")) as pool,
        tqdm(total=len(specs), desc="runs", disable=not progress_bar) as bar,
    ):
        futures = {pool.submit(train_one, spec, out_dir, threads): index for index, spec in enumerate(specs)}
        for future in as_completed(futures):
            results[futures[future]] = future.result()
            bar.update()
    return [results[index] for index in range(len(specs))]


def _execute_on_ray(specs: Sequence[RunSpec], out_dir: str, address: str, progress_bar: bool) -> list[RunResult]:
    try:
        import ray
    except ImportError as error:
        raise ImportError("--ray-address needs Ray: pip install 'sb3-sera[distributed]'") from error
    ray.init(address=address, ignore_reinit_error=True, log_to_driver=False)
    remote_train: Any = ray.remote(num_cpus=1)(train_one)
    # Workers may start elsewhere: give them an absolute folder
    folder = str(Path(out_dir).resolve())
    pending = {remote_train.remote(spec, folder, 1): index for index, spec in enumerate(specs)}
    results: dict[int, RunResult] = {}
    with tqdm(total=len(specs), desc="runs (ray)", disable=not progress_bar) as bar:
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                results[pending.pop(ref)] = ray.get(ref)
                bar.update()
    return [results[index] for index in range(len(specs))]


def run_comparison(
    algos: Sequence[str] = DEFAULT_ALGOS,
    env_id: str = DEFAULT_ENV,
    seeds: Sequence[int] = DEFAULT_SEEDS,
    n_timesteps: int = DEFAULT_TIMESTEPS,
    out_dir: str = "logs/compare",
    hyperparams: dict[str, dict[str, Any]] | None = None,
    eval_freq: int = 1000,
    n_eval_episodes: int = 5,
    n_jobs: int | None = None,
    progress_bar: bool = True,
) -> list[RunResult]:
    """
    Train every algorithm on every seed, ``n_jobs`` runs at a time (default: one per core), one torch thread each.

    :return: the results, ordered as ``algos`` x ``seeds``
    """
    known = algorithm_classes()
    unknown = [algo for algo in algos if algo not in known]
    if unknown:
        raise ValueError(f"Unknown algorithm(s) {unknown}: expected names among {sorted(known)}")
    if eval_freq > n_timesteps:
        raise ValueError(f"eval_freq={eval_freq} exceeds n_timesteps={n_timesteps}: no evaluation would run")
    if hyperparams is None:
        hyperparams = DEFAULT_HYPERPARAMS if env_id == DEFAULT_ENV else {}
    specs = [
        RunSpec(algo, algo, env_id, seed, n_timesteps, dict(hyperparams.get(algo, {})), eval_freq, n_eval_episodes)
        for algo in algos
        for seed in seeds
    ]
    return execute(specs, out_dir, n_jobs=n_jobs, progress_bar=progress_bar)


@dataclass
class AlgorithmSummary:
    """One algorithm's runs on one task, summarized."""

    #: Final evaluation return of each run
    finals: np.ndarray
    #: Normalized AUC of the learning curve, averaged over runs
    auc: float
    #: Welch's t-test p-value of the final returns against the reference algorithm's (None for the reference,
    #: or with fewer than two runs on a side)
    p_value: float | None


def summarize(results: Sequence[RunResult], reference: str) -> dict[str, AlgorithmSummary]:
    """Per algorithm (in order of first appearance): final returns, mean normalized AUC, Welch p vs ``reference``."""
    algos = list(dict.fromkeys(result.algo for result in results))
    finals = {algo: [run.final_return for run in results if run.algo == algo] for algo in algos}
    return {
        algo: AlgorithmSummary(
            finals=np.array(finals[algo]),
            auc=float(np.mean([normalized_auc(run.timesteps, run.returns) for run in results if run.algo == algo])),
            p_value=None if algo == reference or reference not in finals else welch_p_value(finals[algo], finals[reference]),
        )
        for algo in algos
    }


def summary_table(results: Sequence[RunResult]) -> str:
    """
    A Markdown table per algorithm: final evaluation return (mean ± std over seeds), normalized AUC of the
    learning curve (mean over seeds), Welch's t-test p-value of the final returns against the first algorithm's,
    and wall time.
    """
    reference = results[0].algo
    lines = [
        f"| algorithm | seeds | final return (mean ± std) | normalized AUC | p vs {reference} (Welch) "
        "| wall time s (mean) | steps/s (mean) |",
        "|---|---|---|---|---|---|---|",
    ]
    for algo, summary in summarize(results, reference).items():
        runs = [result for result in results if result.algo == algo]
        walls = np.array([run.wall_time_s for run in runs])
        speed = np.mean([run.n_timesteps / run.wall_time_s for run in runs])
        p_value = summary.p_value
        lines.append(
            f"| {algo} | {len(runs)} | {summary.finals.mean():.1f} ± {summary.finals.std():.1f} | {summary.auc:.1f} "
            f"| {'' if p_value is None else f'{p_value:.3f}'} | {walls.mean():.1f} | {speed:.1f} |"
        )
    return "\n".join(lines)


def plot_learning_curves(results: Sequence[RunResult], path: str | Path) -> None:
    """Mean evaluation return against timesteps per algorithm, with a 95% confidence band over seeds."""
    _plot_over_runs(results, "returns", "evaluation return", path)


def plot_initial_state_bias(results: Sequence[RunResult], path: str | Path) -> None:
    """
    Initial-state value bias ``V(s0) - sum_t gamma^t r_t`` against timesteps per algorithm (paper Fig. 4a), with a
    95% confidence band over seeds; runs without bias records are left out.
    """
    runs = [run for run in results if run.initial_state_bias]
    _plot_over_runs(runs, "initial_state_bias", "initial-state bias", path, zero_line=True)


def _plot_over_runs(
    results: Sequence[RunResult], attribute: str, ylabel: str, path: str | Path, zero_line: bool = False
) -> None:
    """One of a run's per-evaluation lists against timesteps: mean per algorithm, 95% band over its runs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for algo in dict.fromkeys(result.algo for result in results):
        runs = [result for result in results if result.algo == algo]
        length = min(len(getattr(run, attribute)) for run in runs)
        curves = np.array([getattr(run, attribute)[:length] for run in runs])
        timesteps = np.array(runs[0].timesteps[:length])
        mean = curves.mean(axis=0)
        half_width = 1.96 * curves.std(axis=0, ddof=1) / math.sqrt(len(runs)) if len(runs) > 1 else 0 * mean
        ax.plot(timesteps, mean, label=f"{algo} (n={len(runs)})")
        ax.fill_between(timesteps, mean - half_width, mean + half_width, alpha=0.25)
    if zero_line:
        ax.axhline(0.0, color="black", linewidth=0.8)
    ax.set_xlabel("environment steps")
    ax.set_ylabel(ylabel)
    if results:
        ax.set_title(results[0].env_id)
        ax.legend()
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
