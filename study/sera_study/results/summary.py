"""
What a comparison's runs say, for the person who ran it: each algorithm's final return, the first against each other
one with its interval and decision (:func:`summary`), and what that means at its budget (:func:`reading`). ``sb3-sera
compare`` prints them under its runs.
"""

from collections.abc import Sequence

from sera_study.records import FINAL_EVALUATIONS, RunResult
from sera_study.results import stats

#: The level :func:`summary` decides at
ALPHA = 0.05


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
