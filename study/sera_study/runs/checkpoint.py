"""
Resumable runs: a run of ``compare`` or ``bench`` saves a checkpoint every ``checkpoint_freq`` steps, and an
interrupted run continues from its last one, training on to the same final parameters as a run never interrupted.

A checkpoint (``<run>/checkpoint/``) is taken when a rollout starts, after the previous gradient steps, so that the
resumed ``learn()`` begins exactly where the interrupted one would have gone on. It holds:

- ``model.zip``: the model as ``save`` writes it (parameters, optimizers, the algorithm's own state such as SERA's
  step-size statistics);
- ``replay_buffer.pkl``: the filled part of the replay buffer and its position (not the empty capacity);
- ``state.pkl``: what ``save`` leaves out and a run needs to go on bit for bit, all of it plain data
  (:mod:`.env_state`: numbers, arrays and containers, never a class): the step count, the last observation and
  episode starts, the episode-info buffer, every random generator (Python's, NumPy's, torch's, the action space's),
  the state of the training and evaluation environments (each wrapper's counters, the monitor's episodes, the
  simulator's state, the envs' generators, the episode under way), the evaluation callback's records and the number
  of monitor rows written.

The checkpoint is written into ``checkpoint.partial/`` and renamed into place, so a kill leaves the previous one
whole. Resuming builds the environments anew with the run's own factories and writes their states into them; the
monitor file is cut back to the rows the checkpoint counted. A task whose state cannot be written as data, or does not
go back whole into a new environment, is found at the run's first checkpoint: the run goes on without checkpoints,
and a warning names the task and the reason.
"""

import random
import shutil
import time
import warnings
from collections.abc import Callable, Iterator
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.monitor import Monitor, ResultsWriter
from stable_baselines3.common.vec_env import VecEnv

from sb3_sera.common.capabilities import as_the_model_sees
from sera_study.defaults import CHECKPOINT_FREQ
from sera_study.runs.env_state import (
    StateNotCapturable,
    capture,
    check_round_trip,
    dump_data,
    load_data,
    preserved_global_generators,
    restore,
)

#: A checkpoint's step, in plain text
STEP_FILE = "step"
#: Checkpoints a run shorter than three times ``CHECKPOINT_FREQ`` takes by default (a short run resumes too)
SHORT_RUN_CHECKPOINTS = 3


def checkpoint_every(checkpoint_freq: int | None, n_timesteps: int) -> int:
    """
    Steps between a run's checkpoints: ``checkpoint_freq`` as given (0: none), or by default (None)
    ``CHECKPOINT_FREQ``, and a third of the budget where that is less, so that a run shorter than 30K steps also
    resumes from a checkpoint.
    """
    if checkpoint_freq is not None:
        return checkpoint_freq
    return max(1, min(CHECKPOINT_FREQ, n_timesteps // SHORT_RUN_CHECKPOINTS))


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


def _monitors(env: VecEnv) -> list[Monitor]:
    return [wrapper for wrapper in _walk_wrappers(env) if isinstance(wrapper, Monitor)]


def _walk_wrappers(env: Any) -> Iterator[Any]:
    for sub_env in getattr(env, "envs", []):
        while sub_env is not None:
            yield sub_env
            sub_env = getattr(sub_env, "env", None)


def _filled_part(value: Any, buffer: ReplayBuffer) -> np.ndarray | None:
    """A NumPy copy of the filled part of one of the buffer's arrays or tensors (a device buffer's); None for others."""
    if not isinstance(value, np.ndarray | th.Tensor) or value.shape[:1] != (buffer.buffer_size,):
        return None
    filled = buffer.buffer_size if buffer.full else buffer.pos
    return value[:filled].cpu().numpy().copy() if isinstance(value, th.Tensor) else value[:filled].copy()


def _buffer_arrays(buffer: ReplayBuffer) -> dict[str, Any]:
    """The buffer's arrays cut to their filled part (a dict observation: each key's), with its position."""
    arrays: dict[str, Any] = {}
    for name, value in vars(buffer).items():
        if isinstance(value, dict) and value:
            parts = {key: _filled_part(entry, buffer) for key, entry in value.items()}
            if all(part is not None for part in parts.values()):
                arrays[name] = parts
        elif (part := _filled_part(value, buffer)) is not None:
            arrays[name] = part
    return {"arrays": arrays, "pos": buffer.pos, "full": buffer.full}


def _write_filled_part(target: np.ndarray | th.Tensor, array: np.ndarray) -> None:
    if isinstance(target, th.Tensor):
        target[: len(array)] = th.from_numpy(array).to(target.device)
    else:
        target[: len(array)] = array


def _restore_buffer(buffer: ReplayBuffer, saved: dict[str, Any]) -> None:
    for name, value in saved["arrays"].items():
        target = getattr(buffer, name)
        if isinstance(value, dict):
            for key, array in value.items():
                _write_filled_part(target[key], array)
        else:
            _write_filled_part(target, value)
    buffer.pos, buffer.full = saved["pos"], saved["full"]


#: The names :func:`~.env_state.capture` gives the environments in messages
ENV_NAMES = ("env", "eval_env")


def save_checkpoint(
    model: BaseAlgorithm,
    folder: Path,
    callback: BaseCallback | None,
    elapsed_s: float,
    env_states: tuple[Any, Any] | None = None,
) -> Path:
    """
    Write the run's checkpoint (see the module's docstring) into ``folder/checkpoint``, replacing the last one.

    :param env_states: the states of the training and evaluation environments, when already captured
        (:func:`~.env_state.capture`); by default captured here
    :raises StateNotCapturable: where an environment's state cannot be written as data (nothing is written)
    """
    assert model.env is not None
    training, evaluation = env_states if env_states is not None else _env_states(model, callback)
    target = folder / CHECKPOINT_DIR
    partial = folder / f"{CHECKPOINT_DIR}.partial"
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir()
    model.save(partial / "model.zip")
    buffer = getattr(model, "replay_buffer", None)
    dump_data(None if buffer is None else _buffer_arrays(buffer), partial / "replay_buffer.pkl", check=False)
    state = {
        "model": {name: getattr(model, name, None) for name in MODEL_STATE},
        "ep_info_buffer": model.ep_info_buffer,
        "ep_success_buffer": model.ep_success_buffer,
        "random": random.getstate(),
        "numpy": np.random.get_state(legacy=False),
        "torch": th.get_rng_state().numpy(),
        "cuda": [state.numpy() for state in th.cuda.get_rng_state_all()] if th.cuda.is_available() else None,
        "action_space": model.action_space.np_random.bit_generator.state,
        "env": training,
        "callback": None if callback is None else {k: getattr(callback, k) for k in CALLBACK_STATE if hasattr(callback, k)},
        "eval_env": evaluation,
        "monitor_rows": [len(monitor.get_episode_rewards()) for monitor in _monitors(model.env)],
        "monitor_files": [
            None if monitor.results_writer is None else Path(monitor.results_writer.file_handler.name).name
            for monitor in _monitors(model.env)
        ],
        "elapsed_s": elapsed_s,
    }
    dump_data(state, partial / "state.pkl")
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


def _env_states(model: BaseAlgorithm, callback: BaseCallback | None) -> tuple[Any, Any]:
    evaluation = None if callback is None else capture(callback.eval_env, ENV_NAMES[1])  # type: ignore[attr-defined]
    return capture(model.env, ENV_NAMES[0]), evaluation


def checkpoint_dir(folder: Path) -> Path | None:
    """
    ``folder``'s whole checkpoint, or None: the last one, else (a kill while the next one replaced it) the one
    before it.
    """
    for name in (CHECKPOINT_DIR, f"{CHECKPOINT_DIR}.old"):
        if (folder / name / "state.pkl").exists():
            return folder / name
    return None


def remove_checkpoints(folder: Path) -> None:
    """Remove every checkpoint of ``folder``: the last, the one before it and one half-written (a finished run's)."""
    for name in (CHECKPOINT_DIR, f"{CHECKPOINT_DIR}.old", f"{CHECKPOINT_DIR}.partial"):
        shutil.rmtree(folder / name, ignore_errors=True)


def has_checkpoint(folder: Path) -> bool:
    """Whether ``folder`` holds a whole checkpoint."""
    return checkpoint_dir(folder) is not None


def checkpoint_stamp(folder: Path) -> str | None:
    """
    ``folder``'s whole checkpoint as a person reads it, "step 1,000, written 2026-11-27 07:02 UTC" (None: none).
    """
    source = checkpoint_dir(folder)
    if source is None:
        return None
    step = _recorded_step(source)
    written = datetime.fromtimestamp((source / "state.pkl").stat().st_mtime, timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    return f"{'an unrecorded step' if step is None else f'step {step:,}'}, written {written}"


def checkpoint_step(folder: Path) -> int | None:
    """The step of ``folder``'s whole checkpoint (None: none, or one written before its step was recorded)."""
    source = checkpoint_dir(folder)
    return None if source is None else _recorded_step(source)


def _recorded_step(source: Path) -> int | None:
    """The step a checkpoint folder records (None: none recorded, or not readable)."""
    try:
        return int((source / STEP_FILE).read_text())
    except (OSError, ValueError):
        return None


def load_checkpoint(
    model_class: type[BaseAlgorithm], folder: Path, device: str, env: VecEnv, callback: BaseCallback | None
) -> tuple[BaseAlgorithm, float]:
    """
    The model of ``folder``'s checkpoint with everything it needs to go on (see the module's docstring): the
    training environment's state written into ``env`` (built anew as the run built it, without monitor files: the
    run's are reopened, cut back to the checkpoint's rows), the evaluation callback's records and its environment's
    state into ``callback``.

    :return: the model, and the training time the run had spent up to the checkpoint
    :raises StateMismatch: where an environment is not laid out as the saved one was
    """
    source = checkpoint_dir(folder)
    if source is None:
        raise FileNotFoundError(f"{folder}: no whole checkpoint to resume from")
    state = load_data(source / "state.pkl")
    model = model_class.load(source / "model.zip", env=env, device=device)
    # Into the envs as the model sees them: a model acting on latents (IET) wraps them in its latents' env
    assert model.env is not None
    restore(model.env, state["env"], ENV_NAMES[0])
    if callback is not None and state["eval_env"] is not None:
        eval_env = as_the_model_sees(model, callback.eval_env)  # type: ignore[attr-defined]
        restore(eval_env, state["eval_env"], ENV_NAMES[1])
        callback.eval_env = eval_env  # type: ignore[attr-defined]
    buffer_state = load_data(source / "replay_buffer.pkl")
    if buffer_state is not None:
        _restore_buffer(model.replay_buffer, buffer_state)  # type: ignore[attr-defined]
    # Once nothing else can fail: a checkpoint that cannot be loaded leaves the monitor files whole
    for monitor, rows, name in zip(_monitors(env), state["monitor_rows"], state["monitor_files"], strict=True):
        _reopen_monitor(monitor, rows, None if name is None else folder / name)
    for name, value in state["model"].items():
        setattr(model, name, value)
    model.ep_info_buffer, model.ep_success_buffer = state["ep_info_buffer"], state["ep_success_buffer"]
    if callback is not None and state["callback"] is not None:
        for name, value in state["callback"].items():
            setattr(callback, name, value)
    # Generators last: loading the model seeds them again
    random.setstate(state["random"])
    np.random.set_state(state["numpy"])
    th.set_rng_state(th.from_numpy(state["torch"]))
    if state["cuda"] is not None and th.cuda.is_available():
        th.cuda.set_rng_state_all([th.from_numpy(cuda) for cuda in state["cuda"]])
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

    At its first checkpoint it checks that the environments' states go back whole into environments built anew by
    ``make_envs``: where they do not (or cannot be written as data), it warns once, naming the task and the reason,
    and takes no checkpoint in this run.

    :param folder: the run's folder
    :param evaluation: the run's evaluation callback, whose records the checkpoint keeps
    :param make_envs: builds a new training and evaluation environment as the run built its own (no monitor files)
    :param task: the run's task, for the warning
    :param elapsed_s: the training time spent before this ``learn()`` (a resumed run's)
    """

    def __init__(
        self,
        folder: Path,
        every: int,
        evaluation: BaseCallback | None,
        make_envs: Callable[[], tuple[VecEnv, VecEnv]],
        task: str,
        elapsed_s: float = 0.0,
    ) -> None:
        super().__init__()
        self.folder, self.every, self.evaluation = folder, every, evaluation
        self.make_envs, self.task = make_envs, task
        self.elapsed_s = elapsed_s
        self.checked = False
        self.refused: str | None = None
        self._next = 0
        self._started = 0.0

    def _on_training_start(self) -> None:
        self._started = time.perf_counter()
        self._next = (self.num_timesteps // self.every + 1) * self.every

    def _on_rollout_start(self) -> None:
        if self.refused is None and self.num_timesteps >= self._next:
            states = None if self.checked else self._checked_states()
            if self.refused is None:
                elapsed = self.elapsed_s + time.perf_counter() - self._started
                save_checkpoint(self.model, self.folder, self.evaluation, elapsed, states)
            self._next = (self.num_timesteps // self.every + 1) * self.every

    def _checked_states(self) -> tuple[Any, Any] | None:
        """The environments' states, checked to go back into new ones; None, with a warning, where they do not."""
        self.checked = True
        assert self.model.env is not None
        with preserved_global_generators():
            fresh = self.make_envs()
        try:
            training = check_round_trip(self.model.env, fresh[0], ENV_NAMES[0])
            evaluation = None
            if self.evaluation is not None:
                eval_env = self.evaluation.eval_env  # type: ignore[attr-defined]
                evaluation = check_round_trip(eval_env, fresh[1], ENV_NAMES[1])
        except StateNotCapturable as error:
            self.refused = str(error)
            warnings.warn(
                f"{self.task}: this run takes no checkpoints, so an interruption restarts it from step 0: the "
                f"environment's state cannot be saved as data ({error})",
                stacklevel=2,
            )
            return None
        finally:
            for env in fresh:
                env.close()
        return training, evaluation

    def _on_step(self) -> bool:
        return True
