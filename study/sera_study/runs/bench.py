"""
A grid of runs (algorithm variants x tasks x seeds) from a YAML file, on a local process pool or a Ray cluster.

The grid file::

    algorithms:              # variant name -> its algorithm and hyperparameter overrides
      serasac: {}
      ensemble_mean: {algo: serasac, target_aggregation: mean}
      masac: {}
    tasks: [sb3_sera/HalfCheetah-6x1-v0, sb3_sera/SimpleSpread-v0]
    seeds: [0, 1, 2]
    n_timesteps: 50000
    eval_freq: 5000          # optional, default n_timesteps / 10
    eval_episodes: 5         # optional
    hyperparams: {learning_starts: 5000}   # optional overrides for every variant (a variant's own values win)
    studies: [batch_size]    # optional: shared settings the arms may differ in (the grid is about them)

Each run starts from the task's entry in ``hyperparams/<algo>.yml`` (as ``sb3-sera train``), then the grid's
``hyperparams``, then the variant's own values. The variants compared on a task must share the settings every
comparison holds fixed (``learning_starts``, ``batch_size``, ``buffer_size``, ``gamma``, ``tau``, ``train_freq``,
``gradient_steps``, the budget and the evaluations) unless ``studies`` names them. Everything is checked before the
first run starts (each variant's model is built once on each task). Each run writes its rl-zoo3-style folder
``<out>/<variant>/<env_name>_<id>/`` with its records; a finished run is never run again, and an unfinished one goes
on from its last checkpoint, so an interrupted grid resumes where it stopped.
"""

from pathlib import Path
from typing import Any

import yaml

from sera_study.runs.backends import execute
from sera_study.runs.checkpoint import checkpoint_every
from sera_study.runs.engine import check_specs
from sera_study.records import RunResult
from sera_study.registry import algorithm_classes, check_task
from sera_study.runs.specs import RunSpec, check_matched, make_spec

GRID_KEYS = {"algorithms", "tasks", "seeds", "n_timesteps", "eval_freq", "eval_episodes", "hyperparams", "studies"}


class _UniqueKeyLoader(yaml.SafeLoader):
    """Safe YAML loading that refuses a key given twice in one mapping (YAML would keep the last silently)."""


def _unique_mapping(loader: yaml.SafeLoader, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
    seen: set[Any] = set()
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if key in seen:
            raise ValueError(f"line {key_node.start_mark.line + 1}: the key {key!r} is given twice")
        seen.add(key)
    return loader.construct_mapping(node, deep=deep)


_UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _unique_mapping)


def _integer(path: str | Path, key: str, value: Any) -> int:
    """``value`` as an integer (``3e5`` and ``300000.0`` included), else ``ValueError`` naming the key."""
    if isinstance(value, bool) or not isinstance(value, int | float) or float(value) != int(value):
        raise ValueError(f"{path}: {key}: {value!r} is not an integer")
    return int(value)


def read_grid(path: str | Path) -> dict[str, Any]:
    """The grid file's mapping, its keys, their types and its tasks checked (``ValueError`` naming the key)."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"{path}: no such grid file")
    try:
        grid = yaml.load(Path(path).read_text(), Loader=_UniqueKeyLoader)
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None
    if not isinstance(grid, dict):
        raise ValueError(f"{path}: a grid file is a mapping with keys {sorted(GRID_KEYS)}")
    unknown_keys = set(grid) - GRID_KEYS
    if unknown_keys:
        raise ValueError(f"{path}: unknown key(s) {sorted(unknown_keys)}; allowed: {sorted(GRID_KEYS)}")
    missing = {"algorithms", "tasks", "seeds", "n_timesteps"} - set(grid)
    if missing:
        raise ValueError(f"{path}: missing key(s) {sorted(missing)}")
    for key, kind in (("algorithms", dict), ("tasks", list), ("seeds", list)):
        if not isinstance(grid[key], kind) or not grid[key]:
            example = {"algorithms": "{serasac: {}, sac: {}}", "tasks": "[HalfCheetah-v5]", "seeds": "[0, 1, 2]"}[key]
            raise ValueError(f"{path}: {key}: {grid[key]!r} is not a non-empty {kind.__name__} (e.g. {key}: {example})")
    for task in grid["tasks"]:
        if not isinstance(task, str):
            raise ValueError(f"{path}: tasks: {task!r} is not a Gymnasium id")
        try:
            check_task(task)
        except ValueError as error:
            raise ValueError(f"{path}: {error}") from None
    studies = grid.get("studies") or []
    if not isinstance(studies, list) or not all(isinstance(key, str) for key in studies):
        raise ValueError(f"{path}: studies: {studies!r} is not a list of setting names (e.g. studies: [batch_size])")
    if not isinstance(grid.get("hyperparams") or {}, dict):
        raise ValueError(f"{path}: hyperparams: {grid['hyperparams']!r} is not a mapping of hyperparameters")
    return grid


def _variants(path: str | Path, grid: dict[str, Any]) -> dict[str, tuple[str, dict[str, Any]]]:
    """Each variant's algorithm and overrides (the grid's ``hyperparams``, then the variant's own values)."""
    classes = algorithm_classes()
    common = grid.get("hyperparams") or {}
    variants: dict[str, tuple[str, dict[str, Any]]] = {}
    for name, entry in grid["algorithms"].items():
        if entry is not None and not isinstance(entry, dict):
            raise ValueError(f"{path}: variant {name!r}: {entry!r} is not a mapping (e.g. {name}: {{algo: serasac}})")
        params = dict(entry or {})
        algo = params.pop("algo", name)
        if algo not in classes:
            raise ValueError(f"{path}: variant {name!r} names unknown algorithm {algo!r}; known: {sorted(classes)}")
        variants[name] = (algo, {**common, **params})
    return variants


def load_grid(path: str | Path, num_threads: int | None = 1, device: str = "auto") -> list[RunSpec]:
    """
    Read and check a grid file; raise ``ValueError`` naming any unknown key, algorithm, task or hyperparameter
    with the allowed ones.

    :param num_threads: torch threads of each run (None: torch's default)
    :param device: torch device of each run
    :return: the runs, seed by seed, then task by task, then variant by variant: a grid stopped part way has
        every variant at its first seeds
    """
    grid = read_grid(path)
    seeds = [_integer(path, "seeds", seed) for seed in grid["seeds"]]
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"{path}: seeds: {grid['seeds']} repeats a seed")
    variants = _variants(path, grid)
    n_timesteps = _integer(path, "n_timesteps", grid["n_timesteps"])
    eval_freq = _integer(path, "eval_freq", grid.get("eval_freq", max(n_timesteps // 10, 1)))
    episodes = _integer(path, "eval_episodes", grid.get("eval_episodes", 5))
    specs = []
    for seed in seeds:
        for task in grid["tasks"]:
            for name, (algo, overrides) in variants.items():
                try:
                    spec = make_spec(
                        variant=name,
                        algo=algo,
                        env_id=task,
                        seed=seed,
                        n_timesteps=n_timesteps,
                        overrides=overrides,
                        eval_freq=eval_freq,
                        n_eval_episodes=episodes,
                        num_threads=num_threads,
                        device=device,
                    )
                except ValueError as error:
                    raise ValueError(f"{path}: variant {error}") from None
                specs.append(spec)
    for spec in specs:
        spec.studies = list(grid.get("studies") or [])
    check_specs(specs)
    check_matched(specs, str(path))
    return specs


def run_grid(
    path: str | Path,
    out_dir: str | Path,
    n_jobs: int | None = None,
    ray_address: str | None = None,
    num_threads: int | None = 1,
    device: str = "auto",
    checkpoint_freq: int | None = None,
    keep_checkpoints: bool = False,
    accept_older: str | None = None,
    gpus_per_run: float | None = None,
) -> list[RunResult]:
    """
    Run a grid file's runs (see :func:`load_grid`).

    :param checkpoint_freq: steps between a run's checkpoints (0: none; None: :func:`.checkpoint_every`'s default): an
        interrupted grid resumes each unfinished run from its last one (:mod:`~sera_study.runs.checkpoint`)
    :param keep_checkpoints: keep a finished run's last checkpoint (removed by default)
    :param accept_older: why finished runs made by other code are read back (see :func:`.execute`)
    :param gpus_per_run: each run's share of a GPU, or whole GPUs (see :func:`.execute`; None: none shared)
    :return: the results, in the grid's order
    """
    specs = load_grid(path, num_threads, device)
    for spec in specs:
        spec.checkpoint_freq = checkpoint_every(checkpoint_freq, spec.n_timesteps)
        spec.keep_checkpoints = keep_checkpoints
    return execute(
        specs, out_dir, n_jobs=n_jobs, ray_address=ray_address, accept_older=accept_older, gpus_per_run=gpus_per_run
    )
