"""
Runs held back from the ledger's pages while a claim that plans them is interim: a table or figure of the arms' means
would tell the interim state as surely as the claim's own numbers, so until each arm has its planned runs, the runs a
planned claim reads, and those of every claim that waits with it (:func:`~sera_study.results.claims.waits_for`: its family
sharing runs, or a claim sharing the runs of an arm it lacks), appear nowhere but in a count; a run that a claim
printed meanwhile reads (a baseline's, printed before) stays.
"""

from collections.abc import Sequence

from sera_study.records import RunResult
from sera_study.results.claims import Claim, waits_for


def held_back(claims: Sequence[Claim] | None, runs: Sequence[RunResult]) -> tuple[list[RunResult], list[str]]:
    """
    ``runs`` without those read by an interim claim (one with ``planned`` runs an arm that one of its arms lacks) or
    by a claim that waits with one (its numbers are withheld as the interim claim's are: a family decided together,
    such as SERA against two baselines on the same SERA runs, shows nothing until the whole family can be decided),
    but for those a printed claim reads; and a line for each planned claim so held saying how many runs of each arm it
    reads, "(shown)" after an arm whose runs a printed claim keeps on the pages.
    """
    claims = list(claims or ())
    counts = {
        claim.id: {arm: sum(claim.reads(run) and run.variant == arm for run in runs) for arm in (claim.arm, claim.baseline)}
        for claim in claims
    }
    interim = {
        claim.id: (claim, {arm for arm, count in counts[claim.id].items() if count < claim.planned})
        for claim in claims
        if claim.planned and any(counts[claim.id].values()) and min(counts[claim.id].values()) < claim.planned
    }
    holding = [claim for claim in claims if any(waits_for(claim, *short) for short in interim.values())]
    printed = [claim for claim in claims if not any(claim is held for held in holding)]
    kept: list[RunResult] = []
    held: list[RunResult] = []
    for run in runs:
        shown = not any(claim.reads(run) for claim in holding) or any(claim.reads(run) for claim in printed)
        (kept if shown else held).append(run)
    lines = []
    for claim in holding:
        if not claim.planned or not any(counts[claim.id].values()):
            continue
        arms = " and ".join(
            f"{count} of {arm}{' (shown)' if count and not any(claim.reads(r) and r.variant == arm for r in held) else ''}"
            for arm, count in counts[claim.id].items()
        )
        waiting = [short.id for short, lacking in interim.values() if short is not claim and waits_for(claim, short, lacking)]
        withheld = "" if claim.id in interim else f"; held with {', '.join(waiting)}"
        lines.append(f"- {claim.id}: {arms} ({claim.planned} an arm planned{withheld})")
    return kept, lines
