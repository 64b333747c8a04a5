"""The results page's readings: every number the ledger gives filled in by code, and a clear error for the rest."""

import numpy as np
import pytest

from sera_study.records import RunResult
from sera_study.results import stats
from sera_study.results.claims import Claim, evaluate
from sera_study.results.groups import group_runs
from sera_study.results.readings import fill_readings

TASK = "HalfCheetah-v5"


def _run(variant: str, seed: int, final: float, wall: float = 100.0, resumed: bool = False) -> RunResult:
    # Evaluations at 1K, 2K and 3K steps; the last three (the final return's) average to ``final``
    return RunResult(
        variant, variant, TASK, seed, 3000, wall, final, timesteps=[1000, 2000, 3000],
        returns=[final - 3.0, final, final + 3.0], resumes=[{"from_step": 2000}] if resumed else [],
    )  # fmt: skip


@pytest.fixture(scope="module")
def ledger():
    """Five runs of SERASAC ending at 10-14 and five of SAC at 4-8, and one exploratory claim between them."""
    runs = [_run("serasac", seed, 10.0 + seed, wall=1000.0 + seed, resumed=seed == 3) for seed in range(5)]
    runs += [_run("sac", seed, 4.0 + seed) for seed in range(5)]
    groups = group_runs(runs)
    decided = evaluate([Claim("return-sac", TASK, 3000, "final_return", "serasac", "sac", "higher")], groups)
    return decided, groups


def _fill(ledger, text: str) -> str:
    return fill_readings(text, *ledger)


def test_a_claims_numbers_are_the_ledgers(ledger):
    # Means 12 and 6, each arm's sd sqrt(2.5); Welch: se 1, 8 degrees of freedom, t(0.975, 8) = 2.306
    assert _fill(ledger, "{{claim: return-sac | n}}") == "5 vs 5"
    assert _fill(ledger, "{{claim: return-sac | interval}}") == "6 [3.69, 8.31]"
    assert _fill(ledger, "{{claim: return-sac | arm mean}} and {{claim: return-sac | baseline mean sd}}") == "12 and 6 ± 2"
    # Every SERASAC run above every SAC run: the permutation p is 2/252, the least five against five allow
    assert _fill(ledger, "{{claim: return-sac | permutation p}}") == "0.0079"
    assert _fill(ledger, "{{claim: return-sac | test}}") == "BH q 0.0079, BY q 0.0079: supported"
    assert _fill(ledger, "{{claim: return-sac | high % of baseline}}") == f"{100 * 8.3060 / 6:.1f}%"
    std = float(np.std([10, 11, 12, 13, 14], ddof=1))
    assert _fill(ledger, "{{claim: return-sac | power at 2}}") == f"{stats.welch_power(2, std, std, 5, 5):.2f}"
    assert _fill(ledger, "{{claim: return-sac | runs for 80% power at 2}}") == str(stats.runs_for_power(2, std, std))


def test_a_groups_numbers_are_the_ledgers(ledger):
    assert _fill(ledger, "{{runs: serasac | HalfCheetah-v5 | 3000 | finals}}") == "10.0, 11.0, 12.0, 13.0 and 14.0"
    assert _fill(ledger, "{{runs: sac | HalfCheetah-v5 | 3,000 | mean sd}}") == "6 ± 2"
    assert _fill(ledger, "{{runs: serasac | HalfCheetah-v5 | 3000 | resumed seeds}}") == "seed 3"
    assert _fill(ledger, "{{runs: sac | HalfCheetah-v5 | 3000 | resumed seeds}}") == "none"
    assert _fill(ledger, "{{runs: serasac | HalfCheetah-v5 | 3000 | wall times}}") == "1,000-1,004 s"
    # Read at step 2,000: the mean of the evaluations at 1K and 2K, final - 1.5, so 10.5 ± 1.6 for SERASAC
    assert _fill(ledger, "{{runs: serasac | HalfCheetah-v5 | 3000 | at 2000}}") == "10.5 ± 1.6"


def test_the_text_is_wrapped_again_with_each_number_on_one_line(ledger):
    text = "- " + "word " * 20 + "{{runs: sac |\n  HalfCheetah-v5 | 3000 | mean sd}} " + "word " * 20
    filled = _fill(ledger, text)
    assert "6 ± 2" in filled.splitlines()[0] or "6 ± 2" in filled.splitlines()[1]
    assert all(len(line) <= 120 for line in filled.splitlines()) and filled.splitlines()[1].startswith("  word")


@pytest.mark.parametrize(
    ("text", "error"),
    [
        ("{{claim: nope | n}}", r"\{\{claim: nope \| n\}\}: no claim 'nope'"),
        ("{{claim: return-sac | spread}}", r"no field 'spread': the fields are n, arm mean, .*power at <effect>"),
        ("{{runs: tqc | HalfCheetah-v5 | 3000 | mean}}", r"no group .* is .tqc. on HalfCheetah-v5 at 3000 steps; its groups"),
        ("{{runs: sac | HalfCheetah-v5 | mean}}", r"a placeholder is \{\{claim: <id> \| <field>\}\} or"),
        ("{{runs: sac | HalfCheetah-v5 | 3000 | at 500}}", r"a run has no evaluation up to step 500"),
    ],
)  # fmt: skip
def test_what_the_ledger_cannot_fill_is_a_clear_error(ledger, text, error):
    with pytest.raises(ValueError, match=error):
        _fill(ledger, text)
