"""
``sb3-sera train``, ``optimize``, ``enjoy`` and ``record-video``: the library's rl-zoo3 registration
(:mod:`sb3_sera.zoo`), its evaluations recording the initial-state value bias, argument checks, then the zoo's own
``train``, ``enjoy`` and ``record_video`` with the package's ``hyperparams/<algo>.yml`` as the default
``--conf-file``. A run that must resume to the same bits goes through the run engine (``compare``, ``bench``).
"""

import os
import runpy
import shutil
import sys
from collections.abc import Callable, Sequence
from contextlib import suppress
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
    :func:`~sera_study.runs.policy_kwargs.parse_policy_kwargs`, every other value as a Python literal or else
    as the string itself (``lin_3e-4``); ``ValueError`` naming an item without a colon.
    """
    from sera_study.runs.policy_kwargs import parse_policy_kwargs, parse_value

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


def run_zoo(command: str, argv: Sequence[str]) -> None:
    """
    Run rl-zoo3's ``command`` (train, enjoy, record-video, optimize) with the package's algorithms: rl-zoo3's own,
    which saves the model when Ctrl-C stops a train.
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
    saved = sys.argv
    sys.argv = [f"sb3-sera {command}", *args]
    # A train that fails before its first evaluation or model leaves no run folder behind
    log_folder = Path(_flag_value(args, "-f", "--log-folder") or "logs")
    runs = log_folder / (_flag_value(args, "--algo") or "ppo")
    made = [folder for folder in (log_folder, runs) if not folder.exists()]
    before = set(runs.iterdir()) if runs.is_dir() else set()
    try:
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
