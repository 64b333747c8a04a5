"""
Resumable runs: a run of ``compare`` or ``bench`` saves a checkpoint every ``checkpoint_freq`` steps, and an
interrupted run continues from its last one, training on to the same final parameters as a run never interrupted.

A checkpoint (``<run>/checkpoint/``) is taken when a rollout starts, after the previous gradient steps, so that the
resumed ``learn()`` begins exactly where the interrupted one would have gone on. It holds:

- ``model.zip``: the model as ``save`` writes it (parameters, optimizers, the algorithm's own state such as SERA's
  step-size statistics);
- ``replay_buffer.pkl``: the filled part of the replay buffer and its position (not the empty capacity);
- ``state.pkl``: what ``save`` leaves out and a run needs to go on bit for bit: the step count, the last
  observation and episode starts, the episode-info buffer, every random generator (Python's, NumPy's, torch's, the
  action space's), the training and evaluation environments with their state (the MuJoCo simulation, the envs'
  generators, the episode under way), the evaluation callback's records and the number of monitor rows written.

The checkpoint is written into ``checkpoint.partial/`` and renamed into place, so a kill leaves the previous one
whole. On resume the monitor file is cut back to the rows the checkpoint counted.
"""

import importlib
import io
import pickle
import random
import shutil
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cloudpickle
import numpy as np
import torch as th
from gymnasium.utils import EzPickle
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.monitor import Monitor, ResultsWriter
from stable_baselines3.common.vec_env import VecEnv

#: A checkpoint's step, in plain text
STEP_FILE = "step"
#: Steps between checkpoints by default: a 50K-step run keeps at most 10K steps of work at risk
CHECKPOINT_FREQ = 10_000
#: A run's checkpoint folder
CHECKPOINT_DIR = "checkpoint"
#: What of the model ``save`` leaves out that a run needs to go on
MODEL_STATE = ("num_timesteps", "_episode_num", "_last_obs", "_last_episode_starts", "_last_original_obs")
#: What of the evaluation callback a run needs to go on (its evaluations so far and its step count)
CALLBACK_STATE = (
    "n_calls",
    "evaluations_results",
    "evaluations_timesteps",
    "evaluations_length",
    "evaluations_successes",
    "_is_success_buffer",
    "best_mean_reward",
    "last_mean_reward",
    "diagnostics",
    "bias_timesteps",
    "bias_values",
    "bias_returns",
)


def _set_state(obj: Any, state: dict[str, Any]) -> None:
    obj.__dict__.update(state)


def _module_attribute(module: str, name: str) -> Any:
    return getattr(importlib.import_module(module), name)


def _rebound_class_reference(cls: type) -> tuple[str, str] | None:
    """
    Where a class rebound in its own module can still be found by name: ``(module, name)`` of a loaded module that
    holds it, or None when its module holds it (the usual case) or no module does.

    rl-zoo3 replaces ``gymnasium.wrappers.common.TimeLimit`` with its own subclass when imported; an env wrapped
    before that (MaMuJoCo's inner single-agent env) keeps Gymnasium's class, which its module no longer names.
    cloudpickle would pickle that class by value, and its methods by reference to Gymnasium's: a resumed process
    would then build a copy of the class whose ``reset`` fails in ``super()``. This reference keeps the class itself.
    """
    name = cls.__name__
    if "." in cls.__qualname__ or getattr(sys.modules.get(cls.__module__), name, None) is cls:
        return None
    for module_name, module in list(sys.modules.items()):
        if module is not None and getattr(module, name, None) is cls:
            return module_name, name
    return None


class _StatePickler(cloudpickle.Pickler):
    """
    Pickles environments with their state. Gymnasium's and PettingZoo's envs pickle as ``EzPickle`` (their
    constructor's arguments: a new, unstarted env); this pickler writes their attributes instead (the MuJoCo
    simulation, the random generator, the episode under way), leaving out pygame's rendering surfaces. A class
    rebound in its module is pickled by where it is still found (:func:`_rebound_class_reference`).
    """

    def reducer_override(self, obj: Any) -> Any:
        if isinstance(obj, EzPickle):
            state = {k: None if type(v).__module__.startswith("pygame") else v for k, v in vars(obj).items()}
            return object.__new__, (type(obj),), state, None, None, _set_state
        if isinstance(obj, type):
            reference = _rebound_class_reference(obj)
            if reference is not None:
                return _module_attribute, reference
        return super().reducer_override(obj)


def _monitors(env: VecEnv) -> list[Monitor]:
    return [wrapper for wrapper in _walk_wrappers(env) if isinstance(wrapper, Monitor)]


def _walk_wrappers(env: Any) -> Iterator[Any]:
    for sub_env in getattr(env, "envs", []):
        while sub_env is not None:
            yield sub_env
            sub_env = getattr(sub_env, "env", None)


def _pickle_env(env: VecEnv) -> bytes:
    """The environment pickled with its state (:class:`_StatePickler`), its monitors' files left out."""
    monitors = _monitors(env)
    writers = [monitor.results_writer for monitor in monitors]
    for monitor in monitors:
        monitor.results_writer = None
    try:
        data = io.BytesIO()
        _StatePickler(data, protocol=pickle.HIGHEST_PROTOCOL).dump(env)
        return data.getvalue()
    finally:
        for monitor, writer in zip(monitors, writers, strict=True):
            monitor.results_writer = writer


def _buffer_arrays(buffer: ReplayBuffer) -> dict[str, Any]:
    """The buffer's arrays cut to their filled part (a dict observation: each key's), with its position."""
    filled = buffer.buffer_size if buffer.full else buffer.pos
    arrays: dict[str, Any] = {}
    for name, value in vars(buffer).items():
        if isinstance(value, np.ndarray) and value.shape[:1] == (buffer.buffer_size,):
            arrays[name] = value[:filled].copy()
        elif isinstance(value, dict) and value and all(isinstance(v, np.ndarray) for v in value.values()):
            arrays[name] = {key: array[:filled].copy() for key, array in value.items()}
    return {"arrays": arrays, "pos": buffer.pos, "full": buffer.full}


def _restore_buffer(buffer: ReplayBuffer, saved: dict[str, Any]) -> None:
    for name, value in saved["arrays"].items():
        target = getattr(buffer, name)
        if isinstance(value, dict):
            for key, array in value.items():
                target[key][: len(array)] = array
        else:
            target[: len(value)] = value
    buffer.pos, buffer.full = saved["pos"], saved["full"]


def save_checkpoint(model: BaseAlgorithm, folder: Path, callback: BaseCallback | None, elapsed_s: float) -> Path:
    """Write the run's checkpoint (see the module's docstring) into ``folder/checkpoint``, replacing the last one."""
    target = folder / CHECKPOINT_DIR
    partial = folder / f"{CHECKPOINT_DIR}.partial"
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir()
    model.save(partial / "model.zip")
    buffer = getattr(model, "replay_buffer", None)
    with (partial / "replay_buffer.pkl").open("wb") as handle:
        pickle.dump(None if buffer is None else _buffer_arrays(buffer), handle, protocol=pickle.HIGHEST_PROTOCOL)
    assert model.env is not None
    state = {
        "model": {name: getattr(model, name, None) for name in MODEL_STATE},
        "ep_info_buffer": model.ep_info_buffer,
        "ep_success_buffer": model.ep_success_buffer,
        "random": random.getstate(),
        "numpy": np.random.get_state(),
        "torch": th.get_rng_state(),
        "cuda": th.cuda.get_rng_state_all() if th.cuda.is_available() else None,
        "action_space": model.action_space.np_random.bit_generator.state,
        "env": _pickle_env(model.env),
        "callback": None if callback is None else {k: getattr(callback, k) for k in CALLBACK_STATE if hasattr(callback, k)},
        "eval_env": None if callback is None else _pickle_env(callback.eval_env),  # type: ignore[attr-defined]
        "monitor_rows": [len(monitor.get_episode_rewards()) for monitor in _monitors(model.env)],
        "monitor_files": [
            None if monitor.results_writer is None else Path(monitor.results_writer.file_handler.name).name
            for monitor in _monitors(model.env)
        ],
        "elapsed_s": elapsed_s,
    }
    with (partial / "state.pkl").open("wb") as handle:
        cloudpickle.dump(state, handle, protocol=pickle.HIGHEST_PROTOCOL)
    # The step in plain text, for what a command says of the run without loading it
    (partial / STEP_FILE).write_text(str(model.num_timesteps))
    if target.exists():
        old = folder / f"{CHECKPOINT_DIR}.old"
        shutil.rmtree(old, ignore_errors=True)
        target.rename(old)
        partial.rename(target)
        shutil.rmtree(old)
    else:
        partial.rename(target)
    return target


def checkpoint_dir(folder: Path) -> Path | None:
    """
    ``folder``'s whole checkpoint, or None: the last one, else (a kill while the next one replaced it) the one
    before it.
    """
    for name in (CHECKPOINT_DIR, f"{CHECKPOINT_DIR}.old"):
        if (folder / name / "state.pkl").exists():
            return folder / name
    return None


def has_checkpoint(folder: Path) -> bool:
    """Whether ``folder`` holds a whole checkpoint."""
    return checkpoint_dir(folder) is not None


def checkpoint_step(folder: Path) -> int | None:
    """The step of ``folder``'s whole checkpoint (None: none, or one written before its step was recorded)."""
    source = checkpoint_dir(folder)
    try:
        return None if source is None else int((source / STEP_FILE).read_text())
    except (OSError, ValueError):
        return None


def load_checkpoint(
    model_class: type[BaseAlgorithm], folder: Path, device: str, callback: BaseCallback | None
) -> tuple[BaseAlgorithm, float]:
    """
    The model of ``folder``'s checkpoint with everything it needs to go on (see the module's docstring), the
    evaluation callback's records and environment restored into ``callback``, and the monitor files cut back to
    the checkpoint's rows.

    :return: the model, and the training time the run had spent up to the checkpoint
    """
    source = checkpoint_dir(folder)
    if source is None:
        raise FileNotFoundError(f"{folder}: no whole checkpoint to resume from")
    with (source / "state.pkl").open("rb") as handle:
        state = pickle.load(handle)
    env = pickle.loads(state["env"])
    for monitor, rows, name in zip(_monitors(env), state["monitor_rows"], state["monitor_files"], strict=True):
        _reopen_monitor(monitor, rows, None if name is None else folder / name)
    model = model_class.load(source / "model.zip", env=env, device=device)
    with (source / "replay_buffer.pkl").open("rb") as handle:
        buffer_state = pickle.load(handle)
    if buffer_state is not None:
        _restore_buffer(model.replay_buffer, buffer_state)  # type: ignore[attr-defined]
    for name, value in state["model"].items():
        setattr(model, name, value)
    model.ep_info_buffer, model.ep_success_buffer = state["ep_info_buffer"], state["ep_success_buffer"]
    if callback is not None and state["callback"] is not None:
        for name, value in state["callback"].items():
            setattr(callback, name, value)
        callback.eval_env = pickle.loads(state["eval_env"])  # type: ignore[attr-defined]
    # Generators last: loading the model seeds them again
    random.setstate(state["random"])
    np.random.set_state(state["numpy"])
    th.set_rng_state(state["torch"])
    if state["cuda"] is not None and th.cuda.is_available():
        th.cuda.set_rng_state_all(state["cuda"])
    model.action_space.np_random.bit_generator.state = state["action_space"]
    return model, float(state["elapsed_s"])


def _reopen_monitor(monitor: Monitor, rows: int, path: Path | None) -> None:
    """Cut the monitor's file back to its header and ``rows`` episodes, and write on after them."""
    if path is None:
        return
    lines = path.read_text().splitlines(keepends=True)
    path.write_text("".join(lines[: 2 + rows]))
    # Appending: the file keeps its header lines, the writer adds rows only
    monitor.results_writer = ResultsWriter(
        str(path), extra_keys=monitor.reset_keywords + monitor.info_keywords, override_existing=False
    )


class Checkpointer(BaseCallback):
    """
    Saves a checkpoint every ``every`` steps, when a rollout starts (after the previous gradient steps).

    :param folder: the run's folder
    :param evaluation: the run's evaluation callback, whose records the checkpoint keeps
    :param elapsed_s: the training time spent before this ``learn()`` (a resumed run's)
    """

    def __init__(self, folder: Path, every: int, evaluation: BaseCallback | None, elapsed_s: float = 0.0) -> None:
        super().__init__()
        self.folder, self.every, self.evaluation = folder, every, evaluation
        self.elapsed_s = elapsed_s
        self._next = 0
        self._started = 0.0

    def _on_training_start(self) -> None:
        self._started = time.perf_counter()
        self._next = (self.num_timesteps // self.every + 1) * self.every

    def _on_rollout_start(self) -> None:
        if self.num_timesteps >= self._next:
            save_checkpoint(self.model, self.folder, self.evaluation, self.elapsed_s + time.perf_counter() - self._started)
            self._next = (self.num_timesteps // self.every + 1) * self.every

    def _on_step(self) -> bool:
        return True
