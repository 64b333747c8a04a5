"""
``sb3-sera train``, ``optimize``, ``enjoy`` and ``record-video``: the library's rl-zoo3 registration
(:mod:`sb3_sera.zoo`), its evaluations recording the initial-state value bias, argument checks, then the zoo's own
``train``, ``enjoy`` and ``record_video`` with the package's ``hyperparams/<algo>.yml`` as the default
``--conf-file``; ``train`` with the run engine's checkpoints, from which the same command line resumes an
interrupted train (``_CheckpointedTrain``).
"""

import json
import os
import runpy
import shutil
import sys
from collections.abc import Callable, Sequence
from contextlib import nullcontext, suppress
from pathlib import Path
from typing import Any

import gymnasium as gym
from stable_baselines3.common.base_class import BaseAlgorithm

from sb3_sera.common.capabilities import capabilities
from sb3_sera.common.evaluation import InitialStateBiasCallback
from sb3_sera.zoo import register
from sera_study.defaults import ZOO_COMMANDS
from sera_study.registry import (
    HYPERPARAMS_DIR,
    ZOO_ALGOS,
    ZOO_ONLY_KEYS,
    accepted_hyperparams,
    algorithm_default,
    check_known,
    default_hyperparams,
    hyperparams_file,
)

#: The zoo commands that load a model only to run it
PLAYBACK_COMMANDS = ("enjoy", "record-video")
#: The package's off-policy algorithms (rl-zoo3's ``off_policy_algos``, which its enjoy and record-video load with a
#: one-transition replay buffer; that list is local to those commands, so :func:`playback_algos` does it for ours)
ZOO_OFF_POLICY_ALGOS = tuple(name for name, algo in ZOO_ALGOS.items() if capabilities(algo)["off_policy"])
#: The single-agent-only algorithms (no CTDE tasks)
SINGLE_AGENT_ALGOS = tuple(name for name, algo in ZOO_ALGOS.items() if not capabilities(algo)["multi_agent"])
#: The multi-agent-only algorithms (CTDE tasks alone)
MULTI_AGENT_ALGOS = tuple(name for name, algo in ZOO_ALGOS.items() if not capabilities(algo)["single_agent"])


def _with_small_buffer(algo_class: type[BaseAlgorithm]) -> type[BaseAlgorithm]:
    """``algo_class`` whose ``load`` makes a one-transition replay buffer unless ``buffer_size`` is given."""

    class Playback(algo_class):  # type: ignore[valid-type,misc]
        @classmethod
        def load(cls, path: Any, *args: Any, **kwargs: Any) -> BaseAlgorithm:
            return super().load(path, *args, **{"buffer_size": 1, **kwargs})

    Playback.__name__ = Playback.__qualname__ = algo_class.__name__
    return Playback


def playback_algos() -> dict[str, type[BaseAlgorithm]]:
    """
    The package's algorithms as rl-zoo3's ``enjoy`` and ``record-video`` load them: the off-policy ones with a
    one-transition replay buffer, as the zoo loads its own, instead of allocating the saved ``buffer_size``.
    """
    return {name: _with_small_buffer(algo) if name in ZOO_OFF_POLICY_ALGOS else algo for name, algo in ZOO_ALGOS.items()}


def register_with_zoo(command: str = "train") -> None:
    """
    Register the package's algorithms with rl-zoo3 (:func:`sb3_sera.zoo.register`), and make its evaluations also
    record the initial-state value bias (:class:`~sb3_sera.common.evaluation.InitialStateBiasCallback`); idempotent.

    :param command: the zoo command about to run; for ``enjoy`` and ``record-video`` the algorithms are those of
        :func:`playback_algos`
    """
    from rl_zoo3 import exp_manager, utils

    register()
    if command in PLAYBACK_COMMANDS:
        utils.ALGOS.update(playback_algos())
    exp_manager.EvalCallback = InitialStateBiasCallback  # type: ignore[misc]


def _flag_value(argv: Sequence[str], *names: str) -> str | None:
    for index, arg in enumerate(argv):
        if arg in names and index + 1 < len(argv):
            return argv[index + 1]
        for name in names:
            if arg.startswith(f"{name}="):
                return arg.split("=", 1)[1]
    return None


def zoo_argv(command: str, argv: Sequence[str]) -> list[str]:
    """
    The zoo's arguments for ``command``: ``optimize`` is ``train -optimize``, and ``train``/``optimize`` read the
    package's ``hyperparams/<algo>.yml`` where it has the task (``registry.hyperparams_file``) unless ``--conf-file``
    is given, with one torch thread (``OMP_NUM_THREADS`` where set) unless ``--num-threads`` is given.
    """
    args = list(argv)
    if command not in ZOO_COMMANDS:
        raise ValueError(f"Unknown zoo command {command!r}: expected one of {ZOO_COMMANDS}")
    if command == "optimize" and "-optimize" not in args and "--optimize-hyperparameters" not in args:
        args.append("-optimize")
    if command in ("train", "optimize"):
        if _flag_value(args, "--num-threads") is None:
            # One torch thread, as compare and bench give each run when runs fill the cores (OMP_NUM_THREADS wins):
            # torch's default, a thread per core, crawls beside other work (docs/guide/install.md, Threads)
            from_env = os.environ.get("OMP_NUM_THREADS", "")
            args += ["--num-threads", from_env if from_env.isdigit() and int(from_env) > 0 else "1"]
        algo = _flag_value(args, "--algo") or "ppo"
        env_id = _flag_value(args, "--env")
        check_algo_task(algo, env_id)
        args = safe_params(algo, args)
        if env_id is not None and _flag_value(args, "-conf", "--conf-file") is None:
            check_budget(algo, env_id, args)
        conf_file = hyperparams_file(algo, env_id)
        if _flag_value(args, "-conf", "--conf-file") is None and conf_file.parent == HYPERPARAMS_DIR:
            args += ["--conf-file", str(conf_file)]
    return args


PARAMS_FLAGS = ("-params", "--hyperparams")


def _params_items(args: Sequence[str]) -> tuple[int, int]:
    """Where the ``-params`` items lie in ``args``: ``(start, end)``, empty where there are none."""
    for index, arg in enumerate(args):
        if arg in PARAMS_FLAGS:
            end = index + 1
            while end < len(args) and not args[end].startswith("-"):
                end += 1
            return index + 1, end
    return len(args), len(args)


def params_overrides(args: Sequence[str]) -> dict[str, Any]:
    """
    The ``-params key:value`` items of a zoo command line, read without executing them: ``policy_kwargs`` by
    :func:`~sera_study.policy_kwargs.parse_policy_kwargs`, every other value as a Python literal or else
    as the string itself (``lin_3e-4``); ``ValueError`` naming an item without a colon.
    """
    from sera_study.policy_kwargs import parse_policy_kwargs, parse_value

    start, end = _params_items(args)
    overrides: dict[str, Any] = {}
    for item in args[start:end]:
        key, sep, value = item.partition(":")
        if not sep or not key:
            raise ValueError(f"-params item {item!r} is invalid: expected key:value (e.g. sera_alpha:0.3)")
        overrides[key] = parse_policy_kwargs(value) if key == "policy_kwargs" else parse_value(value)
    return overrides


def safe_params(algo: str, args: Sequence[str]) -> list[str]:
    """
    ``args`` with each ``-params`` item rewritten as the literal it was read as (:func:`params_overrides`): rl-zoo3
    passes every value to ``eval``, which then rebuilds the value and can run nothing else. Keys the algorithm does not
    take are refused first, with the nearest allowed name.
    """
    overrides = params_overrides(args)
    if not overrides:
        return list(args)
    allowed = accepted_hyperparams(algo) | set(ZOO_ONLY_KEYS) | {"n_timesteps"}
    check_known(algo, overrides, allowed, "-params")
    start, end = _params_items(args)
    items = []
    for item in args[start:end]:
        key, _, text = item.partition(":")
        # policy_kwargs stay as their checked text: only literals, dict(...) and the allowed torch names
        items.append(f"{key}:{text if key == 'policy_kwargs' else repr(overrides[key])}")
    return [*args[:start], *items, *args[end:]]


def check_budget(algo: str, env_id: str, args: Sequence[str]) -> None:
    """``ValueError`` where ``learning_starts`` (the task's entry, then ``-params``) reaches the budget of the run."""
    entry, _ = default_hyperparams(algo, env_id)
    settings = {**entry, **params_overrides(args)}
    flag = _flag_value(args, "-n", "--n-timesteps")
    budget = int(flag) if flag is not None and int(flag) > 0 else settings.get("n_timesteps")
    starts = settings.get("learning_starts", algorithm_default(algo, "learning_starts"))
    if budget is not None and isinstance(starts, int | float) and starts >= float(budget):
        steps = int(float(budget))
        raise ValueError(
            f"{algo} on {env_id}: learning_starts={starts} is at or above the budget n_timesteps={steps}: the run would "
            f"train nothing; lower learning_starts (e.g. -params learning_starts:{max(steps // 10, 1)}) or raise the budget"
        )


def check_algo_task(algo: str, env_id: str | None) -> None:
    """
    ``ValueError`` for an algorithm on a task of the other kind (IET on a single-agent task, SUNRISE or ACE on a
    multi-agent one), naming the tasks it takes, before rl-zoo3 would only say that no hyperparameters were found.
    """
    if env_id is None:
        return
    multi_agent = env_id.startswith("sb3_sera/")
    tasks = sorted(name for name in gym.registry if name.startswith("sb3_sera/"))
    if algo in MULTI_AGENT_ALGOS and not multi_agent:
        raise ValueError(f"{algo} is multi-agent only: train it on a CTDE task ({', '.join(tasks)}), not {env_id}")
    if algo in SINGLE_AGENT_ALGOS and multi_agent:
        raise ValueError(f"{algo} is single-agent only: train it on a Gymnasium task (HalfCheetah-v5, ...), not {env_id}")


#: The zoo command line a train's run folder records, to be told apart from another command's run
ZOO_COMMAND_FILE = "sb3_sera_command.json"
#: Our own flag of ``sb3-sera train``, taken out before rl-zoo3 reads the rest
CHECKPOINT_FLAG = "--checkpoint-freq"


def _take_checkpoint_freq(args: list[str]) -> tuple[list[str], int]:
    """``args`` without :data:`CHECKPOINT_FLAG` and its value, and that value (the default where it is absent)."""
    from sera_study.checkpoint import CHECKPOINT_FREQ

    value = _flag_value(args, CHECKPOINT_FLAG)
    if value is None:
        return args, CHECKPOINT_FREQ
    if not value.isdigit():
        raise ValueError(f"{CHECKPOINT_FLAG}={value!r} is invalid: expected the steps between checkpoints, 0 for none")
    index = next(i for i, arg in enumerate(args) if arg == CHECKPOINT_FLAG or arg.startswith(f"{CHECKPOINT_FLAG}="))
    return [*args[:index], *args[index + (1 if "=" in args[index] else 2) :]], int(value)


def _resumable_run(args: Sequence[str]) -> Path | None:
    """
    The run folder of ``sb3-sera train`` with these arguments that was interrupted after a checkpoint: the task's
    latest run under the log folder, where it recorded the same command line and still holds its checkpoint (a
    finished run's is removed); None where there is none.
    """
    from rl_zoo3.utils import get_latest_run_id

    from sera_study.checkpoint import has_checkpoint
    from sera_study.records import env_name

    env_id = _flag_value(args, "--env") or "CartPole-v1"
    runs = Path(_flag_value(args, "-f", "--log-folder") or "logs") / (_flag_value(args, "--algo") or "ppo")
    latest = runs / f"{env_name(env_id)}_{get_latest_run_id(str(runs), env_name(env_id))}"
    record = latest / ZOO_COMMAND_FILE
    if not (record.exists() and has_checkpoint(latest)):
        return None
    return latest if json.loads(record.read_text()) == list(args) else None


class _CheckpointedTrain:
    """
    rl-zoo3's train with the run engine's checkpoints (every ``every`` steps, 0: none) in its run folder, resuming an
    interrupted run of the same command line (:func:`_resumable_run`) from its last one instead of starting anew: to
    the same final parameters, evaluations and monitor rows as a run never interrupted. Used as a context manager,
    it patches rl-zoo3's ``ExperimentManager`` while the train runs.
    """

    PATCHED = ("__init__", "create_envs", "setup_experiment", "learn")

    def __init__(self, args: list[str], every: int) -> None:
        from rl_zoo3.exp_manager import ExperimentManager

        self.args, self.every = args, every
        self.resume = _resumable_run(args) if every > 0 else None
        self.manager = ExperimentManager
        self.originals = {name: getattr(ExperimentManager, name) for name in self.PATCHED}

    def __enter__(self) -> None:
        for name in self.PATCHED:
            setattr(self.manager, name, getattr(self, f"_{name.strip('_')}")())

    def __exit__(self, *exc_info: Any) -> None:
        for name, method in self.originals.items():
            setattr(self.manager, name, method)

    def _init(self) -> Callable[..., None]:
        def init(manager: Any, *args: Any, **kwargs: Any) -> None:
            self.originals["__init__"](manager, *args, **kwargs)
            if self.resume is not None:
                manager.save_path = str(self.resume)
                manager.params_path = f"{manager.save_path}/{manager.env_name}"

        return init

    def _create_envs(self) -> Callable[..., Any]:
        def create_envs(manager: Any, n_envs: int, eval_env: bool = False, no_log: bool = False) -> Any:
            # A resumed run's monitor file is reopened by its checkpoint, never started again
            no_log = no_log or self.resume is not None
            return self.originals["create_envs"](manager, n_envs, eval_env=eval_env, no_log=no_log)

        return create_envs

    def _setup_experiment(self) -> Callable[..., Any]:
        from sera_study.checkpoint import Checkpointer, checkpoint_step, load_checkpoint

        def setup_experiment(manager: Any) -> Any:
            result = self.originals["setup_experiment"](manager)
            if result is None or self.every <= 0:
                return result
            model, saved = result
            folder = Path(manager.save_path)
            (folder / ZOO_COMMAND_FILE).write_text(json.dumps(self.args))
            evaluation = next((c for c in manager.callbacks if isinstance(c, InitialStateBiasCallback)), None)
            elapsed = 0.0
            if self.resume is not None:
                print(f"Resuming {folder} from its checkpoint at step {checkpoint_step(folder)}", file=sys.stderr)
                model, elapsed = load_checkpoint(type(model), folder, manager.device, model.env, evaluation)

            def make_envs() -> tuple[Any, Any]:
                return manager.create_envs(model.n_envs, no_log=True), manager.create_envs(manager.n_eval_envs, eval_env=True)

            task = manager.env_name.gym_id
            manager.callbacks.append(Checkpointer(folder, self.every, evaluation, make_envs, task, elapsed))
            return model, saved

        return setup_experiment

    def _learn(self) -> Callable[..., None]:
        from sera_study.checkpoint import checkpoint_step, remove_checkpoints

        def learn(manager: Any, model: Any) -> None:
            if self.every <= 0 or manager.algo == "ars":
                self.originals["learn"](manager, model)
                return
            # rl-zoo3's learn, on from a resumed run's step to the budget the command names
            kwargs: dict[str, Any] = {"callback": manager.callbacks}
            if manager.log_interval > -1:
                kwargs["log_interval"] = manager.log_interval
            elif manager.log_interval < -1:
                kwargs["log_interval"] = None
            done, folder = model.num_timesteps, Path(manager.save_path)
            try:
                model.learn(manager.n_timesteps - done, reset_num_timesteps=done == 0, **kwargs)
            except KeyboardInterrupt:
                # As rl-zoo3: the model is saved after this; and the same command resumes from the checkpoint
                step = checkpoint_step(folder)
                where = f"resumes it from step {step}" if step is not None else "starts it again (no checkpoint yet)"
                print(f"Interrupted: the same command {where} in {folder}", file=sys.stderr)
            else:
                remove_checkpoints(folder)
            finally:
                if manager.callbacks:
                    manager.callbacks[0].on_training_end()
                with suppress(EOFError):  # as rl-zoo3: a subprocess env may be gone already
                    model.env.close()

        return learn


def run_zoo(command: str, argv: Sequence[str]) -> None:
    """
    Run rl-zoo3's ``command`` (train, enjoy, record-video, optimize) with the package's algorithms. ``train`` also
    takes :data:`CHECKPOINT_FLAG` (default every 10,000 steps, 0: none): checkpoints of the run engine in the run's
    folder, from which the same command line resumes an interrupted run (``_CheckpointedTrain``).
    """
    register_with_zoo(command)
    from rl_zoo3.enjoy import enjoy
    from rl_zoo3.train import train

    def record_video() -> None:
        # rl-zoo3 keeps this one in its module's __main__ block
        runpy.run_module("rl_zoo3.record_video", run_name="__main__")

    entry_points: dict[str, Callable[[], None]] = {
        "train": train,
        "optimize": train,
        "enjoy": enjoy,
        "record-video": record_video,
    }
    args = zoo_argv(command, argv)
    every = 0
    if command == "train":
        args, every = _take_checkpoint_freq(args)
    saved = sys.argv
    sys.argv = [f"sb3-sera {command}", *args]
    # A train that fails before its first evaluation or model leaves no run folder behind
    log_folder = Path(_flag_value(args, "-f", "--log-folder") or "logs")
    runs = log_folder / (_flag_value(args, "--algo") or "ppo")
    made = [folder for folder in (log_folder, runs) if not folder.exists()]
    before = set(runs.iterdir()) if runs.is_dir() else set()
    try:
        with _CheckpointedTrain(args, every) if command == "train" else nullcontext():
            entry_points[command]()
    except BaseException:
        if command in ("train", "optimize") and runs.is_dir():
            for folder in set(runs.iterdir()) - before:
                if folder.is_dir() and not any(folder.glob("*.zip")) and not any(folder.glob("evaluations.npz")):
                    shutil.rmtree(folder, ignore_errors=True)
            # and the log and algorithm folders it made, where they stayed empty
            for folder in reversed(made):
                with suppress(OSError):
                    folder.rmdir()
        raise
    finally:
        sys.argv = saved
