"""
Train several algorithms on one task for several seeds, each with the task's hyperparameters from
``hyperparams/<algo>.yml`` (as ``sb3-sera train``) and the caller's overrides; the runs are recorded by the run
engine (:mod:`sera_study.runs.engine`) and summarized above it (:mod:`sera_study.results.summary`, the report).
"""

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from sera_study.runs.backends import default_threads, execute
from sera_study.runs.checkpoint import checkpoint_every
from sera_study.defaults import DEFAULT_ALGOS, DEFAULT_ENV, DEFAULT_SEEDS, DEFAULT_TIMESTEPS
from sera_study.runs.engine import check_specs
from sera_study.runs.policy_kwargs import parse_value
from sera_study.records import RunResult
from sera_study.registry import algorithm_classes, check_task
from sera_study.runs.specs import check_matched, make_spec

def parse_params(items: Sequence[str], algos: Sequence[str]) -> tuple[dict[str, Any], dict[str, dict[str, Any]]]:
    """
    ``-params`` items: ``key:value`` for every algorithm, ``algo:key:value`` for one algorithm (one of ``algos`` or
    any known algorithm's name, so that a name not compared is refused rather than read as a key).

    :return: the common overrides and the per-algorithm ones
    """
    common: dict[str, Any] = {}
    per_algo: dict[str, dict[str, Any]] = {}
    for item in items:
        head, sep, rest = item.partition(":")
        if not sep or not head or not rest:
            raise ValueError(
                f"-params item {item!r} is invalid: expected key:value or algo:key:value (e.g. serasac:sera_alpha:0.3)"
            )
        key, sep, value = rest.partition(":")
        if (head in algos or head in algorithm_classes()) and sep and key.isidentifier():
            per_algo.setdefault(head, {})[key] = parse_value(value)
        else:
            common[head] = parse_value(rest)
    return common, per_algo


def run_comparison(
    algos: Sequence[str] = DEFAULT_ALGOS,
    env_id: str = DEFAULT_ENV,
    seeds: Sequence[int] = DEFAULT_SEEDS,
    n_timesteps: int = DEFAULT_TIMESTEPS,
    out_dir: str | Path = "logs/compare",
    params: dict[str, Any] | None = None,
    algo_params: dict[str, dict[str, Any]] | None = None,
    eval_freq: int = 1000,
    n_eval_episodes: int = 5,
    n_jobs: int | None = None,
    num_threads: int | None = None,
    device: str = "auto",
    progress_bar: bool = True,
    studies: Sequence[str] = (),
    checkpoint_freq: int | None = None,
    keep_checkpoints: bool = False,
    accept_older: str | None = None,
) -> list[RunResult]:
    """
    Train every algorithm on every seed, ``n_jobs`` runs at a time (default: one per core). Every setting is checked
    for every algorithm before the first run.

    :param params: overrides for every algorithm
    :param algo_params: overrides per algorithm (they win over ``params``)
    :param num_threads: torch threads per run (default: the cores divided among the ``n_jobs`` runs)
    :param studies: shared settings the algorithms may differ in (every other one must be the same for all:
        :func:`~sera_study.runs.specs.check_matched`)
    :param checkpoint_freq: steps between a run's checkpoints (0: none; None: :func:`.checkpoint_every`'s default):
        the same command resumes an interrupted run from its last one
    :param keep_checkpoints: keep a finished run's last checkpoint (removed by default)
    :param accept_older: why finished runs made by other code are read back (see :func:`.execute`)
    :return: the results, ordered as ``algos`` x ``seeds``
    """
    known = algorithm_classes()
    unknown = [algo for algo in algos if algo not in known]
    if unknown:
        raise ValueError(f"Unknown algorithm(s) {unknown}: expected names among {sorted(known)}")
    stray = sorted(set(algo_params or {}) - set(algos))
    if stray:
        raise ValueError(f"-params name algorithm(s) {stray} that are not compared; compared: {list(algos)}")
    check_task(env_id)
    if n_timesteps < 1:
        raise ValueError(f"n_timesteps={n_timesteps} is out of range: the budget of a run must be an integer >= 1")
    if eval_freq > n_timesteps:
        raise ValueError(f"eval_freq={eval_freq} exceeds n_timesteps={n_timesteps}: no evaluation would run")
    n_jobs = min(n_jobs or os.cpu_count() or 1, len(algos) * len(seeds))
    threads = default_threads(n_jobs) if num_threads is None else num_threads
    specs = [
        make_spec(
            variant=algo,
            algo=algo,
            env_id=env_id,
            seed=seed,
            n_timesteps=n_timesteps,
            overrides={**(params or {}), **(algo_params or {}).get(algo, {})},
            eval_freq=eval_freq,
            n_eval_episodes=n_eval_episodes,
            num_threads=threads,
            device=device,
        )
        for algo in algos
        for seed in seeds
    ]
    for spec in specs:
        spec.studies = list(studies)
        spec.checkpoint_freq = checkpoint_every(checkpoint_freq, n_timesteps)
        spec.keep_checkpoints = keep_checkpoints
    check_specs(specs)
    check_matched(specs)
    return execute(specs, out_dir, n_jobs=n_jobs, progress_bar=progress_bar, accept_older=accept_older)
