"""
Train several algorithms on one task for several seeds, each with the task's hyperparameters from
``hyperparams/<algo>.yml`` (as ``sb3-sera train``) and the caller's overrides; the runs are recorded by the run
engine (:mod:`sera_study.engine`) and summarized by the report (:mod:`sera_study.report`).
"""

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from sera_study import stats
from sera_study.backends import default_threads, execute
from sera_study.checkpoint import checkpoint_every
from sera_study.defaults import DEFAULT_ALGOS, DEFAULT_ENV, DEFAULT_SEEDS, DEFAULT_TIMESTEPS
from sera_study.engine import check_specs
from sera_study.policy_kwargs import parse_value
from sera_study.records import FINAL_EVALUATIONS, RunResult
from sera_study.registry import algorithm_classes, check_task
from sera_study.specs import check_matched, make_spec

#: The level :func:`summary` decides at
ALPHA = 0.05


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
        :func:`~sera_study.specs.check_matched`)
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


def summary(results: Sequence[RunResult], algos: Sequence[str]) -> str:
    """
    The one comparison a user came for, in a few lines: each algorithm's final return (mean and standard deviation
    over its runs), then the first algorithm against each other one: the difference of means with its 95% Welch
    interval and the decision at alpha 0.05 (:func:`.stats.decision_p_value`), or why there is none (too few runs).
    """
    returns = {algo: [r.final_return for r in results if r.variant == algo] for algo in algos}
    budget = max((r.n_timesteps for r in results), default=0)
    env_id = results[0].env_id if results else "?"
    width = max(len(algo) for algo in algos)
    lines = [f"In short: final return (mean of the last {FINAL_EVALUATIONS} evaluations) on {env_id} at {budget:,} steps"]
    for algo, values in returns.items():
        spread = f" ± {stats.sample_std(values):.1f}" if len(values) > 1 else ""
        lines.append(f"  {algo:<{width}}  {sum(values) / len(values):.1f}{spread} ({len(values)} run(s))")
    first, *others = algos
    for other in others:
        x, y = returns[first], returns[other]
        head = f"  {first} - {other}:"
        if min(len(x), len(y)) < 2:
            lines.append(f"{head} no interval from one run a side: more seeds (--seeds) to compare")
            continue
        decision = stats.decide(x, y, ALPHA)
        interval = f"{decision.difference:+.1f}, 95% Welch interval [{decision.low:.1f}, {decision.high:.1f}]"
        if decision.p is None:
            verdict = f"too few runs to decide (smallest possible p {decision.smallest_p:.3g} at {len(x)} against {len(y)})"
        else:
            ahead = f"{first} {'ahead' if decision.difference > 0 else 'behind'}"
            verdict = f"p {decision.p:.3g}: " + (
                ahead if decision.p < ALPHA else "not separated (not a finding of no difference)"
            )
        lines.append(f"{head} {interval}; {verdict}")
    return "\n".join(lines)


def reading(results: Sequence[RunResult], algos: Sequence[str]) -> str:
    """
    What :func:`summary` means at its budget, for someone new to it: whether each algorithm learned (its first
    evaluation against its final return), what runs this many can decide, and how to get a comparison that can.
    """
    by_algo = {algo: [r for r in results if r.variant == algo] for algo in algos}
    learned, too_few = [], []
    #: Whether each algorithm's mean final return is above its mean first evaluation (absent: no evaluation, or too
    #: few after learning starts to tell)
    improved: dict[str, bool] = {}
    for algo, runs in by_algo.items():
        firsts = [(run.timesteps[0], run.returns[0]) for run in runs if run.timesteps]
        if not firsts:
            continue
        if min(len(_trained_returns(run)) for run in runs) < FINAL_EVALUATIONS:
            too_few.append(algo)
            continue
        start = sum(value for _, value in firsts) / len(firsts)
        final = sum(run.final_return for run in runs) / len(runs)
        improved[algo] = final > start
        flat = "" if improved[algo] else " (no better than its first evaluation)"
        learned.append(f"{algo} {start:.0f} at step {firsts[0][0]:,} -> {final:.0f}{flat}")
    lines = ["What it means:"]
    if learned:
        lines.append(f"  Learning (mean evaluation return, first -> final): {'; '.join(learned)}.")
    if too_few:
        which = "it trains" if len(too_few) == 1 else "they train"
        lines.append(
            f"  {' and '.join(too_few)}: too few evaluations after learning starts to tell whether {which} (the final "
            f"return needs {FINAL_EVALUATIONS} after learning_starts): a longer run, or evaluations more often (--eval-freq)."
        )
    first, *others = algos
    needed = runs_to_decide()
    budget = max((r.n_timesteps for r in results), default=0)
    elsewhere = "the ledger compares at the paper's budgets, 5 to 30 runs an arm: docs/results/index.md"
    for other in others:
        x = [r.final_return for r in by_algo[first]]
        y = [r.final_return for r in by_algo[other]]
        decision = stats.decide(x, y, ALPHA) if min(len(x), len(y)) >= 2 else None
        if decision is None or decision.p is None:
            lines.append(
                f"  {min(len(x), len(y))} run(s) a side cannot tell {first} from {other} at p < {ALPHA} whatever they "
                f"score{_what_they_show(improved, (first, other))} A test that can decide needs {needed} runs a side or "
                f"more (--seeds {' '.join(map(str, range(needed)))}); {elsewhere}."
            )
        elif decision.p < ALPHA:
            lines.append(
                f"  {first} {'ahead of' if decision.difference > 0 else 'behind'} {other} on this task at {budget:,} steps "
                f"(p {decision.p:.3g}): one task at one budget, which says little of longer runs or other tasks; "
                f"{elsewhere}."
            )
        else:
            lines.append(
                f"  These runs do not separate {first} from {other} (not a finding of no difference): the interval "
                f"allows anything from {decision.low:+.1f} to {decision.high:+.1f}, and more runs (--seeds) narrow it; "
                f"{elsewhere}."
            )
    return "\n".join(lines)


def _trained_returns(run: RunResult) -> list[float]:
    """A run's evaluation returns after its learning starts (every one for an on-policy run, which has no such step)."""
    starts = int(run.hyperparams.get("learning_starts", 0) or 0)
    return [value for step, value in zip(run.timesteps, run.returns, strict=True) if step > starts]


def _what_they_show(improved: dict[str, bool], algos: Sequence[str]) -> str:
    """What runs too few to decide still show of ``algos``: which improved on their first evaluation and which not."""
    flat = [algo for algo in algos if improved.get(algo) is False]
    if not flat:
        return (
            ": each ended above its first evaluation, so these runs show that each trains, not which is better."
            if all(improved.get(algo) for algo in algos)
            else "."
        )
    which = " and ".join(flat)
    return (
        f": {which} ended no better than {'its' if len(flat) == 1 else 'their'} first evaluation, so these runs show "
        f"no learning of {'it' if len(flat) == 1 else 'them'} at this budget yet, and nothing of which is better."
    )


def runs_to_decide(threshold: float = ALPHA) -> int:
    """The fewest runs a side (equal sides) at which :func:`.stats.decide` can give a p below ``threshold``."""
    n = 2
    while stats.smallest_p_value(n, n) >= threshold:
        n += 1
    return n
