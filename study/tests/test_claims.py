"""The paper's claims on run records: per-run measures, tests, the Holm family and verdicts by hand."""

import json
import shutil
import subprocess
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml
from scipy import stats

from sb3_sera.common.evaluation import BIAS_FILE, DIAGNOSTICS_FILE
from sera_study.results import claims, claims_text, measures
from sera_study.results.declared import declaration, seen_before_lines, unseen_lines
from sera_study.results.report import group_runs, load_runs
from sera_study.results.stats import benjamini_hochberg
from tests.helpers import ROOT


def _claim_run(tmp_path: Path, variant: str, seed: int, mc_corr: float, finals: list[float]):
    """A finished run whose last evaluation records ``mc_error_corr`` and whose curve is ``finals``."""
    folder = tmp_path / variant / f"HalfCheetah-v5_{seed + 1}"
    (folder / "HalfCheetah-v5").mkdir(parents=True)
    args = {"algo": "serasac", "variant": variant, "env": "HalfCheetah-v5", "seed": seed, "n_timesteps": 300}
    (folder / "HalfCheetah-v5" / "args.yml").write_text(yaml.safe_dump(args))
    (folder / "HalfCheetah-v5" / "config.yml").write_text(yaml.safe_dump({"n_timesteps": 300, "learning_starts": 100}))
    steps = np.array([100, 200, 300])
    np.savez(folder / "evaluations.npz", timesteps=steps, results=np.array(finals)[:, None], ep_lengths=np.ones((3, 1)))
    # Values -5, 13, 9 against discounted returns 0, 10, 10: after learning_starts (steps 200, 300) the biases are
    # 3 and -1 against returns of 10 and 10, a relative bias of (3 + 1) / 20 = 0.2
    values, returns = np.array([[-5.0], [13.0], [9.0]]), np.array([[0.0], [10.0], [10.0]])
    np.savez(folder / BIAS_FILE, timesteps=steps, values=values, discounted_returns=returns)
    np.savez(
        folder / DIAGNOSTICS_FILE,
        timesteps=steps,
        mc_error_corr=np.array([0.9, 0.9, mc_corr]),
        td_error_corr=np.array([0.5, 0.5, mc_corr / 2]),
        td_target_var=np.array([1.0, 4.0, 9.0]),
        td_target_mean=np.array([1.0, 2.0, 6.0]),
    )
    (folder / "result.json").write_text(json.dumps({"wall_time_s": 1.0}))


def _decided(tmp_path, claims_list=None):
    runs, _ = load_runs([tmp_path])
    groups = group_runs(runs)
    return runs, groups, claims.evaluate(claims_list if claims_list is not None else claims.default_claims(groups), groups)


def test_claims_by_hand(tmp_path):
    for seed, corr in enumerate([0.2, 0.3, 0.4, 0.3]):
        _claim_run(tmp_path, "serasac", seed, corr, [0.0, 10.0, 20.0])
    for seed, corr in enumerate([0.6, 0.7, 0.8, 0.7]):
        _claim_run(tmp_path, "sera_nolr", seed, corr, [0.0, 10.0, 30.0])
    runs, _, decided = _decided(tmp_path)
    run = next(run for run in runs if run.variant == "serasac")
    assert measures.relative_bias(run) == pytest.approx(0.2)
    # After learning_starts (steps 200, 300) the biases are 3 and -1: magnitude (3 + 1) / 2, signed (3 - 1) / 2
    assert measures.abs_bias(run) == pytest.approx(2.0) and measures.signed_bias(run) == pytest.approx(1.0)
    # Second half (steps >= 150): variances 4 and 9 over mean squares 4 + 2^2 and 9 + 6^2 -> (0.5 + 0.2) / 2 = 0.35;
    # the raw variances' mean is 6.5
    assert measures.target_relative_variance(run) == pytest.approx(0.35)
    assert measures.target_variance(run) == pytest.approx(6.5)
    # The final return is the mean of the last three evaluations: (0 + 10 + 20) / 3
    assert measures.final_return(run) == pytest.approx(10.0)
    by_id = {result.claim.id: result for result in decided}
    mc = by_id["mc_error_corr-sera_nolr"]
    # SERA 0.3 against 0.7: -0.4 with Welch's interval (variances 2/300 a side, df 6); the sides do not overlap, so
    # only the observed split and its mirror are as far: permutation p = 2 / C(8, 4) = 2 / 70, above Welch's
    half = stats.t.ppf(0.975, 6) * np.sqrt(2 * (0.02 / 3) / 4)
    assert mc.difference == pytest.approx(-0.4) and (mc.low, mc.high) == pytest.approx((-0.4 - half, -0.4 + half))
    assert mc.permutation_p == pytest.approx(2 / 70) and mc.welch_p < mc.permutation_p == mc.p_value
    # The exploratory claims' q-values: Benjamini-Hochberg over all of them, the verdicts read from them
    exploratory = [result for result in decided if not result.claim.primary]
    q_values = benjamini_hochberg([1.0 if r.p_value is None else r.p_value for r in exploratory])
    for result, q in zip(exploratory, q_values, strict=True):
        assert result.adjusted_p == (None if result.p_value is None else pytest.approx(q))
        if result.p_value is not None and q >= 0.05:
            assert result.verdict == "inconclusive", result.claim.id
    # Two claims alone: q = 2/70 each, below 0.05: SERA's MC-error correlation lower (supported); its AUC, claimed
    # higher, lower (SERA (0, 10, 20) -> 10, NoLR (0, 10, 30) -> 12.5 in every run: contradicted)
    pair = [by_id["mc_error_corr-sera_nolr"].claim, by_id["auc-sera_nolr"].claim]
    mc, auc = _decided(tmp_path, pair)[2]
    assert mc.adjusted_p == pytest.approx(2 / 70) and mc.verdict == "supported"
    assert (auc.difference, auc.low, auc.high) == (-2.5, -2.5, -2.5) and auc.verdict == "contradicted"
    lines = claims_text.claims_section([mc, auc])
    assert lines[0].startswith("Exploratory claims") and any("| contradicted |" in line for line in lines)
    # Three runs a side: the smallest permutation p is 2/20, never below 0.05: no test
    for folder in tmp_path.glob("*/HalfCheetah-v5_4"):
        shutil.rmtree(folder)
    decided = _decided(tmp_path)[2]
    assert all(r.p_value is None for r in decided)
    assert {r.verdict for r in decided if r.difference is not None} == {"too few runs to decide (smallest possible p 0.1)"}
    # One run a side: no interval either
    for folder in [*tmp_path.glob("*/HalfCheetah-v5_3"), *tmp_path.glob("*/HalfCheetah-v5_2")]:
        shutil.rmtree(folder)
    decided = _decided(tmp_path)[2]
    assert all(r.verdict == "too few runs to decide (fewer than 2 an arm)" and r.low is None for r in decided)


def test_beside_each_verdict_the_first_declared_rules_and_benjamini_yekutieli(tmp_path):
    # Every SERA run above every SAC run, one of them far above: the raw difference's permutation p is 2/252, Welch's
    # (which decides with the studentized one) 0.28
    for seed, (arm, baseline) in enumerate(zip([10, 11, 12, 13, 200], [0, 1, 2, 3, 4], strict=True)):
        _claim_run(tmp_path, "serasac", seed, 0.5, [float(arm)] * 3)
        _claim_run(tmp_path, "sac", seed, 0.5, [float(baseline)] * 3)
    declared = [
        claims.Claim("return", "HalfCheetah-v5", 300, "final_return", "serasac", "sac", "higher"),
        claims.Claim("bias", "HalfCheetah-v5", 300, "abs_bias", "serasac", "sac", "lower"),
    ]
    result, bias = _decided(tmp_path, declared)[2]
    assert result.verdict == "inconclusive" and result.declared_p == pytest.approx(2 / 252)
    assert result.declared_verdict == "supported"
    # Equal biases: the same verdict under both rules; BY's q is BH's times 1 + 1/2
    assert bias.declared_verdict == bias.verdict == "inconclusive"
    assert result.by_q == pytest.approx(min(1.0, result.adjusted_p * 1.5))
    text = "\n".join(claims_text.claims_section([result, bias]))
    assert "1 of the 2 tested claims read the same, and these differently:" in text
    assert "- return: supported under the first rule (raw permutation p 0.0079, unadjusted), inconclusive under" in text
    # A verdict that stands on BH alone says so
    result.verdict, result.by_q = "supported", 0.08
    assert claims_text.rests_on_bh_alone(result) and "(BH alone: BY q 0.0800)" in claims_text.claims_table([result], False)[2]


def test_declared_claims_are_one_holm_family_and_need_matched_settings(tmp_path):
    for seed in range(4):
        _claim_run(tmp_path, "serasac", seed, 0.2 + seed / 10, [0.0, 10.0, 20.0 + seed])
        _claim_run(tmp_path, "sera_nolr", seed, 0.6 + seed / 10, [0.0, 10.0, 30.0 + seed])
    declared = [
        claims.Claim("corr", "HalfCheetah-v5", 300, "mc_error_corr", "serasac", "sera_nolr", "lower", primary=True),
        claims.Claim("auc", "HalfCheetah-v5", 300, "auc", "serasac", "sera_nolr", "higher", primary=True),
        claims.Claim("later", "Ant-v5", 300, "auc", "serasac", "sac", "higher", primary=True),
    ]
    _, _, decided = _decided(tmp_path, declared)
    corr, _, later = decided
    # A family of three: Holm's first threshold is 0.05 / 3, and 4 against 4 runs give p of 2/70 at best: no test
    assert corr.p_value is None and corr.verdict == "too few runs to decide (smallest possible p 0.0286)"
    assert later.verdict == "waiting for runs" and "no runs of serasac or sac" in later.note
    # A family of one: decided at 0.05 (Holm's adjustment by hand: study/tests/test_stats.py)
    corr = _decided(tmp_path, declared[:1])[2][0]
    assert corr.p_value == corr.adjusted_p == pytest.approx(2 / 70) and corr.verdict == "supported"
    lines = claims_text.claims_section(decided)
    assert lines[0].startswith("Primary claims, family 'paper'") and "('paper': 3 claims;" in lines[-1]
    # A baseline trained with another learning_starts is no comparison: the claim says which setting differs
    for folder in (tmp_path / "sera_nolr").iterdir():
        config = folder / "HalfCheetah-v5" / "config.yml"
        config.write_text(yaml.safe_dump({"n_timesteps": 300, "learning_starts": 50}))
    corr = _decided(tmp_path, declared[:1])[2][0]
    assert corr.verdict == "waiting for runs" and corr.p_value is None
    assert corr.note == "unmatched: learning_starts: serasac=100, sera_nolr=50"
    # Unless the claim compares the arms each at its own settings (it names what may differ)
    systems = claims.Claim(
        "systems", "HalfCheetah-v5", 300, "mc_error_corr", "serasac", "sera_nolr", "lower", studies=("learning_starts",)
    )
    assert _decided(tmp_path, [systems])[2][0].verdict == "supported"


def test_seeds_families_and_planned_runs(tmp_path):
    # Seeds 0-3 on one side of the difference, seeds 4-7 on the other
    for seed in range(8):
        sign = 1.0 if seed < 4 else -1.0
        _claim_run(tmp_path, "serasac", seed, 0.5, [0.0, 0.0, 30.0 * sign + seed])
        _claim_run(tmp_path, "sera_nolr", seed, 0.5, [0.0, 0.0, -30.0 * sign + seed])
    declared = [
        claims.Claim(
            "early", "HalfCheetah-v5", 300, "final_return", "serasac", "sera_nolr", "higher", primary=True, seeds=(0, 3)
        ),
        claims.Claim("late", "HalfCheetah-v5", 300, "final_return", "serasac", "sera_nolr", "higher", seeds=(4, 7)),
        claims.Claim("all", "HalfCheetah-v5", 300, "auc", "serasac", "sera_nolr", "higher", primary=True, family="b"),
        claims.Claim("planned", "HalfCheetah-v5", 300, "final_return", "serasac", "sera_nolr", "higher", planned=5),
    ]
    early, late, every, planned = _decided(tmp_path, declared)[2]
    # Final returns (mean of the three evaluations): seeds 0-3 at +10 + seed/3 against -10 + seed/3
    assert len(early.arm_values) == len(late.arm_values) == 4 and len(every.arm_values) == 8
    assert early.difference == pytest.approx(20.0) and late.difference == pytest.approx(-20.0)
    # Two families of one claim: Holm leaves each p as it is
    assert early.adjusted_p == pytest.approx(early.p_value) == pytest.approx(2 / 70)
    assert every.adjusted_p == every.p_value and every.claim.family == "b"
    assert early.verdict == "supported"
    # The exploratory pair's q-values: 2 * 2/70 for the later seeds (above 0.05), capped by the other claim's p
    assert late.p_value == pytest.approx(2 / 70) and late.adjusted_p == pytest.approx(min(4 / 70, planned.p_value))
    assert late.verdict == "inconclusive"
    # As many runs as planned or more: decided as any other claim
    assert planned.p_value is not None and planned.verdict == "inconclusive"
    # An exploratory family of its own: adjusted alone, and the default family without it
    alone = claims.Claim("alone", "HalfCheetah-v5", 300, "final_return", "serasac", "sera_nolr", "higher", family="x")
    late, alone = _decided(tmp_path, [declared[1], alone])[2]
    assert late.claim.family == "exploratory" and alone.claim.family == "x"
    assert late.adjusted_p == pytest.approx(late.p_value) and alone.adjusted_p == pytest.approx(alone.p_value)
    assert "Exploratory claims, family 'x' (Benjamini-Hochberg q-values within the family" in "\n".join(
        claims_text.claims_section([late, alone])
    )
    lines = claims_text.claims_section([early, every])
    assert lines[0] == "Primary claims, family 'paper' (Holm-adjusted within the family):"
    assert "Primary claims, family 'b' (Holm-adjusted within the family):" in lines
    assert "('paper': 1, 'b': 1 claims;" in lines[-1]
    # Fewer runs than planned: interim, nothing shown but the numbers of runs
    short = claims.Claim(
        "short", "HalfCheetah-v5", 300, "final_return", "serasac", "sera_nolr", "higher", seeds=(0, 7), planned=9
    )
    related = [
        claims.Claim("pooled", "HalfCheetah-v5", 300, "auc", "serasac", "sera_nolr", "higher", seeds=(7, 20)),
        claims.Claim("other-seeds", "HalfCheetah-v5", 300, "auc", "serasac", "sera_nolr", "higher", seeds=(20, 29)),
        claims.Claim("other-task", "Ant-v5", 300, "auc", "serasac", "sera_nolr", "higher"),
    ]
    result, pooled, other_seeds, other_task = _decided(tmp_path, [short, *related])[2]
    assert result.verdict == "interim (8 and 8 of 9 runs)" and result.withheld
    assert result.p_value is None and result.difference is None and result.low is None
    # A claim that reads one of its runs (seed 7) tells nothing either, and counts as untested in the adjustment
    assert pooled.verdict == "withheld while short is interim" and pooled.withheld
    assert len(pooled.arm_values) == 1 and pooled.difference is pooled.p_value is pooled.adjusted_p is None
    assert not other_seeds.withheld and not other_task.withheld
    table = claims_text.claims_table([result, pooled], False)
    rows = [line for line in table if line.startswith("| short") or "pooled" in line]
    assert [row.split(" | ")[5:9] for row in rows] == [["8 vs 8", "", "", ""], ["1 vs 1", "", "", ""]]


def test_the_ledger_declares_its_claims():
    declared = claims.load_claims(Path(__file__).parents[2] / "results" / "claims.yml")
    primary = [claim for claim in declared if claim.primary]
    assert [claim.family for claim in primary].count("paper") == 6
    paper = [claim for claim in primary if claim.family != "fast"]
    assert {claim.task for claim in paper} == {"sb3_sera/HalfCheetah-6x1-v0", "sb3_sera/SimpleSpread-v0"}
    # Issue 90's decision: the screen's choice against CrossQ and against the mean of the same critics, 5 runs planned
    fast = [(c.id, c.task, c.arm, c.baseline, c.planned) for c in primary if c.family == "fast"]
    assert fast == [
        ("fast-return-crossq", "HalfCheetah-v5", "serasac_fast", "crossq", 5),
        ("fast-return-mean", "HalfCheetah-v5", "serasac_fast", "serasac_fast_mean", 5),
    ]
    assert all(measures.MEASURES[claim.measure].paper_units for claim in primary)
    # The confirmatory test of SERA's weighting: a family of its own, on the new seeds alone, 20 runs an arm planned
    confirmatory = [claim for claim in primary if claim.family == "aggregation"]
    assert [(c.arm, c.baseline, c.measure, c.seeds, c.planned) for c in confirmatory] == [
        ("serasac", "ensemble_mean", "final_return", (10, 29), 20)
    ]
    # The claims declared for seeds 0-9 read none of the confirmatory runs; the pooled contrast is exploratory
    later = {"ma-return-ensemble-mean-confirmatory", "ma-return-ensemble-mean-pooled"}
    later |= {"ma-return-iet", "ma-return-mappo"}
    multiagent = [c for c in declared if c.task == "sb3_sera/HalfCheetah-6x1-v0" and c.n_timesteps == 50_000]
    assert {claim.seeds for claim in multiagent if claim.id not in later} == {(0, 9)}
    pooled = next(claim for claim in declared if claim.id == "ma-return-ensemble-mean-pooled")
    assert pooled.seeds == (0, 29) and not pooled.primary
    # Simple Spread's: a family of its own, 20 runs an arm planned, the claims beside it reading its runs
    spread = [claim for claim in declared if claim.task == "sb3_sera/SimpleSpread-v0"]
    assert [(c.id, c.primary, c.family, c.planned) for c in spread if c.primary] == [
        ("spread-return-ensemble-mean-confirmatory", True, "spread", 20)
    ]
    assert all(claim.shares_runs(spread[0]) for claim in spread)
    # The paper's systems, each at its own settings: only ACE's replay settings differ from SERASAC's
    systems = {claim.baseline: claim.studies for claim in declared if claim.id.endswith(("sunrise", "ace", "iet", "mappo"))}
    assert systems == {"sunrise": (), "ace": ("batch_size", "tau"), "iet": (), "mappo": ()}
    # The paper's budget: a primary family of two, five runs an arm planned, its exploratory claims in a family of
    # their own beside the SB3 alternatives', every claim declared before them left in the one family they had
    budget = [claim for claim in declared if claim.n_timesteps == 300_000]
    assert [(c.baseline, c.primary, c.planned) for c in budget if c.family == "paper-budget" and c.primary] == [
        ("masac", True, 5),
        ("ensemble_mean", True, 5),
    ]
    assert len([c for c in budget if not c.primary and c.family == "paper-budget"]) == 6
    alternatives = {(c.measure, c.baseline): c.studies for c in declared if c.family == "sb3-alternatives"}
    assert alternatives == {
        ("final_return", "tqc"): (),
        ("auc", "tqc"): (),
        ("final_return", "crossq"): ("learning_starts",),
        ("auc", "crossq"): ("learning_starts",),
    }
    assert {c.family for c in declared if not c.primary} == {"exploratory", "paper-budget", "sb3-alternatives", "fast"}
    assert sum(c.family == "exploratory" for c in declared) == 50


@pytest.mark.parametrize(
    ("entry", "message"),
    [
        (
            {"id": "a", "task": "T", "n_timesteps": 1, "measure": "speed", "arm": "x", "baseline": "y", "direction": "lower"},
            "unknown measure 'speed'; measures: ",
        ),
        (
            {"id": "a", "task": "T", "n_timesteps": 1, "measure": "auc", "arm": "x", "baseline": "y", "direction": "up"},
            "direction 'up' is not one of",
        ),
        (
            {"id": "a", "task": "T", "measure": "auc", "arm": "x", "baseline": "y", "direction": "higher", "primry": True},
            r"unknown field\(s\) \['primry'\], missing \['n_timesteps'\]",
        ),
        (
            {
                "id": "a",
                "task": "T",
                "n_timesteps": 1,
                "measure": "auc",
                "arm": "x",
                "baseline": "y",
                "direction": "higher",
                "seeds": [3, 1],
            },
            r"seeds \[3, 1\] is not \[first, last\]",
        ),
        (
            {
                "id": "a",
                "task": "T",
                "n_timesteps": 1,
                "measure": "auc",
                "arm": "x",
                "baseline": "y",
                "direction": "higher",
                "planned": -1,
            },
            "planned -1 is not a number of runs",
        ),
        (
            {
                "id": "a",
                "task": "T",
                "n_timesteps": 1,
                "measure": "auc",
                "arm": "x",
                "baseline": "y",
                "direction": "higher",
                "family": 3,
            },
            "family 3 is not a name",
        ),
        (
            {
                "id": "a",
                "task": "T",
                "n_timesteps": 1,
                "measure": "auc",
                "arm": "x",
                "baseline": "y",
                "direction": "higher",
                "studies": ["net_arch"],
            },
            r"studies \['net_arch'\] is not a list of shared settings; allowed: \['learning_starts'",
        ),
    ],
)
def test_claims_files_are_checked(tmp_path, entry, message):
    path = tmp_path / "claims.yml"
    path.write_text(yaml.safe_dump({"claims": [entry]}))
    with pytest.raises(ValueError, match=message):
        claims.load_claims(path)
    valid = {"id": "a", "task": "T", "n_timesteps": 1, "measure": "auc", "arm": "x", "baseline": "y", "direction": "higher"}
    path.write_text(yaml.safe_dump({"claims": [valid, valid]}))
    with pytest.raises(ValueError, match="claim 'a': the id is declared twice"):
        claims.load_claims(path)


def test_claims_after_planned_after_must_plan_their_runs(tmp_path):
    # CrossQ's claims, planned nowhere, were decided as each run arrived; from the claim the file names on, each plans
    entry = {"task": "T", "n_timesteps": 1, "measure": "auc", "arm": "x", "baseline": "y", "direction": "higher"}
    old, planned, unplanned = {"id": "old", **entry}, {"id": "new", "planned": 5, **entry}, {"id": "late", **entry}
    path = tmp_path / "claims.yml"
    path.write_text(yaml.safe_dump({"planned_after": "old", "claims": [old, planned]}))
    assert [claim.planned for claim in claims.load_claims(path)] == [0, 5]
    path.write_text(yaml.safe_dump({"planned_after": "old", "claims": [old, planned, unplanned]}))
    with pytest.raises(ValueError, match="claim 'late' plans no runs: every claim declared after 'old' says how many"):
        claims.load_claims(path)
    path.write_text(yaml.safe_dump({"planned_after": "gone", "claims": [old]}))
    with pytest.raises(ValueError, match="planned_after 'gone' is not the id of one of its claims"):
        claims.load_claims(path)
    # The ledger's own file names the rule's place
    assert yaml.safe_load((ROOT / "results" / "claims.yml").read_text())["planned_after"] == "fast6x1-return-paper"


def test_disagreement_measures_by_hand(tmp_path):
    folder = tmp_path / "run"
    folder.mkdir()
    run = type("Run", (), {"folder": str(folder)})()
    # Three critics: unit own variance and 0.5 shared with every other critic
    cov = np.eye(3) + 0.5
    np.savez(folder / DIAGNOSTICS_FILE, timesteps=np.array([1]), critic_cov_matrix=cov[None])
    # Own part about the ensemble mean: (1 - 1/3) = 2/3; ensemble mean's variance: (3 * 1.5 + 6 * 0.5) / 9 = 5/6
    assert measures.relative_disagreement(run) == pytest.approx((2 / 3) / (5 / 6))
    assert measures.closest_pair(run) == pytest.approx(1.0)
    # Critics 0 and 1 near duplicates: Var(Q0 - Q1) = 1 + 1 - 2 * 0.99 = 0.02 against 1.0 for the other two pairs
    cov = np.array([[1.0, 0.99, 0.5], [0.99, 1.0, 0.5], [0.5, 0.5, 1.0]])
    np.savez(folder / DIAGNOSTICS_FILE, timesteps=np.array([1]), critic_cov_matrix=cov[None])
    assert measures.closest_pair(run) == pytest.approx(0.02 / ((0.02 + 1.0 + 1.0) / 3))


def test_no_verdict_of_the_ledger_points_where_its_interval_does_not():
    ledger = Path(__file__).parents[2] / "results"
    runs, _ = load_runs([ledger])
    decided = {r.claim.id: r for r in claims.evaluate(claims.load_claims(ledger / "claims.yml"), group_runs(runs))}
    # The two cases of issue 41: AUC against SERA-NoLR, interval [20, 455] and (raw) permutation p 0.063; SERA's final
    # return against matched SAC, interval [-18, 908] and (raw) permutation p 0.032
    nolr, sac = decided["ma-auc-nolr"], decided["sa-return-sac"]
    assert (nolr.low, nolr.high) == (pytest.approx(20.2, abs=0.1), pytest.approx(455, abs=1))
    assert nolr.permutation_p == pytest.approx(0.043, abs=0.001) and nolr.welch_p < 0.05
    assert sac.low < 0 < sac.high and sac.welch_p > 0.05 and sac.p_value > 0.05 and sac.verdict == "inconclusive"
    for result in decided.values():
        if result.welch_p is None:
            continue
        excludes_zero = result.low > 0 or result.high < 0
        assert (result.welch_p < 0.05) == excludes_zero, result.claim.id
        if result.verdict in ("supported", "contradicted"):
            assert excludes_zero and result.p_value >= result.welch_p, result.claim.id


def test_what_was_seen_before_a_claim_comes_from_git(tmp_path):
    ledger = tmp_path / "results"
    git = ["git", "-C", str(tmp_path), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git, "init", "-q"], check=True)
    for seed in range(2):
        _claim_run(ledger, "serasac", seed, 0.2, [0.0, 10.0, 20.0 + seed])
        _claim_run(ledger, "sera_nolr", seed, 0.6, [0.0, 10.0, 30.0 + seed])
    entry = (
        "{id: later, task: HalfCheetah-v5, n_timesteps: 300, measure: auc, arm: serasac, baseline: sera_nolr, "
        "direction: higher}"
    )
    (ledger / "claims.yml").write_text(f"claims:\n  - {entry}\n")
    subprocess.run([*git, "add", "."], check=True)
    subprocess.run([*git, "commit", "-qm", "two runs a side, then the claim"], check=True)
    for seed in range(2, 6):
        _claim_run(ledger, "serasac", seed, 0.2, [0.0, 10.0, 20.0 + seed])
        _claim_run(ledger, "sera_nolr", seed, 0.6, [0.0, 10.0, 30.0 + seed])
    declared = declaration(ledger, "later")
    assert declared is not None and len(declared.runs) == 4 and "serasac/HalfCheetah-v5_1" in declared.runs
    runs, _ = load_runs([ledger])
    unsaved = claims.Claim("unsaved", "HalfCheetah-v5", 300, "auc", "serasac", "sera_nolr", "higher")
    results = claims.evaluate([*claims.load_claims(ledger / "claims.yml"), unsaved], group_runs(runs))
    _, _, row, missing = seen_before_lines(results, runs, ledger)
    # Two of each arm's six runs were in the ledger when the claim was committed; on the four added after, SERA's
    # AUC is 2.5 below NoLR's, the sides apart (the permutation test's best p at 4 against 4: 2/70)
    assert row.startswith(f"| later | {declared.commit} (")
    assert row.endswith("| 2 of 6 | 2 of 6 | 4 against 4: -2.5 [-3.06, -1.94], p 0.0286 |")
    assert missing == "| unsaved | not committed, or no git history | | | |"
    # A baseline whose runs were all in before the claim: nothing to decide on the runs added after, SERA's counted
    before_only = [run for run in runs if run.variant == "serasac" or run.seed < 2]
    _, _, row, _ = seen_before_lines(results, before_only, ledger)
    assert row.endswith("| 2 of 6 | 2 of 6 | 4 and 0 runs: waiting for runs (no runs of sera_nolr) |")
    assert declaration(tmp_path.parent, "later") is None  # no repository there


def test_a_claim_reads_the_runs_of_its_task_budget_arms_and_seeds():
    claim = claims.Claim("c", "HalfCheetah-v5", 300, "auc", "serasac", "sac", "higher", seeds=(0, 4))
    run = SimpleNamespace(env_id="HalfCheetah-v5", n_timesteps=300, variant="sac", seed=4)
    assert claim.reads(run)
    for change in ({"env_id": "Ant-v5"}, {"n_timesteps": 600}, {"variant": "ace"}, {"seed": 5}):
        assert not claim.reads(SimpleNamespace(**{**vars(run), **change})), change


def test_a_claim_on_seen_runs_is_also_given_without_them_once_decided(tmp_path):
    # The arm's seeds 0 and 1 end at 10 and 11 (seen under another name before the claim), seeds 2-4 at 2, 3 and 4;
    # the baseline's five at 0, 1, 2, 3 and 4
    for seed, final in enumerate([10.0, 11.0, 2.0, 3.0, 4.0]):
        _claim_run(tmp_path, "fast", seed, 0.5, [final] * 3)
    for seed in range(5):
        _claim_run(tmp_path, "base", seed, 0.5, [float(seed)] * 3)
    runs, _ = load_runs([tmp_path])
    claim = claims.Claim("fast-return", "HalfCheetah-v5", 300, "final_return", "fast", "base", "higher", planned=5)
    seen = [claims.Seen("fast", "HalfCheetah-v5", (0, 1), "screen")]
    decided = claims.evaluate([claim], group_runs(runs))
    # On every run the difference is 6 - 2 = 4; without the seen two, 3 - 2 = 1, three runs against five
    assert decided[0].difference == pytest.approx(4.0)
    (line,) = unseen_lines(decided, runs, seen)
    assert line.startswith("- fast-return without fast's seeds 0 and 1 (seen as screen's): 3 against 5: 1 [")
    # Another task's runs of the arm are not the seen ones; an interim claim shows nothing
    assert unseen_lines(decided, runs, [claims.Seen("fast", "Hopper-v5", (0, 1), "screen")]) == []
    interim = claims.evaluate([claim], group_runs([run for run in runs if (run.variant, run.seed) != ("fast", 4)]))
    assert interim[0].verdict.startswith("interim") and unseen_lines(interim, runs, seen) == []


@pytest.mark.parametrize(
    "entry, message",
    [
        ({"arm": "fast", "task": "HalfCheetah-v5", "seeds": [0]}, "exactly \\['arm', 'task', 'seeds', 'as'\\]"),
        ({"arm": "fast", "task": "HalfCheetah-v5", "seeds": "0-1", "as": "screen"}, "not a list of integers"),
    ],
)
def test_bad_seen_entries_are_refused_naming_the_fields(tmp_path, entry, message):
    path = tmp_path / "claims.yml"
    path.write_text(yaml.safe_dump({"claims": [], "seen": [entry]}))
    with pytest.raises(ValueError, match=message):
        claims.load_seen(path)
