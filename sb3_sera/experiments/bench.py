"""
A grid of runs (algorithm variants x tasks x seeds) from a YAML file, on a local process pool or a Ray cluster.

The grid file::

    algorithms:              # variant name -> its algorithm and hyperparameters
      serasac: {}
      ensemble_mean: {algo: serasac, target_aggregation: mean}
      masac: {}
    tasks: [sb3_sera/HalfCheetah-6x1-v0, sb3_sera/SimpleSpread-v0]
    seeds: [0, 1, 2]
    n_timesteps: 50000
    eval_freq: 5000          # optional, default n_timesteps / 10
    eval_episodes: 5         # optional
    hyperparams: {learning_starts: 5000}   # optional, for every variant (a variant's own values win)

Everything is checked before the first run starts. Each run writes its rl-zoo3-style folder
``<out>/<variant>/<env_name>_<seed>/``; a finished run is never run again, so an interrupted grid resumes.
"""

import inspect
from pathlib import Path
from typing import Any

import gymnasium as gym
import yaml

from sb3_sera.experiments.compare import RunResult, RunSpec, algorithm_classes, env_name, execute, summary_table

GRID_KEYS = {"algorithms", "tasks", "seeds", "n_timesteps", "eval_freq", "eval_episodes", "hyperparams"}


def load_grid(path: str | Path) -> list[RunSpec]:
    """
    Read and check a grid file; raise ``ValueError`` naming any unknown key, algorithm, task or hyperparameter
    with the allowed ones.

    :return: the runs, variant by variant, then task by task, then seed by seed
    """
    grid = yaml.safe_load(Path(path).read_text())
    if not isinstance(grid, dict):
        raise ValueError(f"{path}: a grid file is a mapping with keys {sorted(GRID_KEYS)}")
    unknown_keys = set(grid) - GRID_KEYS
    if unknown_keys:
        raise ValueError(f"{path}: unknown key(s) {sorted(unknown_keys)}; allowed: {sorted(GRID_KEYS)}")
    missing = {"algorithms", "tasks", "seeds", "n_timesteps"} - set(grid)
    if missing:
        raise ValueError(f"{path}: missing key(s) {sorted(missing)}")
    classes = algorithm_classes()
    common: dict[str, Any] = grid.get("hyperparams") or {}
    variants: dict[str, tuple[str, dict[str, Any]]] = {}
    for name, entry in (grid["algorithms"] or {}).items():
        params = dict(entry or {})
        algo = params.pop("algo", name)
        if algo not in classes:
            raise ValueError(f"{path}: variant {name!r} names unknown algorithm {algo!r}; known: {sorted(classes)}")
        hyperparams = {**common, **params}
        accepted = set(inspect.signature(classes[algo]).parameters) - {"policy", "env", "seed", "verbose"}
        unknown = sorted(set(hyperparams) - accepted)
        if unknown:
            raise ValueError(
                f"{path}: variant {name!r}: unknown hyperparameter(s) {unknown} for {algo}; allowed: {sorted(accepted)}"
            )
        variants[name] = (algo, hyperparams)
    unknown_tasks = [task for task in grid["tasks"] if task not in gym.registry]
    if unknown_tasks:
        registered = sorted(env_id for env_id in gym.registry if env_id.startswith("sb3_sera/"))
        raise ValueError(f"{path}: unknown task(s) {unknown_tasks}; registered ids include {registered} and Gymnasium's")
    n_timesteps = int(grid["n_timesteps"])
    eval_freq = int(grid.get("eval_freq", max(n_timesteps // 10, 1)))
    episodes = int(grid.get("eval_episodes", 5))
    return [
        RunSpec(name, algo, task, int(seed), n_timesteps, hyperparams, eval_freq, episodes)
        for name, (algo, hyperparams) in variants.items()
        for task in grid["tasks"]
        for seed in grid["seeds"]
    ]


def run_grid(
    path: str | Path, out_dir: str, n_jobs: int | None = None, ray_address: str | None = None
) -> dict[str, list[RunResult]]:
    """
    Run a grid file's runs (see :func:`load_grid`) and write ``<out>/<env_name>_summary.md`` per task.

    :return: the results by task
    """
    specs = load_grid(path)
    results = execute(specs, out_dir, n_jobs=n_jobs, ray_address=ray_address)
    by_task: dict[str, list[RunResult]] = {}
    for result in results:
        by_task.setdefault(result.env_id, []).append(result)
    for task, task_results in by_task.items():
        table = summary_table(task_results)
        (Path(out_dir) / f"{env_name(task)}_summary.md").write_text(f"{task}\n\n{table}\n")
    return by_task
