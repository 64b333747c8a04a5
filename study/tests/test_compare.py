"""The comparison job end to end at a tiny budget: records, hyperparameters from the YAML files, reports, resume."""

import json
import re
import subprocess
import sys

import numpy as np
import pytest
import torch as th
import yaml

import sb3_sera
from sera_study import registry
from sera_study.cli import main
from sera_study.records import RunResult
from sera_study.results import summary
from sera_study.runs import backends, compare, engine, specs

TINY = ["--seeds", "0", "-n", "240", "--eval-freq", "120", "--eval-episodes", "1", "--reps", "200"]


def test_compare_cli_end_to_end(tmp_path, capsys):
    out = tmp_path / "runs"
    argv = ["compare", "--algos", "serasac", "sac", *TINY, "--n-jobs", "2", "--out", str(out)]
    argv += ["--num-threads", "1", "--device", "cpu", "-params", "learning_starts:100", "serasac:sera_alpha:0.3"]
    main(argv)
    printed = capsys.readouterr().out
    # Where the report and the runs are, then the comparison in short and what it means, last (the tables: in the file)
    short = printed[printed.index("In short: final return (mean of the last 3 evaluations) on Pendulum-v1 at 240 steps") :]
    assert printed.index("Report: ") < printed.index("In short") and "| serasac | 1 |" not in printed
    assert short.index("serasac - sac: no interval from one run a side") < short.index("What it means:")
    assert "1 run(s) a side cannot tell serasac from sac at p < 0.05" in short
    # A run folder of compare is a zoo run folder: rl-zoo3's enjoy opens it
    main(["enjoy", "--algo", "serasac", "--env", "Pendulum-v1", "-f", str(out), "--exp-id", "1", "-n", "10", "--no-render"])
    # The report's figures are named after its path
    assert f"Figures:\n  {out / 'reports' / 'Pendulum-v1_1' / 'Pendulum-v1_240_auc.png'}" in printed
    report = out / "reports" / "Pendulum-v1_1"
    assert (report / "Pendulum-v1_240_curves.png").stat().st_size > 0
    assert "final return IQM [95% CI]" in (report / "report.md").read_text()
    for algo in ("serasac", "sac"):
        folder = out / algo / "Pendulum-v1_1"  # ids from 1, as rl-zoo3 numbers them
        evaluations = np.load(folder / "evaluations.npz")
        assert evaluations["timesteps"].tolist() == [120, 240]
        assert (folder / "Pendulum-v1.zip").exists() and (folder / "0.monitor.csv").exists()
        args = yaml.safe_load((folder / "Pendulum-v1" / "args.yml").read_text())
        config = yaml.safe_load((folder / "Pendulum-v1" / "config.yml").read_text())
        assert (args["algo"], args["variant"], args["env"], args["seed"], args["n_timesteps"]) == (
            algo,
            algo,
            "Pendulum-v1",
            0,
            240,
        )
        assert args["hyperparams_source"].endswith(f"{algo}.yml:Pendulum-v1")
        assert {"torch", "stable-baselines3", "sb3-sera"} <= set(args["versions"])
        # hyperparams/<algo>.yml's Pendulum entry (learning rate 1e-3, as `sb3-sera train` uses), then -params
        assert config["learning_rate"] == 1e-3 and config["learning_starts"] == 100
        assert ("sera_alpha" in config) == (algo == "serasac")
        # The thread and device flags reached the worker
        result = json.loads((folder / "result.json").read_text())
        assert (result["torch_threads"], result["device"], args["num_threads"], args["device"]) == (1, "cpu", 1, "cpu")
        # TensorBoard runs named by variant and seed
        assert (folder / f"{algo}_seed0_1").is_dir()
    # The same command again: finished runs are read back, and the report goes to a new folder
    stamp = (out / "serasac" / "Pendulum-v1_1" / "result.json").stat().st_mtime_ns
    main(argv)
    assert (out / "serasac" / "Pendulum-v1_1" / "result.json").stat().st_mtime_ns == stamp
    assert (out / "reports" / "Pendulum-v1_2" / "report.md").exists()
    assert (out / "reports" / "Pendulum-v1_1" / "report.md").exists()
    # Other settings make a new run with the next id, never mixed with the first
    main([*argv, "serasac:sera_alpha:0.6", "--algos", "serasac"])
    args = yaml.safe_load((out / "serasac" / "Pendulum-v1_2" / "Pendulum-v1" / "config.yml").read_text())
    assert args["sera_alpha"] == 0.6
    assert not (out / "sac" / "Pendulum-v1_2").exists()


@pytest.mark.parametrize(
    ("params", "message"),
    [
        (["learning_starts:10"], r"ppo on Pendulum-v1: unknown hyperparameter\(s\) \['learning_starts'\] for ppo"),
        (["ppo:learning_starts:10"], r"unknown hyperparameter\(s\) \['learning_starts'\] for ppo"),
        (["serasac:sera_alpha:2.0"], r"serasac on Pendulum-v1: ValueError: sera_alpha=2.0 is out of range"),
        (["td3:tau:0.1"], r"-params name algorithm\(s\) \['td3'\] that are not compared"),
        (["learning_starts"], r"-params item 'learning_starts' is invalid: expected key:value or algo:key:value"),
    ],
)
def test_params_are_checked_for_every_algorithm_before_any_run(tmp_path, capsys, params, message):
    out = tmp_path / "runs"
    with pytest.raises(SystemExit) as exit_info:
        main(["compare", "--algos", "serasac", "ppo", *TINY, "--out", str(out), "-params", *params])
    assert exit_info.value.code == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("sb3-sera compare: error: ") and "\n" not in error

    assert re.search(message, error)
    assert not out.exists()


def test_parse_params():
    common, per_algo = compare.parse_params(
        ["learning_starts:1e2", "serasac:sera_alpha:0.3", "learning_rate:lin_3e-4"], ["serasac"]
    )
    assert common == {"learning_starts": 100.0, "learning_rate": "lin_3e-4"}
    assert per_algo == {"serasac": {"sera_alpha": 0.3}}


def test_unknown_algorithm_is_refused_before_any_run(tmp_path):
    with pytest.raises(ValueError, match=r"Unknown algorithm\(s\) \['sera'\]: expected names among .*'serasac'"):
        compare.run_comparison(algos=["sera"], out_dir=str(tmp_path))
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["-n", "-100"], "n_timesteps=-100 is out of range: the budget of a run must be an integer >= 1"),
        (["--env", "Pendulm-v1"], "unknown task 'Pendulm-v1'; did you mean 'Pendulum-v1'"),
        (["--device", "gpu"], "device='gpu' is not a torch device: expected auto, cpu, cuda or cuda:N"),
    ],
)
def test_a_wrong_budget_or_task_is_named_as_such(tmp_path, capsys, argv, message):
    with pytest.raises(SystemExit) as exit_info:
        main(["compare", "--out", str(tmp_path / "runs"), *argv])
    assert exit_info.value.code == 2 and message in capsys.readouterr().err


def test_a_failed_run_leaves_no_folder_and_is_named(tmp_path, capsys):
    bad = specs.make_spec(
        variant="serasac",
        algo="serasac",
        env_id="Pendulum-v1",
        seed=0,
        n_timesteps=200,
        overrides={"policy_kwargs": "dict(n_critics=1)"},
        eval_freq=100,
        n_eval_episodes=1,
    )
    good = specs.make_spec(
        variant="sac",
        algo="sac",
        env_id="Pendulum-v1",
        seed=0,
        n_timesteps=200,
        overrides={"learning_starts": 100},
        eval_freq=100,
        n_eval_episodes=1,
    )
    with pytest.raises(
        RuntimeError, match=r"1 of 2 run\(s\) failed: serasac on Pendulum-v1 seed 0 \(.*serasac/Pendulum-v1_1\): ValueError: "
    ):
        backends.execute([bad, good], tmp_path, n_jobs=2, progress_bar=False)
    # The worker's traceback, down to the line that raised, is on stderr
    stderr = capsys.readouterr().err
    assert "serasac/Pendulum-v1_1) failed:" in stderr and "Traceback" in stderr and "train_one" in stderr
    assert not (tmp_path / "serasac" / "Pendulum-v1_1").exists()
    assert (tmp_path / "sac" / "Pendulum-v1_1" / "result.json").exists()


#: Runs the command line in a fresh interpreter, then says which heavy modules it imported
WITHOUT_TORCH = """
import sys
from sera_study.cli import main
try:
    main(sys.argv[1:])
finally:
    print("imported:", [name for name in ("torch", "stable_baselines3", "rl_zoo3") if name in sys.modules], file=sys.stderr)
"""


@pytest.mark.parametrize(
    ("argv", "code", "expected"),
    [
        (["compare", "--help"], 0, "environment steps of a run (default: 6000)"),
        (["bench", "--help"], 0, "--gpus-per-run SHARE"),
        (["ledger", "add", "--help"], 0, "--unclaimed"),
        (["bench", "grid.yml", "--n-jobs", "two"], 2, "argument --n-jobs: invalid int value: 'two'"),
        (["compare", "--bogus"], 2, "unrecognized arguments: --bogus"),
    ],
)
def test_help_and_argument_errors_come_before_torch_is_imported(argv, code, expected):
    completed = subprocess.run([sys.executable, "-c", WITHOUT_TORCH, *argv], capture_output=True, text=True)
    assert completed.returncode == code, completed.stderr[-2000:]
    assert expected in completed.stdout + completed.stderr
    assert "imported: []" in completed.stderr


def test_module_entry_point_help():
    completed = subprocess.run([sys.executable, "-m", "sera_study", "compare", "--help"], capture_output=True, text=True)
    assert completed.returncode == 0
    assert "--n-timesteps" in completed.stdout and "--num-threads" in completed.stdout
    # Plain text with every default, no Sphinx markup
    assert "environment steps of a run (default: 6000)" in completed.stdout and "(default: one per core)" in completed.stdout
    assert "``" not in completed.stdout and ":mod:" not in completed.stdout and "(default: None)" not in completed.stdout
    # The description is the module's docstring
    assert "Train several algorithms on one task for several seeds" in completed.stdout


def test_policy_follows_the_task():
    from stable_baselines3.common.env_util import make_vec_env

    assert engine.policy_for(make_vec_env("Pendulum-v1")) == "MlpPolicy"
    assert engine.policy_for(make_vec_env("sb3_sera/SimpleSpread-v0")) == "CTDEPolicy"


def test_hyperparameters_come_from_the_zoo_files():
    # This package's file for its algorithms, rl-zoo3's own for the zoo's
    spec = specs.make_spec(variant="serasac", algo="serasac", env_id="HalfCheetah-v5", seed=0, n_timesteps=20000)
    assert spec.hyperparams["learning_starts"] == 10000 and spec.hyperparams["critic_lr_max"] == 5e-4
    assert spec.hyperparams_source.endswith("hyperparams/serasac.yml:HalfCheetah-v5")
    sac = specs.make_spec(
        variant="sac", algo="sac", env_id="Pendulum-v1", seed=0, n_timesteps=1000, overrides={"batch_size": 64}
    )
    assert sac.hyperparams == {"policy": "MlpPolicy", "learning_rate": 1e-3, "batch_size": 64}
    assert "rl_zoo3" in sac.hyperparams_source


def test_stock_sac_on_a_paper_task_shares_serasacs_settings(tmp_path, capsys):
    # rl-zoo3 has no HalfCheetah-v5 entry for SAC: the package's sac.yml gives the paper's common settings, so the
    # arms match; on a task it does not name, rl-zoo3's entry applies
    shared = {}
    for algo in ("serasac", "sac"):
        spec = specs.make_spec(variant=algo, algo=algo, env_id="HalfCheetah-v5", seed=0, n_timesteps=20000)
        shared[algo] = registry.shared_settings(algo, spec.hyperparams)
    assert shared["sac"] == shared["serasac"] and shared["sac"]["learning_starts"] == 10000
    assert registry.default_hyperparams("sac", "HalfCheetah-v5")[1] == "hyperparams/sac.yml:HalfCheetah-v5"
    assert registry.default_hyperparams("sac", "Hopper-v5")[1] == "rl_zoo3/hyperparams/sac.yml:default"
    # A comparison whose arms differ in a shared setting is refused naming it and each arm's value
    with pytest.raises(SystemExit):
        main(["compare", *TINY, "--out", str(tmp_path / "runs"), "-params", "sac:batch_size:64"])
    error = capsys.readouterr().err
    assert "differ in batch_size: serasac=256, sac=64" in error and "compare --studies batch_size" in error
    assert not (tmp_path / "runs").exists()


def test_default_threads_follow_omp_num_threads(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert backends.default_threads(1) == 1
    monkeypatch.delenv("OMP_NUM_THREADS")
    monkeypatch.setattr(backends.os, "cpu_count", lambda: 8)
    assert backends.default_threads(1) == 8 and backends.default_threads(3) == 2 and backends.default_threads(16) == 1


def test_schedules_read_as_rl_zoo3_reads_them():
    converted = engine.schedules({"learning_rate": "lin_1e-3", "clip_range": 0.2, "gamma": "lin_0.9"})
    # Only rl-zoo3's schedule keys, text only: linear from the initial value at progress 1 to 0 at progress 0
    assert list(converted) == ["learning_rate"]
    assert converted["learning_rate"](1.0) == pytest.approx(1e-3) and converted["learning_rate"](0.5) == pytest.approx(5e-4)
    with pytest.raises(ValueError, match=r"learning_rate='exp_3' is not a schedule: write a number, or lin_<initial"):
        engine.schedules({"learning_rate": "exp_3"})


def _results(finals: dict[str, list[float]]) -> list:
    return [
        RunResult(
            variant=algo, algo=algo, env_id="Pendulum-v1", seed=seed, n_timesteps=6000, wall_time_s=1.0, final_return=value
        )
        for algo, values in finals.items()
        for seed, value in enumerate(values)
    ]


def test_the_summary_gives_the_difference_its_interval_and_a_decision_only_where_one_is_possible():
    # Two runs a side: 2 of the 6 splits are as extreme as any, so no p below 1/3 exists
    short = summary.summary(_results({"serasac": [-200.0, -180.0], "sac": [-300.0, -250.0]}), ["serasac", "sac"])
    assert "  serasac  -190.0 ± 14.1 (2 run(s))\n  sac      -275.0 ± 35.4 (2 run(s))" in short
    assert "serasac - sac: +85.0, 95% Welch interval [" in short
    assert short.endswith("; too few runs to decide (smallest possible p 0.333 at 2 against 2)")
    # Six a side, fully apart: the two extreme splits of 924, 2/924
    finals = {"serasac": [-200.0 + i for i in range(6)], "sac": [-260.0 + 3 * i for i in range(6)]}
    assert summary.summary(_results(finals), ["serasac", "sac"]).endswith("; p 0.00216: serasac ahead")
    assert summary.summary(_results(finals), ["sac", "serasac"]).endswith("; p 0.00216: sac behind")
    # Undecided: the runs do not separate the two, which is not a finding that they are alike
    level = {"serasac": [-200.0, -210.0, -190.0, -205.0], "sac": [-201.0, -195.0, -211.0, -199.0]}
    assert summary.summary(_results(level), ["serasac", "sac"]).endswith(": not separated (not a finding of no difference)")


def test_the_reading_says_what_the_runs_can_decide_and_where_a_real_comparison_is():
    results = _results({"serasac": [-200.0, -180.0], "sac": [-300.0, -250.0]})
    for result in results:
        result.timesteps, result.returns = [1000, 2000, 4000, 6000], [-1200.0, *[result.final_return] * 3]
        result.hyperparams["learning_starts"] = 1000
    text = summary.reading(results, ["serasac", "sac"])
    assert "Learning (mean evaluation return, first -> final): serasac -1200 at step 1,000 -> -190; sac -1200" in text
    # 2 runs a side: the smallest p is 1/3; 4 a side (2 of 70 splits: 0.029) is the fewest that can decide
    assert summary.runs_to_decide() == 4
    assert "2 run(s) a side cannot tell serasac from sac at p < 0.05" in text and "--seeds 0 1 2 3)" in text
    assert "each ended above its first evaluation, so these runs show that each trains" in text
    # A run that did not improve says so: the README's small HalfCheetah comparison (-1 -> -9 and -3 -> -7)
    for result, first in zip(results, [-1.0, -1.0, -3.0, -3.0], strict=True):
        result.returns = [first, *[-9.0 if result.variant == "serasac" else -7.0] * 3]
    for result in results:
        result.final_return = result.returns[-1]
    text = summary.reading(results, ["serasac", "sac"])
    assert "serasac -1 at step 1,000 -> -9 (no better than its first evaluation); sac -3" in text
    assert "serasac and sac ended no better than their first evaluation, so these runs show no learning" in text
    assert "each trains" not in text
    # Three evaluations, the first at learning_starts (before any gradient step): the last three are not three of
    # training, so nothing is said of learning (once: "each trains" of -24.85 -> -24.64)
    for result in results:
        result.timesteps, result.returns = [1000, 2000, 3000], [-24.85, -24.7, -24.64]
    text = summary.reading(results, ["serasac", "sac"])
    assert "serasac and sac: too few evaluations after learning starts to tell whether they train" in text
    assert "Learning (" not in text and "each trains" not in text
    finals = {"serasac": [-200.0 + i for i in range(6)], "sac": [-260.0 + 3 * i for i in range(6)]}
    assert "serasac ahead of sac on this task at 6,000 steps (p 0.00216)" in summary.reading(
        _results(finals), ["serasac", "sac"]
    )
    level = {"serasac": [-200.0, -210.0, -190.0, -205.0], "sac": [-201.0, -195.0, -211.0, -199.0]}
    assert (
        "These runs do not separate serasac from sac (not a finding of no difference): the interval allows"
        in summary.reading(_results(level), ["serasac", "sac"])
    )


@pytest.mark.skipif(th.cuda.is_available(), reason="a machine without CUDA")
def test_a_cuda_device_without_cuda_is_refused_not_run_on_the_cpu(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["compare", "--out", str(tmp_path / "runs"), "--device", "cuda"])
    assert "device='cuda', but torch finds no CUDA device on this machine" in capsys.readouterr().err
    assert not (tmp_path / "runs").exists()


def test_version_flag(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out.strip() == f"sb3-sera {sb3_sera.__version__}"


def test_an_off_policy_setting_for_an_on_policy_algorithm_says_so():
    with pytest.raises(ValueError, match=r"ppo is on-policy and takes no 'learning_starts' \(an off-policy algorithm's"):
        registry.check_hyperparams("ppo", {"learning_starts": 100}, "-params")
    with pytest.raises(ValueError, match=r"did you mean 'learning_rate' for 'learning_rat'"):
        registry.check_hyperparams("ppo", {"learning_rat": 1e-3}, "-params")
