"""
Runs held back from the ledger's pages while a claim that plans them is interim: a table or figure of the arms' means
would tell the interim state as surely as the claim's own numbers, so until each arm has its planned runs, the runs a
planned claim reads, and those of every claim that shares runs with it, appear nowhere but in a count.
"""

from collections.abc import Sequence

from sera_study.claims import Claim
from sera_study.records import RunResult


def held_back(claims: Sequence[Claim] | None, runs: Sequence[RunResult]) -> tuple[list[RunResult], list[str]]:
    """
    ``runs`` without those read by an interim claim (one with ``planned`` runs an arm that one of its arms lacks) or
    by a claim that shares runs with one (its numbers are withheld as the interim claim's are: a family decided
    together, such as SERA against two baselines on the same SERA runs, shows nothing until the whole family can be
    decided), and a line for each planned claim so held saying how many runs of each arm it holds.
    """
    claims = list(claims or ())
    counts = {
        claim.id: {arm: sum(claim.reads(run) and run.variant == arm for run in runs) for arm in (claim.arm, claim.baseline)}
        for claim in claims
    }
    interim = [
        claim
        for claim in claims
        if claim.planned and any(counts[claim.id].values()) and min(counts[claim.id].values()) < claim.planned
    ]
    # shares_runs holds of a claim and itself, so the interim claims are among those holding
    holding = [claim for claim in claims if any(claim.shares_runs(short) for short in interim)]
    kept = [run for run in runs if not any(claim.reads(run) for claim in holding)]
    lines = []
    for claim in holding:
        if not claim.planned or not any(counts[claim.id].values()):
            continue
        arms = " and ".join(f"{count} of {arm}" for arm, count in counts[claim.id].items())
        waiting = [short.id for short in interim if short is not claim and claim.shares_runs(short)]
        withheld = "" if any(claim is short for short in interim) else f"; held with {', '.join(waiting)}"
        lines.append(f"- {claim.id}: {arms} ({claim.planned} an arm planned{withheld})")
    return kept, lines
