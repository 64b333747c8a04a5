"""True resume: a run interrupted at a random step continues from its last checkpoint to the same final parameters."""

import copy
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
import torch as th
from stable_baselines3.common.callbacks import BaseCallback

from sb3_sera.common.device_buffer import DeviceReplayBuffer
from sera_study.records import load_result
from sera_study.registry import algorithm_classes
from sera_study.runs import engine
from sera_study.runs.checkpoint import CHECKPOINT_DIR, _buffer_arrays, _restore_buffer, has_checkpoint
from sera_study.runs.folders import assign_folders
from sera_study.runs.specs import make_spec
from tests.common.test_device_buffer import ACTION, OBSERVATION, _fill
from tests.helpers import CTDE_TASK


class _Stop(BaseCallback):
    """Stands in for a kill: raises KeyboardInterrupt at a given step."""

    at = 0

    def __init__(self, *args, **kwargs) -> None:
        super().__init__()

    def _on_step(self) -> bool:
        if self.num_timesteps >= _Stop.at:
            raise KeyboardInterrupt
        return True


def _parameters(folder, spec) -> dict[str, th.Tensor]:
    model = algorithm_classes()[spec.algo].load(folder / f"{spec.env_id.replace('/', '-')}.zip", device="cpu")
    return copy.deepcopy(model.policy.state_dict())


#: Small networks of each algorithm's kind (the zoo's are [256, 256]): a resume restores the same state whatever its sizes
SMALL_NETWORKS = {
    "serasac": "dict(net_arch=[32, 32], critic_archs=[[32, 32], [32], [48], [32, 32], [48]])",
    "masac": "dict(net_arch=[32, 32])",
    "iet": "dict(net_arch=[32, 32], hidden_dim=16)",
    "sunrise": "dict(net_arch=[32, 32])",
    "ace": "dict(feature_dim=32, hidden=16, n_actors=3)",
    "mappo": "dict(net_arch=[32, 32])",
    "tqc": "dict(net_arch=[32, 32], n_quantiles=5)",
    "crossq": "dict(net_arch=[32, 32])",
    # SERASAC with CrossQ's critics: batch renormalization's running statistics and step counts, no target critics
    "serasac_crossq": "dict(net_arch=[32, 32], critic_archs=[[32, 32], [32], [48]], n_critics=3, batch_norm=True)",
}
#: The rest of each algorithm's small settings: an off-policy run starts learning at step 100, MAPPO's rollouts of 64
#: steps end past the 400-step budget (at 448), which the run stops at
SMALL_SETTINGS = {
    "sunrise": {"n_members": 3},
    "mappo": {"n_steps": 64, "batch_size": 32, "n_epochs": 2},
}
#: Steps a rollout of each algorithm collects before its updates (off-policy: one); a checkpoint is taken as a rollout
#: starts
ROLLOUT = {"mappo": 64}


def _last_checkpoint(stop: int, rollout: int, every: int = 100) -> int:
    """
    The step of the last checkpoint before a kill at step ``stop``: the first rollout start at or past each multiple of
    ``every``, among the rollouts started before the kill (the step that reaches ``stop`` ends the rollout it is in, so
    a checkpoint due as the next one starts is never taken)
    """
    starts = range(0, stop, rollout)
    return max(min(start for start in starts if start >= mark) for mark in range(every, starts[-1] + 1, every))


@pytest.mark.parametrize(
    ("stop", "rollout", "expected"),
    [(300, 1, 200), (301, 1, 300), (256, 64, 128), (257, 64, 256), (320, 64, 256), (321, 64, 320), (369, 64, 320)],
)
def test_the_last_checkpoint_before_a_kill_by_hand(stop, rollout, expected):
    assert _last_checkpoint(stop, rollout) == expected


@pytest.mark.parametrize(
    ("variant", "env_id"),
    [
        ("serasac", "Pendulum-v1"),
        ("serasac_crossq", "Pendulum-v1"),
        ("masac", CTDE_TASK),
        ("iet", CTDE_TASK),
        ("sunrise", "Pendulum-v1"),
        ("ace", "Pendulum-v1"),
        ("mappo", CTDE_TASK),
        ("tqc", "Pendulum-v1"),
        ("crossq", "Pendulum-v1"),
    ],
)
def test_an_interrupted_run_resumes_to_the_same_final_parameters(tmp_path, monkeypatch, variant, env_id):
    algo = variant.split("_")[0]
    replay = {} if algo in ROLLOUT else {"learning_starts": 100, "batch_size": 32, "buffer_size": 2000}
    overrides = {**replay, **SMALL_SETTINGS.get(algo, {}), "policy_kwargs": SMALL_NETWORKS[variant]}
    spec = make_spec(variant, algo, env_id, seed=0, n_timesteps=400, overrides=overrides, eval_freq=150, n_eval_episodes=1)
    spec.device = "cpu"
    # Uninterrupted, without checkpoints
    whole = copy.deepcopy(spec)
    whole.checkpoint_freq = 0
    (straight,) = assign_folders([whole], tmp_path / "straight")
    engine.train_one(whole, straight)
    # Checkpoints every 100 steps, a kill at a random step between two of them, then the same run again
    spec.checkpoint_freq = 100
    (resumed,) = assign_folders([spec], tmp_path / "resumed")
    _Stop.at = int(np.random.default_rng().integers(230, 370))
    with monkeypatch.context() as patch:
        patch.setattr(engine, "ProgressFile", _Stop)
        with pytest.raises(KeyboardInterrupt):
            engine.train_one(spec, resumed)
    assert has_checkpoint(resumed) and not (resumed / "result.json").exists()
    engine.train_one(spec, resumed)
    first, second = _parameters(straight, spec), _parameters(resumed, spec)
    assert first.keys() == second.keys()
    for name in first:
        assert th.equal(first[name], second[name]), f"{name} differs after a kill at step {_Stop.at}"
    # Both stopped at the budget (MAPPO too, whose last rollout would end past it)
    model_class, name = algorithm_classes()[spec.algo], f"{spec.env_id.replace('/', '-')}.zip"
    assert [model_class.load(folder / name, device="cpu").num_timesteps for folder in (straight, resumed)] == [400, 400]
    # The same evaluations, the same training episodes in the monitor file, and no checkpoint left behind
    for name in ("evaluations.npz", "initial_state_bias.npz"):
        if name != "evaluations.npz" and not (straight / name).exists():  # ACE's critics record no initial-state bias
            assert not (resumed / name).exists()
            continue
        with np.load(straight / name) as a, np.load(resumed / name) as b:
            assert all(np.array_equal(a[key], b[key]) for key in a.files), name
    columns = ["r", "l"]
    monitors = [pd.read_csv(folder / "0.monitor.csv", skiprows=1)[columns] for folder in (straight, resumed)]
    assert monitors[0].equals(monitors[1])
    assert not (resumed / CHECKPOINT_DIR).exists()
    # The records say whether, from where and under which code a run was resumed
    (resume,) = load_result(resumed).resumes
    assert (
        resume["from_step"] == _last_checkpoint(_Stop.at, ROLLOUT.get(algo, 1))
        and resume["code_before"] == resume["code_after"]
    ), f"a kill at step {_Stop.at}"
    assert load_result(straight).resumes == [] and not (resumed / engine.RESUMES_FILE).exists()


_ENV_ACROSS_PROCESSES = """
import sys
from pathlib import Path
from stable_baselines3.common.env_util import make_vec_env
import sb3_sera  # the multi-agent task ids
from sera_study.runs.env_state import StateMismatch, capture, dump_data, load_data, restore
step, order, path = sys.argv[1], sys.argv[2], Path(sys.argv[3])
if order == "before":
    import rl_zoo3  # replaces Gymnasium's TimeLimit before MaMuJoCo wraps its inner env in it
env = make_vec_env("sb3_sera/HalfCheetah-6x1-v0", n_envs=1, seed=0)
import rl_zoo3  # after MaMuJoCo wrapped its inner env, where order is "after"
if step == "save":
    env.reset()
    for _ in range(995):
        env.step([env.action_space.sample()])
    dump_data(capture(env), path)
else:
    try:
        restore(env, load_data(path))
    except StateMismatch as error:
        sys.exit(f"mismatch: {error}")
    steps = [env.step([env.action_space.sample()])[2][0] for _ in range(10)]
    assert any(steps), "the episode should have ended"
"""


@pytest.mark.parametrize("order", ["before", "after"])
def test_a_mamujoco_env_state_is_data_that_a_new_process_restores_whenever_rl_zoo3_is_imported(tmp_path, order):
    # Saved in one process, restored in another into an env built the same way: the episode goes on, ends and resets
    script, saved = tmp_path / "env_across_processes.py", tmp_path / "env.pkl"
    script.write_text(_ENV_ACROSS_PROCESSES)
    for step in ("save", "load"):
        done = subprocess.run([sys.executable, str(script), step, order, str(saved)], capture_output=True, text=True)
        assert done.returncode == 0, done.stderr[-2000:]
    # An env built otherwise (Gymnasium's TimeLimit where rl-zoo3's was) is named, not restored into
    other = "after" if order == "before" else "before"
    done = subprocess.run([sys.executable, str(script), "load", other, str(saved)], capture_output=True, text=True)
    assert done.returncode == 1 and "mismatch: env.envs[0]" in done.stderr and "TimeLimit" in done.stderr


def test_a_checkpoint_keeps_a_device_buffers_transitions():
    buffer = DeviceReplayBuffer(8, OBSERVATION, ACTION, device="cpu")
    _fill(buffer, 5, 1)
    saved = _buffer_arrays(buffer)
    assert saved["arrays"]["observations"].shape == (5, 1, 3) and isinstance(saved["arrays"]["rewards"], np.ndarray)
    fresh = DeviceReplayBuffer(8, OBSERVATION, ACTION, device="cpu")
    _restore_buffer(fresh, saved)
    for name in ("observations", "next_observations", "actions", "rewards", "dones", "timeouts"):
        assert th.equal(getattr(fresh, name), getattr(buffer, name)), name
    assert (fresh.pos, fresh.full) == (buffer.pos, buffer.full)
