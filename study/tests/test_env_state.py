"""An environment's state as plain data: captured, written into a new environment, refused where it cannot be."""

import copy
import pickle
import threading

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium.envs.classic_control.pendulum import PendulumEnv

from sera_study.registry import algorithm_classes
from sera_study.runs import engine
from sera_study.runs.checkpoint import CHECKPOINT_DIR, checkpoint_dir, has_checkpoint
from sera_study.runs.env_state import (
    StateMismatch,
    StateNotCapturable,
    capture,
    dump_data,
    load_data,
    restore,
    state_difference,
)
from sera_study.runs.folders import SET_ASIDE_FILE, assign_folders
from sera_study.runs.specs import make_spec


class Part:
    def __init__(self, seed: int) -> None:
        self.position = np.zeros(3)
        self.count = 0
        self.rng = np.random.default_rng(seed)
        self.log: list[float] = []
        self.owner: object | None = None
        self.act = print  # code, not state


class Toy:
    def __init__(self, seed: int) -> None:
        self.parts = [Part(seed), Part(seed + 1)]
        self.by_name = {"first": self.parts[0]}  # the same object twice
        self.parts[1].owner = self  # a cycle
        self.view = self.parts[0].position[:2]  # a view of another's array
        self.lazy: np.random.Generator | None = None  # made at the first reset

    def step(self) -> None:
        for part in self.parts:
            part.position += part.rng.normal(size=3)
            part.count += 1
            part.log.append(float(part.position[0]))
        if self.lazy is None:
            self.lazy = np.random.default_rng(7)
        self.parts[0].count += int(self.lazy.integers(10))


def test_a_state_goes_back_into_an_object_built_anew_and_goes_on_the_same():
    toy = Toy(0)
    for _ in range(5):
        toy.step()
    state = capture(toy)
    fresh = Toy(123)
    restore(fresh, state)
    assert state_difference(state, capture(fresh)) is None
    assert fresh.parts[0].count == toy.parts[0].count and fresh.parts[1].log == toy.parts[1].log
    # The view still sees its array, the shared object is one object, the cycle holds
    assert np.shares_memory(fresh.view, fresh.parts[0].position) and fresh.by_name["first"] is fresh.parts[0]
    assert fresh.parts[1].owner is fresh and fresh.parts[0].act is print
    for _ in range(3):
        toy.step(), fresh.step()
    assert all(np.array_equal(a.position, b.position) for a, b in zip(toy.parts, fresh.parts, strict=True))
    assert state_difference(capture(toy), capture(fresh)) is None


def test_the_first_difference_between_two_states_is_named_by_attribute():
    toy, other = Toy(0), Toy(0)
    other.parts[1].count = 4
    assert state_difference(capture(toy), capture(other)) == "env.parts[1].count"


def test_state_outside_python_is_refused_naming_where_it_is():
    toy = Toy(0)
    toy.parts[1].guard = threading.Lock()
    with pytest.raises(StateNotCapturable, match=r"env\.parts\[1\]\.guard is a _thread\.lock, which cannot be"):
        capture(toy)


def test_a_state_written_into_an_object_laid_out_otherwise_names_where():
    state = capture(Toy(0))
    fresh = Toy(0)
    fresh.parts.append(Part(3))
    with pytest.raises(StateMismatch, match=r"env\.parts: the saved state needs 2 items there, the environment has 3"):
        restore(fresh, state)
    fresh = Toy(0)
    fresh.parts[1] = Toy(0)  # a Toy where a Part was
    with pytest.raises(StateMismatch, match=r"env\.parts\[1\]: the saved state needs a Part there, the .* has a study\.tests"):
        restore(fresh, state)


def test_the_data_files_hold_no_class(tmp_path):
    path = tmp_path / "state.pkl"
    state = capture(Toy(0))
    dump_data(state, path)
    assert state_difference(load_data(path), state) is None
    with pytest.raises(pickle.UnpicklingError, match="not plain data"):
        dump_data(Part(0), path)
    path.write_bytes(pickle.dumps(Part(0)))  # as the pickled environments of earlier checkpoints were
    with pytest.raises(pickle.UnpicklingError, match=r"study\.tests\.test_env_state\.Part is not plain data"):
        load_data(path)


class LockedPendulum(PendulumEnv):
    """Pendulum with a lock among its attributes: state no checkpoint can write as data."""

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self.guard = threading.Lock()


gym.register("tests/LockedPendulum-v0", entry_point=LockedPendulum, max_episode_steps=200)
OVERRIDES = {"learning_starts": 100, "batch_size": 32, "buffer_size": 1000, "policy_kwargs": {"net_arch": [16]}}


def _spec(env_id: str, checkpoint_freq: int):
    spec = make_spec("sac", "sac", env_id, seed=0, n_timesteps=400, overrides=OVERRIDES, eval_freq=200, n_eval_episodes=1)
    spec.device, spec.checkpoint_freq = "cpu", checkpoint_freq
    return spec


def test_a_task_whose_state_cannot_be_saved_trains_on_without_checkpoints_and_says_why(tmp_path):
    spec = _spec("tests/LockedPendulum-v0", 100)
    (folder,) = assign_folders([spec], tmp_path)
    with pytest.warns(UserWarning, match=r"tests/LockedPendulum-v0: this run takes no checkpoints.*\.guard is a _thread"):
        engine.train_one(spec, folder)
    assert (folder / "result.json").exists() and not has_checkpoint(folder)


def _parameters(folder, spec) -> dict[str, th.Tensor]:
    model = algorithm_classes()[spec.algo].load(folder / "Pendulum-v1.zip", device="cpu")
    return copy.deepcopy(model.policy.state_dict())


def _stop_at_310(self) -> bool:
    if self.num_timesteps >= 310:
        raise KeyboardInterrupt
    return True


def test_a_run_whose_checkpoint_cannot_be_loaded_is_kept_aside_and_starts_again(tmp_path, monkeypatch, capsys):
    straight = _spec("Pendulum-v1", 0)
    (whole,) = assign_folders([straight], tmp_path / "straight")
    engine.train_one(straight, whole)
    spec = _spec("Pendulum-v1", 100)
    (folder,) = assign_folders([spec], tmp_path / "out")
    # Stopped after its checkpoint at step 300, as by a kill
    with monkeypatch.context() as patch:
        patch.setattr(engine.Checkpointer, "_on_step", _stop_at_310)
        with pytest.raises(KeyboardInterrupt):
            engine.train_one(spec, folder)
    assert has_checkpoint(folder) and not (folder / "result.json").exists()
    monitor_rows = (folder / "0.monitor.csv").read_text()
    state = checkpoint_dir(folder) / "state.pkl"
    state.write_bytes(pickle.dumps(Part(0)))  # a checkpoint that names a class
    engine.train_one(spec, folder)
    aside = folder.with_name(f"{folder.name}.unresumable-UnpicklingError")
    said = capsys.readouterr().err
    assert f"{folder}: not resumed: its checkpoint cannot be loaded (UnpicklingError: " in said and aside.name in said
    assert "resumed from step" not in said
    # Nothing is lost: the old run's checkpoint, monitor rows and reason kept; the run made again from step 0
    assert (aside / CHECKPOINT_DIR / "state.pkl").exists() and (aside / "0.monitor.csv").read_text() == monitor_rows
    assert "is not plain data" in (aside / SET_ASIDE_FILE).read_text()
    first, second = _parameters(whole, straight), _parameters(folder, spec)
    assert all(th.equal(first[name], second[name]) for name in first)
