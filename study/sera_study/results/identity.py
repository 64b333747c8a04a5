"""
Code identity of a ledger's runs: whether runs pooled in one group, made at different commits, ran code that trains
the same. ``study/tools/param_hashes.py --ledger-commits --write results/code_hashes.yml`` hashes each configuration
of the ledger (a variant on a task with its hyperparameters: :func:`configuration_key`) after a short seeded run at
every commit the ledger names; :func:`identity_lines` reads that table for a report's groups.
"""

import hashlib
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml

from sera_study.records import RunResult, read_record

#: The ledger's table of code hashes, in its folder
CODE_HASHES_FILE = "code_hashes.yml"
#: What the hash of a configuration covers, and what it does not
IDENTITY_CHECK = (
    "each configuration's parameters, evaluations and records after a seeded run of 2,300 steps at learning_starts "
    "256 with a 10,000-transition buffer, at each commit; it reaches neither the runs' own learning_starts nor a "
    "checkpoint or a resume, and cannot tell settings apart that only those reach"
)


def configuration_key(variant: str, env_id: str, hyperparams: dict[str, Any]) -> str:
    """``variant env_id digest``, the digest naming the hyperparameters (``config.yml`` without the budget)."""
    settings = json.dumps({k: v for k, v in hyperparams.items() if k != "n_timesteps"}, sort_keys=True, default=str)
    return f"{variant} {env_id} {hashlib.sha256(settings.encode()).hexdigest()[:8]}"


def run_commit(run: RunResult) -> tuple[str, bool]:
    """The commit a run's record names and whether its tree was clean (``("unknown", True)`` without one)."""
    args = read_record(next(Path(run.folder).glob("*/args.yml")))
    return str(args.get("git_commit") or "unknown"), bool(args.get("git_clean", True))


def load_code_hashes(ledger: str | Path) -> dict[str, dict[str, str]] | None:
    """Per commit, per configuration key, the hash (``<ledger>/code_hashes.yml``); None where the ledger has none."""
    path = Path(ledger) / CODE_HASHES_FILE
    if not path.exists():
        return None
    table = yaml.safe_load(path.read_text()) or {}
    return {str(commit): dict(column) for commit, column in (table.get("hashes") or {}).items()}


def identity_lines(groups: Sequence[Any], hashes: dict[str, dict[str, str]]) -> list[str]:
    """
    Per group whose runs come from more than one commit: whether the check's short run hashes the same at each
    (:data:`IDENTITY_CHECK` says what it covers), differs (named per commit), or cannot be told (a commit not hashed,
    or a run made from a modified tree).
    """
    lines = []
    for group in groups:
        by_commit: dict[tuple[str, bool], int] = {}
        for run in group.runs:
            commit = run_commit(run)
            by_commit[commit] = by_commit.get(commit, 0) + 1
        if len(by_commit) < 2:
            continue
        key = configuration_key(group.variant, group.env_id, group.runs[0].hyperparams)
        found = {commit: hashes.get(commit, {}).get(key) for commit, _ in by_commit}
        runs_at = ", ".join(f"{n} at {c[:7]}{'' if clean else ' (modified tree)'}" for (c, clean), n in by_commit.items())
        unknown = [c[:7] for c, value in found.items() if value is None]
        dirty = [c[:7] for c, clean in by_commit if not clean]
        if unknown:
            verdict = f"not hashed at {', '.join(unknown)}: whether the check's run hashes the same is not known"
        elif len(set(found.values())) > 1:
            verdict = "the check's run hashes DIFFERENTLY: " + ", ".join(f"{c[:7]} {h}" for c, h in found.items())
        else:
            verdict = f"the check's run hashes the same at each ({next(iter(found.values()))})"
        if dirty:
            verdict += f"; the tree at {', '.join(dirty)} was modified, which no hash of the commit covers"
        lines.append(f"- {group.label}: runs {runs_at}; {verdict}.")
    return lines


def commit_counts_line(runs: Sequence[RunResult], hashes: dict[str, dict[str, str]] | None) -> str:
    """
    One sentence of how many commits the runs come from, how many of those ``code_hashes.yml`` hashes, and how many
    runs come from the others (named), so that no page keeps such a count by hand.
    """
    by_commit: dict[str, int] = {}
    for run in runs:
        commit = run_commit(run)[0]
        by_commit[commit] = by_commit.get(commit, 0) + 1
    unhashed = {commit: n for commit, n in by_commit.items() if commit not in (hashes or {})}
    commits = f"{len(by_commit)} commit{'' if len(by_commit) == 1 else 's'}"
    if not unhashed:
        return f"The {len(runs)} published runs come from {commits}, each hashed in `{CODE_HASHES_FILE}`."
    named = ", ".join(f"{commit[:7]} ({n})" for commit, n in sorted(unhashed.items(), key=lambda item: -item[1]))
    return (
        f"The {len(runs)} published runs come from {commits}, {len(by_commit) - len(unhashed)} of them hashed in "
        f"`{CODE_HASHES_FILE}`; the runs of the {len(unhashed)} not hashed, by commit: {named}."
    )


def machines_line(runs: Sequence[RunResult]) -> str:
    """
    One sentence of where the runs ran, as each run's record says (``result.json``'s attempts: its GPU, else its CPU
    model), so that no page names a machine from memory: the runs by machine, those that ran on several (a resumed run)
    under each of their machines joined, and those recorded before runs named their CPU counted apart.
    """
    by_machine: dict[str, int] = {}
    for run in runs:
        machines = dict.fromkeys(str(name) for a in run.attempts if (name := a.get("gpu") or a.get("cpu")))
        label = " and ".join(machines)
        by_machine[label] = by_machine.get(label, 0) + 1
    unrecorded = by_machine.pop("", 0)
    named = "; ".join(f"{machine} ({n})" for machine, n in sorted(by_machine.items(), key=lambda item: -item[1]))
    if not named:
        return f"None of the {len(runs)} published runs records the machine it ran on: all were made before runs named it."
    older = f"; {unrecorded} recorded before runs named their CPU" if unrecorded else ""
    return f"Where the {len(runs)} published runs ran, by their records: {named}{older}."
