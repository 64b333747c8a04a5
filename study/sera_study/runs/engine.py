"""
Training one run: its model built from its spec as rl-zoo3 builds it (and every spec's model built once before any
run starts, so that a bad setting is refused early), trained in its run folder with the evaluation callback and a
progress file, and its records written, ``result.json`` last to mark the run finished.
"""

import copy
import json
import os
import platform
import socket
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
import yaml
from gymnasium import spaces
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.vec_env import VecEnv

from sb3_sera.common.capabilities import as_the_model_sees
from sb3_sera.common.evaluation import InitialStateBiasCallback
from sb3_sera.common.mujoco_log import route_mujoco_warnings
from sb3_sera.ctde.env import STATE_KEY
from sera_study.runs.checkpoint import Checkpointer, has_checkpoint, load_checkpoint, remove_checkpoints
from sera_study.runs.folders import notice, set_aside
from sera_study.runs.policy_kwargs import parse_policy_kwargs
from sera_study.records import (
    RESULT_FILE,
    RunResult,
    append_record,
    env_name,
    load_result,
    plain,
    read_list,
    records_dir,
    utc_stamp,
    write_atomic,
)
from sera_study.registry import RUN_KEYS, algorithm_classes
from sera_study.runs.specs import RunSpec

#: The keys whose text value rl-zoo3 reads as a schedule (``lin_3e-4``: linear from 3e-4 to 0), as its train does
SCHEDULE_KEYS = ("learning_rate", "clip_range", "clip_range_vf", "delta_std")


def schedules(hyperparams: dict[str, Any]) -> dict[str, Any]:
    """
    The values of :data:`SCHEDULE_KEYS` given as text turned into rl-zoo3's linear schedules (its public
    ``linear_schedule``), as ``sb3-sera train`` reads the same YAML entry; ``ValueError`` naming any other text.
    """
    from rl_zoo3.utils import linear_schedule

    converted = {}
    for key in SCHEDULE_KEYS:
        value = hyperparams.get(key)
        if not isinstance(value, str):
            continue
        kind, _, initial = value.partition("_")
        try:
            if kind != "lin":
                raise ValueError
            converted[key] = linear_schedule(float(initial))
        except ValueError:
            raise ValueError(f"{key}={value!r} is not a schedule: write a number, or lin_<initial value> (lin_3e-4)") from None
    return converted


def make_model(spec: RunSpec, env: VecEnv, tensorboard_log: str | None = None) -> BaseAlgorithm:
    """The spec's model on ``env``, its hyperparameters turned into objects as rl-zoo3 does."""
    kwargs = {key: value for key, value in spec.hyperparams.items() if key not in RUN_KEYS}
    kwargs.update(schedules(kwargs))
    if isinstance(kwargs.get("policy_kwargs"), str):
        kwargs["policy_kwargs"] = parse_policy_kwargs(kwargs["policy_kwargs"])
    elif isinstance(kwargs.get("policy_kwargs"), dict):
        # SB3 writes into the dict it is given (use_sde, ...): a grid's dict shared by variants must stay as written
        kwargs["policy_kwargs"] = copy.deepcopy(kwargs["policy_kwargs"])
    if isinstance(kwargs.get("train_freq"), list):
        kwargs["train_freq"] = tuple(kwargs["train_freq"])
    noise_type = spec.hyperparams.get("noise_type")
    if noise_type is not None:
        assert isinstance(env.action_space, spaces.Box)
        n_actions = env.action_space.shape[0]
        noise_std = float(spec.hyperparams.get("noise_std", 0.1))
        noises = {"normal": NormalActionNoise, "ornstein-uhlenbeck": OrnsteinUhlenbeckActionNoise}
        if noise_type not in noises:
            raise ValueError(f"noise_type={noise_type!r} is invalid: expected one of {sorted(noises)}")
        kwargs["action_noise"] = noises[noise_type](mean=np.zeros(n_actions), sigma=noise_std * np.ones(n_actions))
    policy = spec.hyperparams.get("policy", policy_for(env))
    model_class = algorithm_classes()[spec.algo]
    return model_class(policy, env, seed=spec.seed, verbose=0, device=spec.device, tensorboard_log=tensorboard_log, **kwargs)


def check_specs(specs: Sequence[RunSpec]) -> None:
    """
    Build each distinct (algorithm, task, hyperparameters) model once, without training, so that a value out of range
    (``sera_alpha=2``) or a bad ``policy_kwargs`` is refused before the first run starts: ``ValueError`` naming the run.
    """
    seen = set()
    for spec in specs:
        key = json.dumps([spec.algo, spec.env_id, spec.hyperparams], sort_keys=True, default=str)
        if key in seen:
            continue
        seen.add(key)
        env = make_vec_env(spec.env_id, n_envs=1, env_kwargs=spec.hyperparams.get("env_kwargs") or {})
        try:
            make_model(spec, env)
        except (ValueError, TypeError, KeyError, SyntaxError, NameError) as error:
            raise ValueError(f"{spec.variant} on {spec.env_id}: {type(error).__name__}: {error}") from None
        finally:
            env.close()


def policy_for(env: VecEnv) -> str:
    """``"CTDEPolicy"`` for a multi-agent CTDE task (Dict observation with a state), else ``"MlpPolicy"``."""
    space = env.observation_space
    return "CTDEPolicy" if isinstance(space, spaces.Dict) and STATE_KEY in space.spaces else "MlpPolicy"


#: Where a running run keeps its step count for the command's progress bar (removed when it ends)
PROGRESS_FILE = ".progress"


class ProgressFile(BaseCallback):
    """
    Writes the model's step count to a file, for the progress bar of the command: at the first step, then whenever
    ``seconds`` have passed since the last write, so that the bar moves with the steps made whatever their rate.
    """

    def __init__(self, path: Path, seconds: float = 1.0) -> None:
        super().__init__()
        self.path, self.seconds = path, seconds
        self._written: float | None = None

    def _on_step(self) -> bool:
        now = time.monotonic()
        if self._written is None or now - self._written >= self.seconds:
            write_atomic(self.path, str(self.num_timesteps))
            self._written = now
        return True


class StopAtBudget(BaseCallback):
    """
    Ends an on-policy ``learn()`` at the run's budget: SB3's on-policy loop finishes the rollout under way past it
    (rollouts of 2,048 steps took a 50,000-step MAPPO run to 51,200), where this stops collecting at the budget and
    trains on no partial rollout. Off-policy runs end at the budget without it (a step, then its gradient step).
    """

    def __init__(self, budget: int) -> None:
        super().__init__()
        self.budget = budget

    def _on_step(self) -> bool:
        return self.num_timesteps < self.budget


#: Where a run under way keeps its resumes until ``result.json`` takes them
RESUMES_FILE = ".resumes.json"
#: Where a run under way keeps where each of its starts ran (:func:`placement`) until ``result.json`` takes them
ATTEMPTS_FILE = ".attempts.json"


def cpu_model(cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """This machine's CPU model, as Linux names it in ``cpuinfo`` (else ``platform.processor()``, else "unknown")."""
    try:
        for line in cpuinfo.read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and value.strip():
                return value.strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def placement() -> dict[str, Any]:
    """
    Where this process makes a run: the host, its CPU model, the GPU torch sees (where there is one), the GPUs it may
    use (``CUDA_VISIBLE_DEVICES``, where set) and, in a Ray task, the node and the resources Ray gave it (a GPU's
    share with ``--gpus-per-run``).
    """
    where: dict[str, Any] = {"host": socket.gethostname(), "cpu": cpu_model()}
    if th.cuda.is_available():
        where["gpu"] = th.cuda.get_device_name()
    if "CUDA_VISIBLE_DEVICES" in os.environ:
        where["cuda_visible_devices"] = os.environ["CUDA_VISIBLE_DEVICES"]
    ray = sys.modules.get("ray")  # imported in a Ray worker; never imported here for a local run
    context = ray.get_runtime_context() if ray is not None and ray.is_initialized() else None
    if context is not None and context.get_task_id() is not None:
        where.update(ray_node=context.get_node_id(), ray_resources=context.get_assigned_resources())
    return where


def steps_done(folder: Path, budget: int) -> int:
    """Steps a run has made: its budget when finished, else what its progress file says (0 before it starts)."""
    if (folder / RESULT_FILE).exists():
        return budget
    try:
        return min(int((folder / PROGRESS_FILE).read_text() or 0), budget)
    except (OSError, ValueError):
        return 0


def train_one(spec: RunSpec, folder: str | Path) -> RunResult:
    """
    Train one run in its folder (made by :func:`.assign_folders`), evaluating every ``spec.eval_freq`` steps; a
    finished run is read back.
    """
    folder = Path(folder)
    if (folder / RESULT_FILE).exists():
        return load_result(folder)
    route_mujoco_warnings()
    # rl-zoo3 replaces Gymnasium's TimeLimit when imported (as `sb3-sera train` does): patched before any env is
    # made, every env of every run is built alike, whatever the caller imported and when, and a resumed run's envs as
    # its first process built them
    import rl_zoo3.gym_patches  # noqa: F401

    code = _start_records(spec, folder)
    if spec.num_threads is not None:
        th.set_num_threads(spec.num_threads)
    envs = _RunEnvs(spec, folder)
    callback = envs.callback()
    model, elapsed, callback = _resumed(spec, folder, envs, callback, code)
    if model is None:
        model = make_model(spec, envs.train(str(folder)), tensorboard_log=str(folder))
    trained = model

    def make_both() -> tuple[VecEnv, VecEnv]:
        # As the model sees its envs (IET's with its latents), for the checkpoint's check that their states go back
        return as_the_model_sees(trained, envs.train()), as_the_model_sees(trained, envs.evaluation())

    callbacks: list[BaseCallback] = [callback, ProgressFile(folder / PROGRESS_FILE)]
    if spec.checkpoint_freq > 0:
        callbacks.append(Checkpointer(folder, spec.checkpoint_freq, callback, make_both, spec.env_id, elapsed))
    if not isinstance(model, OffPolicyAlgorithm):
        callbacks.append(StopAtBudget(spec.n_timesteps))
    start = time.perf_counter()
    model.learn(
        spec.n_timesteps - model.num_timesteps,
        callback=callbacks,
        tb_log_name=f"{spec.variant}_seed{spec.seed}",
        reset_num_timesteps=model.num_timesteps == 0,
    )
    _finish(spec, folder, model, callback, elapsed + time.perf_counter() - start)
    return load_result(folder)


def _start_records(spec: RunSpec, folder: Path) -> tuple[str | None, str | None]:
    """
    Record where this start runs and the run's settings; the commits of the code that ran the run before (None for a
    run never started) and of the code that runs now.
    """
    # An interrupted run starts again here, maybe under newer code (or on another machine, a Ray task retried after
    # its node was lost): its record names the code that runs now, its resumes (below) the code before, and its
    # attempts where each start ran
    append_record(folder / ATTEMPTS_FILE, {"at": utc_stamp(), **placement()})
    records = records_dir(folder, spec.env_id) / "args.yml"
    code_before = (yaml.safe_load(records.read_text()) or {}).get("git_commit") if records.exists() else None
    args = plain(spec.args())
    write_atomic(records, yaml.safe_dump(args, sort_keys=True))
    return code_before, args.get("git_commit")


class _RunEnvs:
    """
    A run's environments: the training env (monitored in the run's folder, or not), the evaluation env, and the
    evaluation callback that records the run's evaluations in its folder.
    """

    def __init__(self, spec: RunSpec, folder: Path):
        self.spec, self.folder = spec, folder
        self.env_kwargs = spec.hyperparams.get("env_kwargs") or {}
        self.n_envs = int(spec.hyperparams.get("n_envs", 1))

    def train(self, monitor_dir: str | None = None) -> VecEnv:
        spec = self.spec
        return make_vec_env(
            spec.env_id, n_envs=self.n_envs, seed=spec.seed, monitor_dir=monitor_dir, env_kwargs=self.env_kwargs
        )

    def evaluation(self) -> VecEnv:
        return make_vec_env(self.spec.env_id, n_envs=1, seed=self.spec.seed + 10_000, env_kwargs=self.env_kwargs)

    def callback(self) -> InitialStateBiasCallback:
        return InitialStateBiasCallback(
            self.evaluation(),
            eval_freq=max(self.spec.eval_freq // self.n_envs, 1),
            n_eval_episodes=self.spec.n_eval_episodes,
            log_path=str(self.folder),
            verbose=0,
        )


def _resumed(
    spec: RunSpec,
    folder: Path,
    envs: _RunEnvs,
    callback: InitialStateBiasCallback,
    code: tuple[str | None, str | None],
) -> tuple[BaseAlgorithm | None, float, InitialStateBiasCallback]:
    """
    An interrupted run's model from its last checkpoint, the wall time it had, and the callback that goes on with its
    evaluations; ``(None, 0.0, callback)`` where there is none, or where it cannot be loaded (the run is set aside,
    and a new callback starts it again from step 0).
    """
    if not has_checkpoint(folder):
        return None, 0.0, callback
    # Interrupted: on from the last checkpoint, to the same final parameters as a run never interrupted
    env = envs.train()
    try:
        model, elapsed = load_checkpoint(algorithm_classes()[spec.algo], folder, spec.device, env, callback)
    except Exception as error:  # whatever it is, the run starts again and the checkpoint is kept for inspection
        env.close()
        callback.eval_env.close()
        aside = set_aside(folder, spec.env_id, error)
        notice(
            f"{folder}: not resumed: its checkpoint cannot be loaded ({type(error).__name__}: {error}); the run "
            f"is kept as {aside.name}, and starts again from step 0 in {folder.name}"
        )
        return None, 0.0, envs.callback()
    resume = {"from_step": int(model.num_timesteps), "at": utc_stamp(), "code_before": code[0], "code_after": code[1]}
    append_record(folder / RESUMES_FILE, resume)
    notice(f"{folder}: resumed from step {model.num_timesteps:,}")
    return model, elapsed, callback


def _finish(spec: RunSpec, folder: Path, model: BaseAlgorithm, callback: InitialStateBiasCallback, wall_time: float) -> None:
    """Save the model, close the envs and write ``result.json``, whose presence marks the run as finished."""
    (folder / PROGRESS_FILE).unlink(missing_ok=True)
    model.save(folder / env_name(spec.env_id))
    assert model.env is not None
    model.env.close()
    callback.eval_env.close()
    # Written last: its presence marks the run as finished. Threads and device as the worker saw them
    result = {
        "wall_time_s": wall_time,
        "torch_threads": th.get_num_threads(),
        "device": str(model.device),
        "resumes": read_list(folder / RESUMES_FILE),
        "attempts": read_list(folder / ATTEMPTS_FILE),
    }
    write_atomic(folder / RESULT_FILE, json.dumps(result))
    for name in (RESUMES_FILE, ATTEMPTS_FILE):
        (folder / name).unlink(missing_ok=True)
    if not spec.keep_checkpoints:
        remove_checkpoints(folder)
