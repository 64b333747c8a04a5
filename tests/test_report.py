"""`sb3-sera report` on fixed run folders (values by hand and by scipy) and on TensorBoard logs of a real run."""

import shutil

import numpy as np
import pytest
from scipy import stats

from sb3_sera import SERASAC
from sb3_sera.experiments.cli import main
from sb3_sera.experiments.report import load_runs, load_scalars, split_by_task, write_report

TASK = "sb3_sera/HalfCheetah-6x1-v0"


def fake_run(root, algo: str, run_id: int, returns: list[float], last_bias: float | None = None) -> None:
    folder = root / algo / f"sb3_sera-HalfCheetah-6x1-v0_{run_id}"
    folder.mkdir(parents=True)
    timesteps = np.array([1000, 2000, 3000])
    # Two evaluation episodes per point, averaging to `returns`
    results = np.stack([np.array(returns) - 1.0, np.array(returns) + 1.0], axis=1)
    np.savez(folder / "evaluations.npz", timesteps=timesteps, results=results, ep_lengths=np.ones_like(results))
    if last_bias is not None:
        # Episodes' V(s0) and discounted returns: the last evaluation's means differ by `last_bias`
        values = np.array([[10.0, 12.0], [20.0, 22.0], [30.0, 30.0]])
        discounted = values - np.array([[1.0, 1.0], [0.0, 0.0], [last_bias - 1.0, last_bias + 1.0]])
        np.savez(folder / "initial_state_bias.npz", timesteps=timesteps, values=values, discounted_returns=discounted)


def test_report_tables_by_hand(tmp_path):
    runs_root = tmp_path / "runs"
    fake_run(runs_root, "serasac", 1, [0.0, 3000.0, 5000.0], last_bias=4.0)
    fake_run(runs_root, "serasac", 2, [0.0, 3000.0, 6000.0], last_bias=2.0)
    fake_run(runs_root, "masac", 1, [0.0, 1000.0, 4000.0])
    fake_run(runs_root, "masac", 2, [0.0, 2000.0, 4400.0])
    runs = load_runs([runs_root])
    assert {run.env_id for run in runs} == {TASK}  # the folder name maps back to the registered id
    assert [run.initial_state_bias for run in runs if run.algo == "serasac"] == [[1.0, 0.0, 4.0], [1.0, 0.0, 2.0]]
    report = write_report([runs_root], tmp_path / "report").read_text()
    lines = report.splitlines()
    serasac = next(line for line in lines if line.startswith("| serasac |"))
    masac = next(line for line in lines if line.startswith("| masac |"))
    # serasac: finals 5000, 6000; paper 5520 ± 711; AUC (0, 3000, 5000) = 2750, (0, 3000, 6000) = 3000
    # last initial-state bias 4 and 2 -> 3; masac has no bias records
    assert serasac == "| serasac | 2 | 5500.0 ± 500.0 | 5520 ± 711 | 2875.0 |  |  | 3.0 |"
    p_value = stats.ttest_ind([5000.0, 6000.0], [4000.0, 4400.0], equal_var=False).pvalue
    # masac: finals 4000, 4400 -> 4200 ± 200; AUC (0, 1000, 4000) = 1500, (0, 2000, 4400) = 2100; +30.95 %
    assert masac == f"| masac | 2 | 4200.0 ± 200.0 | 4500 ± 802 | 1800.0 | {p_value:.3f} | +31.0 |  |"
    assert "Paper only: Ensemble Mean 4831 ± 721, IET 4608 ± 783, MATD3 3815 ± 912, MAPPO 3623 ± 812" in report
    assert (tmp_path / "report" / "sb3_sera-HalfCheetah-6x1-v0_curves.png").stat().st_size > 0
    assert "![sb3_sera/HalfCheetah-6x1-v0 initial-state bias](sb3_sera-HalfCheetah-6x1-v0_bias.png)" in report
    assert (tmp_path / "report" / "sb3_sera-HalfCheetah-6x1-v0_bias.png").stat().st_size > 0


def test_report_diagnostics_from_tensorboard(tmp_path, capsys):
    SERASAC("MlpPolicy", "Pendulum-v1", learning_starts=50, batch_size=32, tensorboard_log=str(tmp_path / "tb"), seed=0).learn(
        450, log_interval=1
    )
    scalars = load_scalars([tmp_path / "tb"])
    assert set(scalars) == {"SERASAC"}
    steps, values = scalars["SERASAC"]["train/td_target_var"][0]
    assert steps.tolist() == [200, 400] and np.all(values > 0)
    assert len([tag for tag in scalars["SERASAC"] if tag.startswith("train/kappa_")]) == 5
    # The same events as a run of the task's variant "serasac", in rl-zoo3's <tb>/<env_name>/<name>_<n> layout
    shutil.copytree(tmp_path / "tb" / "SERASAC_1", tmp_path / "tb" / "sb3_sera-HalfCheetah-6x1-v0" / "serasac_1")
    assert split_by_task(load_scalars([tmp_path / "tb"])).keys() == {TASK, None}
    fake_run(tmp_path / "runs", "serasac", 1, [0.0, 1.0, 2.0])
    main(["report", str(tmp_path / "runs"), "--tensorboard-log", str(tmp_path / "tb"), "--out", str(tmp_path / "out")])
    report = capsys.readouterr().out
    # the task's runs are drawn in the task's section, the rest in a section of their own
    assert "![sb3_sera/HalfCheetah-6x1-v0 training diagnostics](sb3_sera-HalfCheetah-6x1-v0_diagnostics.png)" in report
    assert (tmp_path / "out" / "sb3_sera-HalfCheetah-6x1-v0_diagnostics.png").stat().st_size > 0
    assert "Training diagnostics" in report
    assert (tmp_path / "out" / "diagnostics.png").stat().st_size > 0


def test_report_needs_runs(tmp_path):
    with pytest.raises(ValueError, match="No run folders"):
        write_report([tmp_path], tmp_path / "out")
