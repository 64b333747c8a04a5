"""
What was seen before each claim: from the ledger's git history, the commit that first declared a claim in
``claims.yml``, the runs of each of its arms already in the ledger then, and the claim's result on the runs added
after it alone (the confirmatory part of the evidence) beside the result on every run.
"""

import dataclasses
import subprocess
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sera_study.records import RunResult
from sera_study.results.claims import Claim, ClaimResult, Seen, evaluate
from sera_study.results.claims_text import interval_text
from sera_study.results.report import group_runs


@dataclass(frozen=True)
class Declaration:
    """The commit that first declared a claim, and the runs the ledger held then."""

    #: Its abbreviated hash and its date (YYYY-MM-DD)
    commit: str
    date: str
    #: The ledger's run folders at that commit, as ``<variant>/<env_name>_<id>``
    runs: frozenset[str]


def _git(folder: Path, *args: str) -> str | None:
    """``git args`` in ``folder``'s repository, or None where git or the history is not at hand."""
    try:
        done = subprocess.run(["git", "-C", str(folder), *args], capture_output=True, text=True, timeout=60, check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    return done.stdout if done.returncode == 0 else None


def declaration(ledger: str | Path, claim_id: str, claims_file: str = "claims.yml") -> Declaration | None:
    """
    The commit that first added the claim ``claim_id`` to the ledger's claims file, with the runs the ledger held at
    it; None where the ledger has no git history or the claim is not committed yet.
    """
    folder = Path(ledger).resolve()
    top = _git(folder, "rev-parse", "--show-toplevel")
    if top is None:
        return None
    root = Path(top.strip()).resolve()
    relative = folder.relative_to(root).as_posix()
    # Flow-style entries ({id: name, ...}): the name followed by its comma, so that no longer id that starts with it
    # matches
    log = _git(root, "log", "--reverse", "--format=%h %cs", "-S", f"id: {claim_id},", "--", f"{relative}/{claims_file}")
    if not log or not log.strip():
        return None
    commit, date = log.splitlines()[0].split()
    listing = _git(root, "ls-tree", "-r", "--name-only", commit, "--", relative) or ""
    runs = {"/".join(Path(path).parts[1:3]) for path in listing.splitlines() if len(Path(path).parts) > 3}
    return Declaration(commit, date, frozenset(runs))


def _run_name(run: RunResult, ledger: Path) -> str:
    return Path(run.folder).resolve().relative_to(ledger).as_posix()


def seen_before_lines(results: Sequence[ClaimResult], runs: Sequence[RunResult], ledger: str | Path) -> list[str]:
    """
    A Markdown table, for each claim of ``results``: when it was declared, how many runs of each arm (of those it
    reads) the ledger held then and holds now, and its result on the runs added after the declaration alone
    (unadjusted: the difference with its Welch interval and the decision p).
    """
    folder = Path(ledger).resolve()
    rows = []
    for result in results:
        claim = result.claim
        declared = declaration(folder, claim.id)
        if declared is None:
            rows.append(f"| {claim.id} | not committed, or no git history | | | |")
            continue
        after = _alone(claim, [run for run in runs if _run_name(run, folder) not in declared.runs])
        counts = []
        for variant, now in ((claim.arm, len(result.arm_values)), (claim.baseline, len(result.baseline_values))):
            then = sum(
                1 for run in runs if run.variant == variant and _run_name(run, folder) in declared.runs and claim.reads(run)
            )
            counts.append(f"{then} of {now}")
        rows.append(f"| {claim.id} | {declared.commit} ({declared.date}) | {counts[0]} | {counts[1]} | {after} |")
    if not rows:
        return []
    return [
        "| claim | declared at | SERA runs in the ledger then, of now | baseline runs then, of now | on the runs added "
        "after: difference [95% Welch CI], p (unadjusted) |",
        "|---|---|---|---|---|",
        *rows,
    ]


def _alone(claim: Claim, runs: Sequence[RunResult], **changes: Any) -> str:
    """
    The claim, with ``changes``, decided on ``runs`` alone as a claim of its own (no family; interim until the runs it
    plans), in a few words: its runs, the difference with its Welch interval and p, or its verdict.
    """
    result = evaluate([dataclasses.replace(claim, primary=False, **changes)], group_runs(list(runs)))[0]
    if result.difference is None:
        # Counted here: where an arm has no runs, the result holds the other's none either
        counts = [sum(run.variant == arm and claim.reads(run) for run in runs) for arm in (claim.arm, claim.baseline)]
        note = f" ({result.note})" if result.note else ""
        return f"{counts[0]} and {counts[1]} runs: {result.verdict}{note}"
    p = f", p {result.p_value:.3g}" if result.p_value is not None else f" ({result.verdict})"
    return f"{len(result.arm_values)} against {len(result.baseline_values)}: {interval_text(result)}{p}"


def unseen_lines(results: Sequence[ClaimResult], runs: Sequence[RunResult], seen: Sequence[Seen]) -> list[str]:
    """
    A line for each decided claim whose arm has runs :class:`.Seen` before its declaration: the claim on the same runs
    less those (unadjusted, no runs planned: the difference with its Welch interval and the decision p). Nothing for
    a claim still interim or withheld, whose numbers the pages do not show yet.
    """
    lines = []
    for result in results:
        if result.withheld or result.difference is None:
            continue
        for entry in seen:
            if (entry.arm, entry.task) != (result.claim.arm, result.claim.task):
                continue
            kept = [run for run in runs if (run.variant, run.env_id) != (entry.arm, entry.task) or run.seed not in entry.seeds]
            without = _alone(result.claim, kept, planned=0)
            seeds = " and ".join(str(seed) for seed in entry.seeds)
            lines.append(f"- {result.claim.id} without {entry.arm}'s seeds {seeds} (seen as {entry.seen_as}'s): {without}")
    return lines
