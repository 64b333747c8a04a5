"""The paper's mechanism claims on run records: per-run measures and verdicts by hand."""

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from sb3_sera.experiments import claims
from sb3_sera.experiments.evaluation import BIAS_FILE, DIAGNOSTICS_FILE
from sb3_sera.experiments.report import load_runs


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


def test_claims_by_hand(tmp_path):
    for seed, corr in enumerate([0.2, 0.3, 0.4]):
        _claim_run(tmp_path, "serasac", seed, corr, [0.0, 10.0, 20.0])
    for seed, corr in enumerate([0.6, 0.7, 0.8]):
        _claim_run(tmp_path, "sera_nolr", seed, corr, [0.0, 10.0, 30.0])
    runs, _ = load_runs([tmp_path])
    by_variant = {v: [r for r in runs if r.variant == v] for v in ("serasac", "sera_nolr")}
    run = by_variant["serasac"][0]
    assert claims.relative_bias(run) == pytest.approx(0.2)
    # Second half (steps >= 150): variances 4 and 9 over mean squares 4 + 2^2 and 9 + 6^2 -> (0.5 + 0.2) / 2 = 0.35
    assert claims.target_relative_variance(run) == pytest.approx(0.35)
    lines = claims.claims_table(by_variant, reps=500)
    mc_row = next(line for line in lines if "mc_error_corr" in line)
    # SERA 0.3 against 0.7: -0.4; every resample of SERA lies in [0.2, 0.4] and of NoLR in [0.6, 0.8]
    assert "| -0.4 [" in mc_row and mc_row.endswith("| supported |")
    low, high = (float(x) for x in mc_row.split("| -0.4 [")[1].split("]")[0].split(", "))
    assert -0.6 <= low <= -0.4 <= high <= -0.2
    # AUC: SERA (0, 10, 20) -> 10, NoLR (0, 10, 30) -> 12.5: SERA lower, claimed higher
    auc_row = next(line for line in lines if "normalized AUC" in line)
    assert "| -2.5 [-2.5, -2.5] | not supported |" in auc_row
    # Fewer than MIN_RUNS a side: no interval, no verdict
    few = claims.claims_table({k: v[:2] for k, v in by_variant.items()}, reps=500)
    assert all("too few runs" in line for line in few if line.startswith("| Fig."))


def test_verdicts():
    assert claims.verdict(-0.3, -0.1, lower=True) == "supported"
    assert claims.verdict(0.1, 0.3, lower=True) == "not supported"
    assert claims.verdict(-0.1, 0.3, lower=True) == "inconclusive at this n"
    assert claims.verdict(0.1, 0.3, lower=False) == "supported"
    point, low, high = claims.mean_difference_interval(np.array([1.0, 1.0]), np.array([0.0, 0.0]), reps=100)
    assert (point, low, high) == (1.0, 1.0, 1.0)


def test_disagreement_measures_by_hand(tmp_path):
    folder = tmp_path / "run"
    folder.mkdir()
    run = type("Run", (), {"folder": str(folder)})()
    # Three critics: unit own variance and 0.5 shared with every other critic
    cov = np.eye(3) + 0.5
    np.savez(folder / DIAGNOSTICS_FILE, timesteps=np.array([1]), critic_cov_matrix=cov[None])
    # Own part about the ensemble mean: (1 - 1/3) = 2/3; ensemble mean's variance: (3 * 1.5 + 6 * 0.5) / 9 = 5/6
    assert claims.relative_disagreement(run) == pytest.approx((2 / 3) / (5 / 6))
    assert claims.closest_pair(run) == pytest.approx(1.0)
    # Critics 0 and 1 near duplicates: Var(Q0 - Q1) = 1 + 1 - 2 * 0.99 = 0.02 against 1.0 for the other two pairs
    cov = np.array([[1.0, 0.99, 0.5], [0.99, 1.0, 0.5], [0.5, 0.5, 1.0]])
    np.savez(folder / DIAGNOSTICS_FILE, timesteps=np.array([1]), critic_cov_matrix=cov[None])
    assert claims.closest_pair(run) == pytest.approx(0.02 / ((0.02 + 1.0 + 1.0) / 3))
