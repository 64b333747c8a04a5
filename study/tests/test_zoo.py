"""rl-zoo3 bridge: the zoo's own train / enjoy / optimize with this package's algorithms and hyperparameter files."""

import inspect
import os
import pickle
import subprocess
import sys

import gymnasium as gym
import numpy as np
import optuna
import pytest
import yaml

from sb3_sera import SERASAC
from sera_study.cli import main
from sera_study.registry import default_hyperparams
from sera_study.runs.zoo import (
    HYPERPARAMS_DIR,
    MULTI_AGENT_ALGOS,
    SINGLE_AGENT_ALGOS,
    ZOO_ALGOS,
    ZOO_OFF_POLICY_ALGOS,
    register_with_zoo,
    zoo_argv,
)
from tests.helpers import CTDE_TASK, ENV_ID

PAPER_TASKS = {
    "HalfCheetah-v5",
    "Ant-v5",
    "Humanoid-v5",
    "sb3_sera/HalfCheetah-6x1-v0",
    "sb3_sera/Hopper-3x1-v0",
    "sb3_sera/Pusher-3p-v0",
    "sb3_sera/Multiwalker-v0",
    "sb3_sera/SimpleSpread-v0",
}
# Every Gymnasium MuJoCo v5 task
MUJOCO_V5_TASKS = {
    env_id
    for env_id, spec in gym.registry.items()
    if isinstance(spec.entry_point, str) and spec.entry_point.startswith("gymnasium.envs.mujoco") and env_id.endswith("-v5")
}
# Keys rl-zoo3 reads itself rather than passing to the algorithm
ZOO_KEYS = {"n_timesteps", "policy", "n_envs", "noise_type", "noise_std", "normalize", "env_wrapper", "frame_stack"}


@pytest.mark.parametrize("algo", ZOO_ALGOS)
def test_hyperparameter_files_cover_the_paper_tasks(algo):
    entries = yaml.load((HYPERPARAMS_DIR / f"{algo}.yml").read_text(), Loader=yaml.UnsafeLoader)
    # The single-agent baselines have no entries for the multi-agent tasks, whose policies they refuse, and IET none
    # for the single-agent tasks
    if algo in MULTI_AGENT_ALGOS:
        assert set(entries) == {task for task in PAPER_TASKS if task.startswith("sb3_sera/")}
    else:
        paper_tasks = {task for task in PAPER_TASKS if algo not in SINGLE_AGENT_ALGOS or not task.startswith("sb3_sera/")}
        assert set(entries) >= paper_tasks | {"Pendulum-v1"}
        assert len(MUJOCO_V5_TASKS) == 11 and set(entries) >= MUJOCO_V5_TASKS
    accepted = set(inspect.signature(ZOO_ALGOS[algo]).parameters)
    for env_id, entry in entries.items():
        unknown = set(entry) - ZOO_KEYS - accepted
        assert not unknown, (env_id, unknown)
        expected_policy = "CTDEPolicy" if env_id.startswith("sb3_sera/") else "MlpPolicy"
        assert entry["policy"] == expected_policy, env_id
        if env_id in PAPER_TASKS:
            assert entry["n_timesteps"] == 300_000
            # Paper Table 5, except ACE, which keeps its authors' learning rate
            assert entry["gamma"] == 0.99 and entry["learning_rate"] == (1e-4 if algo == "ace" else 3e-4)


def test_zoo_tables_and_arguments():
    register_with_zoo()
    from rl_zoo3 import hyperparams_opt, utils

    for algo in ZOO_ALGOS:
        assert utils.ALGOS[algo] is ZOO_ALGOS[algo]
        assert algo in hyperparams_opt.HYPERPARAMS_SAMPLER and algo in hyperparams_opt.HYPERPARAMS_CONVERTER
    assert zoo_argv("train", ["--algo", "masac"])[-2:] == ["--conf-file", str(HYPERPARAMS_DIR / "masac.yml")]
    mine = ["--algo", "masac", "-conf", "mine.yml"]
    assert zoo_argv("train", mine) == [*mine, "--num-threads", "1"]
    assert "-optimize" in zoo_argv("optimize", ["--algo", "serasac"])
    # Stock SAC reads the package's sac.yml on the tasks it names, rl-zoo3's own file on the others
    sac = ["--algo", "sac", "--env"]
    assert zoo_argv("train", [*sac, "HalfCheetah-v5"])[-1] == str(HYPERPARAMS_DIR / "sac.yml")
    assert zoo_argv("train", [*sac, "Pendulum-v1"]) == [*sac, "Pendulum-v1", "--num-threads", "1"]
    # So do sb3-contrib's TQC and CrossQ: the zoo's HalfCheetah-v4 settings for v5 (CrossQ's critics 1024 wide)
    for algo in ("tqc", "crossq"):
        assert zoo_argv("train", ["--algo", algo, "--env", "HalfCheetah-v5"])[-1] == str(HYPERPARAMS_DIR / f"{algo}.yml")
    assert default_hyperparams("tqc", "HalfCheetah-v5")[0]["learning_starts"] == 10_000
    crossq, where = default_hyperparams("crossq", "HalfCheetah-v5")
    assert where == "hyperparams/crossq.yml:HalfCheetah-v5" and "qf=[1024, 1024]" in crossq["policy_kwargs"]
    assert (crossq["learning_rate"], crossq["learning_starts"], crossq["policy_delay"]) == (1e-3, 5000, 3)
    assert default_hyperparams("tqc", "Hopper-v4")[1] == "rl_zoo3/hyperparams/tqc.yml:Hopper-v4"
    with pytest.raises(ValueError, match="Unknown zoo command 'fly'"):
        zoo_argv("fly", [])


def test_train_and_optimize_take_one_torch_thread_unless_told(monkeypatch):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    for command in ("train", "optimize"):
        args = zoo_argv(command, ["--algo", "serasac", "--env", "Pendulum-v1"])
        assert args[args.index("--num-threads") + 1] == "1"
    assert zoo_argv("train", ["--algo", "sac", "--num-threads", "4"]).count("--num-threads") == 1
    assert "--num-threads" not in zoo_argv("enjoy", ["--algo", "sac"])
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    args = zoo_argv("train", ["--algo", "sac"])
    assert args[args.index("--num-threads") + 1] == "3"


def test_enjoy_and_record_video_load_off_policy_models_with_a_one_transition_buffer(tmp_path):
    from rl_zoo3 import utils

    SERASAC("MlpPolicy", "Pendulum-v1", buffer_size=100_000).save(tmp_path / "model")
    assert set(ZOO_OFF_POLICY_ALGOS) == {"serasac", "masac", "matd3", "maddpg", "sunrise", "ace", "iet"}
    try:
        register_with_zoo("enjoy")
        loaded = utils.ALGOS["serasac"].load(tmp_path / "model")
        assert isinstance(loaded, SERASAC) and loaded.replay_buffer.buffer_size == 1
        assert utils.ALGOS["mappo"] is ZOO_ALGOS["mappo"]  # on-policy: no buffer
    finally:
        register_with_zoo()
    assert all(utils.ALGOS[algo] is ZOO_ALGOS[algo] for algo in ZOO_ALGOS)


def test_record_video_of_a_mamujoco_task(tmp_path, sb3_sera):
    folder = str(tmp_path)
    sb3_sera(
        "train",
        "--algo",
        "masac",
        "--env",
        "sb3_sera/Pusher-3p-v0",
        "-n",
        "100",
        "-f",
        folder,
        "--seed",
        "0",
        "-params",
        "learning_starts:50",
    )
    videos = tmp_path / "videos"
    args = ["--algo", "masac", "--env", "sb3_sera/Pusher-3p-v0", "-f", folder, "--exp-id", "1", "-n", "20", "-o", str(videos)]
    sb3_sera("record-video", *args, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    assert [path.suffix for path in videos.iterdir()] == [".mp4"]


def test_serasac_sampler_keeps_table_4_critics():
    register_with_zoo()
    from rl_zoo3 import hyperparams_opt

    trial = optuna.create_study().ask()
    params = hyperparams_opt.HYPERPARAMS_SAMPLER["serasac"](trial, 1, 1, {"using_her_replay_buffer": False})
    assert set(params["policy_kwargs"]["net_arch"]) == {"pi"}
    assert 0.0 <= params["sera_alpha"] <= 1.0 and params["sera_temperature"] > 0
    # A stored trial converts the same way
    stored = hyperparams_opt.HYPERPARAMS_CONVERTER["serasac"](dict(trial.params))
    assert stored["policy_kwargs"] == params["policy_kwargs"] and stored["sera_alpha"] == params["sera_alpha"]


def test_train_then_enjoy_a_zoo_run(tmp_path, sb3_sera_here):
    folder = str(tmp_path)
    evaluate = ["--eval-freq", "100", "--eval-episodes", "2"]
    sb3_sera_here("train", "--algo", "serasac", "--env", "Pendulum-v1", "-n", "300", "-f", folder, "--seed", "0", *evaluate)
    sb3_sera_here(
        "train", "--algo", "masac", "--env", "sb3_sera/SimpleSpread-v0", "-n", "200", "-f", folder, "--seed", "0", *evaluate,
        "-params", "learning_starts:50",
    )  # fmt: skip
    run = tmp_path / "serasac" / "Pendulum-v1_1"
    assert (run / "Pendulum-v1.zip").exists() and (run / "0.monitor.csv").exists()
    # The zoo saved the hyperparameters it read from this repository's file
    assert "critic_lr_max" in (run / "Pendulum-v1" / "config.yml").read_text()
    enjoyed = sb3_sera_here("enjoy", "--algo", "serasac", "--env", "Pendulum-v1", "-f", folder, "--exp-id", "1", "-n", "200")
    assert "Mean reward" in enjoyed
    assert (tmp_path / "masac" / "sb3_sera-SimpleSpread-v0_1" / "sb3_sera-SimpleSpread-v0.zip").exists()
    # The zoo's evaluations recorded the initial-state bias: three evaluations of two episodes
    bias = np.load(run / "initial_state_bias.npz")
    assert bias["timesteps"].tolist() == [100, 200, 300] and bias["values"].shape == (3, 2)
    # rl-zoo3's plotting scripts (extra "plots") read the run folders, given the dashed folder name of an sb3_sera/ id
    plots = [sys.executable, "-m", "rl_zoo3.plots.all_plots", "-a", "masac", "-f", folder, "--no-display", "-k", "results"]
    completed = subprocess.run(
        [*plots, "-e", "sb3_sera-SimpleSpread-v0", "-o", str(tmp_path / "curves")],
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "MPLBACKEND": "Agg"},
    )
    assert completed.returncode == 0, completed.stderr[-3000:]
    with open(tmp_path / "curves.pkl", "rb") as file:
        curves = pickle.load(file)
    assert list(curves["sb3_sera-SimpleSpread-v0"]) == [f"MASAC-{folder}"]
    # The report reads the zoo's run folders and records too (seed and budget from args.yml), bias and diagnostics
    reported = sb3_sera_here("report", folder, "--out", str(tmp_path / "report"), "--reps", "200")
    assert "## Pendulum-v1, 300 steps" in reported and "## sb3_sera/SimpleSpread-v0, 200 steps" in reported
    for figure in ("bias", "diagnostics", "correlations"):
        assert (tmp_path / "report" / f"Pendulum-v1_300_{figure}.png").exists()


def test_two_workers_tune_one_study(tmp_path):
    storage = f"sqlite:///{tmp_path / 'study.db'}"
    # A fixed sampler seed keeps the sampled batch size and gradient steps (hence the cost) the same on every run
    args = ["optimize", "--algo", "serasac", "--env", "Pendulum-v1", "-n", "120", "--n-trials", "1", "--n-jobs", "1"]
    # One torch thread per worker: two workers with torch's default (one thread per core) oversubscribe the cores
    args += ["--seed", "3", "--num-threads", "1"]
    args += ["--storage", storage, "--study-name", "shared", "--sampler", "random", "--pruner", "none"]
    args += ["--n-evaluations", "1", "--eval-episodes", "1", "-f", str(tmp_path), "-params", "learning_starts:50"]
    # The storage is created once, before the workers start (two workers creating one SQLite schema at the same
    # moment race each other in Optuna); each worker then loads the study
    optuna.create_study(study_name="shared", storage=storage, direction="maximize")
    workers = [
        subprocess.Popen([sys.executable, "-m", "sera_study", *args], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        for _ in range(2)
    ]
    for worker in workers:
        _, stderr = worker.communicate(timeout=600)
        assert worker.returncode == 0, stderr.decode()[-3000:]
    trials = optuna.load_study(study_name="shared", storage=storage).trials
    assert len(trials) == 2
    assert all(trial.state == optuna.trial.TrialState.COMPLETE and np.isfinite(trial.value) for trial in trials)


def test_ace_sampler_and_stored_trial():
    register_with_zoo()
    from rl_zoo3 import hyperparams_opt

    trial = optuna.create_study().ask()
    params = hyperparams_opt.HYPERPARAMS_SAMPLER["ace"](trial, 1, 1, {})
    assert set(params["policy_kwargs"]) == {"n_actors", "depth"}
    assert hyperparams_opt.HYPERPARAMS_CONVERTER["ace"](dict(trial.params)) == params


@pytest.mark.parametrize(
    ("algo", "env", "message"),
    [
        ("iet", "Pendulum-v1", r"iet is multi-agent only: train it on a CTDE task \(sb3_sera/"),
        ("sunrise", "sb3_sera/SimpleSpread-v0", r"sunrise is single-agent only"),
        ("ace", "sb3_sera/HalfCheetah-6x1-v0", r"ace is single-agent only"),
    ],
)
def test_an_algorithm_on_a_task_of_the_other_kind_is_refused_with_the_reason(algo, env, message, capsys):
    with pytest.raises(ValueError, match=message):
        zoo_argv("train", ["--algo", algo, "--env", env])
    with pytest.raises(SystemExit, match=message):
        main(["train", "--algo", algo, "--env", env, "-n", "10"])


def test_train_reads_params_without_executing_them(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    base = ["--algo", "serasac", "--env", "Pendulum-v1", "-n", "300"]
    # Each value rewritten as the literal it was read as: rl-zoo3's eval rebuilds it and can run nothing else
    args = zoo_argv(
        "train", [*base, "-params", "learning_starts:100", "learning_rate:lin_1e-3", "policy_kwargs:dict(net_arch=[64])"]
    )
    assert args[args.index("-params") + 1 : args.index("-params") + 4] == [
        "learning_starts:100",
        "learning_rate:'lin_1e-3'",
        "policy_kwargs:dict(net_arch=[64])",
    ]
    code = "policy_kwargs:__import__('os').system('touch marker')"
    for params, message in [
        ([code], r"is not allowed; write literals, dict\(key=value\) and these names only"),
        (["sera_alfa:0.3"], r"unknown hyperparameter\(s\) \['sera_alfa'\] for serasac; did you mean 'sera_alpha'"),
        (["learning_starts:500"], r"learning_starts=500 is at or above the budget n_timesteps=300: the run would train"),
        (["learning_starts"], r"-params item 'learning_starts' is invalid: expected key:value"),
    ]:
        with pytest.raises(SystemExit, match=message):
            main(["train", *base, "-params", *params])
    # Refused before rl-zoo3 starts: nothing ran, no folder was made
    assert not (tmp_path / "marker").exists() and not (tmp_path / "logs").exists()
    # A value the model refuses once rl-zoo3 has made the run's folder: the folder goes with the failed start
    with pytest.raises(SystemExit, match=r"sera_alpha=2.0 is out of range"):
        main(["train", *base, "-params", "sera_alpha:2.0"])
    assert not (tmp_path / "logs").exists()
    # A key mistyped in a hyperparameter file reaches the model (the zoo passes it on): one line, no folder either
    (tmp_path / "hp.yml").write_text("Pendulum-v1:\n  n_timesteps: 300\n  policy: MlpPolicy\n  critic_lr_mx: 0.001\n")
    with pytest.raises(SystemExit, match=r"unexpected keyword argument 'critic_lr_mx'. Did you mean 'critic_lr_max'"):
        main(["train", "--algo", "serasac", "--env", "Pendulum-v1", "-conf", "hp.yml"])
    assert not (tmp_path / "logs").exists()


def test_the_zoo_reads_the_capabilities_the_classes_declare():
    from sb3_sera.common.capabilities import Capabilities, capabilities
    from sb3_sera.common.compiled import CompiledUpdate

    assert all(issubclass(algo, Capabilities) for algo in ZOO_ALGOS.values())
    assert set(SINGLE_AGENT_ALGOS) == {name for name, algo in ZOO_ALGOS.items() if not capabilities(algo)["multi_agent"]}
    assert set(MULTI_AGENT_ALGOS) == {"iet"} and set(SINGLE_AGENT_ALGOS) == {"sunrise", "ace"}
    assert not capabilities(ZOO_ALGOS["mappo"])["off_policy"] and capabilities(ZOO_ALGOS["masac"])["tunes_like"] == "sac"
    # What the evaluations and compile_update read, declared where it holds (SB3's own SAC: the defaults, soft critics)
    declared = {name: capabilities(algo) for name, algo in ZOO_ALGOS.items()}
    compiled = {name for name, algo in ZOO_ALGOS.items() if issubclass(algo, CompiledUpdate)}
    assert compiled == {"serasac", "sunrise", "masac", "iet", "matd3", "maddpg"}
    assert {name for name, values in declared.items() if values["soft_q_critics"]} == {"serasac", "masac", "iet"}
    assert {name for name, values in declared.items() if values["own_td_targets"] or values["per_critic_rates"]} == {"serasac"}
    assert {name for name, values in declared.items() if values["acts_on_latents"]} == {"iet"}
    from stable_baselines3 import SAC, TD3

    assert capabilities(SAC)["soft_q_critics"] and not capabilities(TD3)["soft_q_critics"]


@pytest.mark.parametrize("algo", sorted(ZOO_ALGOS))
def test_every_algorithm_declares_one_search_space_beside_it_that_round_trips(algo):
    """A space of its own (``tuning``) or an SB3 algorithm's (``tunes_like``), never both nor neither; a trial's
    hyperparameters are the algorithm's keywords, and the zoo's conversion of the stored trial gives them back."""
    from sb3_sera.common.arguments import check_keywords
    from sb3_sera.common.capabilities import capabilities

    declared = capabilities(ZOO_ALGOS[algo])
    assert (declared["tuning"] is None) != (declared["tunes_like"] is None)
    if declared["tuning"] is None:
        return
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    trial = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0)).ask()
    sampled = declared["tuning"].sample(trial, 2, 1, {"using_her_replay_buffer": False})
    check_keywords(ZOO_ALGOS[algo], sampled)
    assert declared["tuning"].convert(dict(trial.params)) == sampled


@pytest.mark.parametrize(
    ("algo", "env_id", "n_steps", "eval_episodes", "params", "bias_shape", "enjoy_steps"),
    [
        # IET's evaluations (their env given latents by the callback) value each episode's first state too
        ("iet", CTDE_TASK, "200", "2", ["-params", "learning_starts:50"], (2, 2), "60"),
        # SUNRISE's record the ensemble's value of each episode's first state (all 10 critics)
        ("sunrise", ENV_ID, "300", "1", [], (3, 1), "200"),
    ],
)
def test_zoo_train_with_evaluations_then_enjoy(
    tmp_path, sb3_sera_here, algo, env_id, n_steps, eval_episodes, params, bias_shape, enjoy_steps
):
    common = ["--algo", algo, "--env", env_id, "-f", str(tmp_path), "--num-threads", "1"]
    evaluations = ["--eval-freq", "100", "--eval-episodes", eval_episodes]
    sb3_sera_here("train", *common, "-n", n_steps, "--seed", "0", *evaluations, *params)
    name = env_id.replace("/", "-")
    run = tmp_path / algo / f"{name}_1"
    assert (run / f"{name}.zip").exists() and (run / "evaluations.npz").exists()
    assert np.load(run / "initial_state_bias.npz")["values"].shape == bias_shape
    assert "Mean reward" in sb3_sera_here("enjoy", *common, "--exp-id", "1", "-n", enjoy_steps, "--no-render")
