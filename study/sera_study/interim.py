"""
Runs held back from the ledger's pages while a claim that plans them is interim: a table or figure of the arms' means
would tell the interim state as surely as the claim's own numbers, so until each arm has its planned runs, the runs a
planned claim reads appear nowhere but in a count.
"""

from collections.abc import Sequence

from sera_study.claims import Claim
from sera_study.records import RunResult


def held_back(claims: Sequence[Claim] | None, runs: Sequence[RunResult]) -> tuple[list[RunResult], list[str]]:
    """
    ``runs`` without those read by an interim claim (one with ``planned`` runs an arm that one of its arms lacks), and
    a line for each such claim saying how many runs of each arm it holds back.
    """
    kept, lines = list(runs), []
    for claim in claims or ():
        if not claim.planned:
            continue
        read = [run for run in runs if claim.reads(run)]
        counts = {arm: sum(run.variant == arm for run in read) for arm in (claim.arm, claim.baseline)}
        if read and min(counts.values()) < claim.planned:
            kept = [run for run in kept if run not in read]
            arms = " and ".join(f"{count} of {arm}" for arm, count in counts.items())
            lines.append(f"- {claim.id}: {arms} ({claim.planned} an arm planned)")
    return kept, lines
