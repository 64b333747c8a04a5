"""The comparison job end to end at a tiny budget: run folders, table, plot, resume."""

import json
import subprocess
import sys

import numpy as np
import pytest

from sb3_sera.experiments import compare
from sb3_sera.experiments.cli import main


def test_compare_cli_end_to_end(tmp_path, capsys):
    out = tmp_path / "runs"
    argv = ["compare", "--algos", "serasac", "sac", "--seeds", "0", "-n", "240", "--eval-freq", "120"]
    argv += ["--eval-episodes", "1", "--n-jobs", "2", "--out", str(out)]
    main(argv)
    printed = capsys.readouterr().out
    assert "| serasac | 1 |" in printed and "| sac | 1 |" in printed
    assert (out / "Pendulum-v1_learning_curves.png").stat().st_size > 0
    assert "final return" in (out / "Pendulum-v1_summary.md").read_text()
    for algo in ("serasac", "sac"):
        folder = out / algo / "Pendulum-v1_0"
        evaluations = np.load(folder / "evaluations.npz")
        assert evaluations["timesteps"].tolist() == [120, 240]
        assert (folder / "Pendulum-v1.zip").exists()
        assert (folder / "0.monitor.csv").exists()
        result = json.loads((folder / "result.json").read_text())
        assert result["final_return"] == pytest.approx(evaluations["results"][-1].mean())

    # A finished run is not run again
    stamp = (out / "serasac" / "Pendulum-v1_0" / "result.json").stat().st_mtime_ns
    main(argv)
    assert (out / "serasac" / "Pendulum-v1_0" / "result.json").stat().st_mtime_ns == stamp


def test_unknown_algorithm_is_refused_before_any_run(tmp_path):
    with pytest.raises(ValueError, match=r"Unknown algorithm\(s\) \['sera'\]: expected names among .*'serasac'"):
        compare.run_comparison(algos=["sera"], out_dir=str(tmp_path))
    assert not any(tmp_path.iterdir())


def test_module_entry_point_help():
    completed = subprocess.run([sys.executable, "-m", "sb3_sera", "compare", "--help"], capture_output=True, text=True)
    assert completed.returncode == 0
    assert "--n-timesteps" in completed.stdout


def test_policy_follows_the_task():
    from stable_baselines3.common.env_util import make_vec_env

    assert compare.policy_for(make_vec_env("Pendulum-v1")) == "MlpPolicy"
    assert compare.policy_for(make_vec_env("sb3_sera/SimpleSpread-v0")) == "CTDEPolicy"


def test_run_folders_follow_rl_zoo3_naming():
    from pathlib import Path

    assert compare.run_dir("out", "masac", "sb3_sera/HalfCheetah-6x1-v0", 2) == Path("out/masac/sb3_sera-HalfCheetah-6x1-v0_2")
