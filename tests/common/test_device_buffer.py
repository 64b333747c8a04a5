"""The replay buffers on the device: SB3's buffers' contents and samples, their save/load, their refusals, and models
training with them (compiled and eager, single- and multi-agent)."""

import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import DictReplayBuffer, ReplayBuffer
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecNormalize

from sb3_sera import MASAC, SERASAC, SUNRISE
from sb3_sera.common.device_buffer import DeviceDictReplayBuffer, DeviceReplayBuffer, device_buffer_class
from sb3_sera.sunrise.buffers import SUNRISEDeviceReplayBuffer, SUNRISEReplayBuffer
from tests.helpers import COMPILED_CTDE_TASK, COMPILED_GROUP, ENV_ID, SMALL, compiled_settings

OBSERVATION = spaces.Box(-10, 10, (3,), dtype=np.float32)
ACTION = spaces.Box(-1, 1, (2,), dtype=np.float32)


def _fill(buffer, n_transitions: int, n_envs: int) -> None:
    """Transition ``t`` of env ``e``: observation ``10 t + e``, next ``10 t + e + 1``, action ``-(10 t + e)``, reward
    ``t + e / 10``, done for odd ``t``, a timeout where ``t`` is a multiple of 3."""
    for t in range(n_transitions):
        base = 10.0 * t + np.arange(n_envs, dtype=np.float32)
        buffer.add(
            np.repeat(base[:, None], 3, axis=1),
            np.repeat(base[:, None] + 1, 3, axis=1),
            -np.repeat(base[:, None], 2, axis=1),
            t + np.arange(n_envs) / 10,
            np.full(n_envs, t % 2, dtype=np.float32),
            [{"TimeLimit.truncated": t % 3 == 0} for _ in range(n_envs)],
        )


def test_holds_what_sb3s_buffer_holds_and_samples_whole_transitions():
    sb3 = ReplayBuffer(8, OBSERVATION, ACTION, device="cpu", n_envs=2)
    ours = DeviceReplayBuffer(8, OBSERVATION, ACTION, device="cpu", n_envs=2)
    # 6 transitions in a buffer of 4 per env: it wraps, as SB3's does
    _fill(sb3, 6, 2)
    _fill(ours, 6, 2)
    assert (ours.pos, ours.full, ours.size()) == (sb3.pos, sb3.full, sb3.size()) == (2, True, 4)
    for name in ("observations", "next_observations", "actions", "rewards", "dones", "timeouts"):
        assert isinstance(getattr(ours, name), th.Tensor)
        np.testing.assert_array_equal(getattr(ours, name).numpy(), getattr(sb3, name), err_msg=name)
    th.manual_seed(0)
    sample = ours.sample(64)
    assert sample.observations.shape == (64, 3) and sample.rewards.shape == sample.dones.shape == (64, 1)
    # Each row is one stored transition: its parts agree (t and e read back from the observation)
    t, e = (sample.observations[:, 0] // 10).long(), (sample.observations[:, 0] % 10).long()
    assert set(t.tolist()) <= {2, 3, 4, 5} and set(e.tolist()) == {0, 1}
    assert th.equal(sample.next_observations, sample.observations + 1)
    assert th.equal(sample.actions, -sample.observations[:, :2])
    assert th.allclose(sample.rewards[:, 0], t + e / 10)
    # A done that is a timeout is not a termination (t = 3: done and timeout)
    assert th.equal(sample.dones[:, 0], ((t % 2 == 1) & (t % 3 != 0)).float())


def test_draws_with_torchs_generator_and_a_calls_batches_at_once():
    buffer = DeviceReplayBuffer(100, OBSERVATION, ACTION, device="cpu")
    _fill(buffer, 40, 1)
    th.manual_seed(3)
    batches = buffer.sample_batches(3, 5)
    th.manual_seed(3)
    again = buffer.sample_batches(3, 5)
    assert [batch.observations.shape for batch in batches] == [(5, 3)] * 3
    assert all(th.equal(a.observations, b.observations) for a, b in zip(batches, again, strict=True))
    th.manual_seed(3)
    one = buffer.sample(15)
    assert th.equal(th.cat([batch.observations for batch in batches]), one.observations)


def test_dict_observations_as_sb3s_dict_buffer():
    space = spaces.Dict({"state": OBSERVATION, "agent": spaces.Discrete(4)})
    sb3 = DictReplayBuffer(4, space, ACTION, device="cpu")
    ours = DeviceDictReplayBuffer(4, space, ACTION, device="cpu")
    assert isinstance(ours, DictReplayBuffer) and device_buffer_class(space) is DeviceDictReplayBuffer
    for t in range(3):
        obs = {"state": np.full((1, 3), t, np.float32), "agent": np.array([t])}
        next_obs = {"state": np.full((1, 3), t + 1, np.float32), "agent": np.array([t + 1])}
        for buffer in (sb3, ours):
            buffer.add(dict(obs), dict(next_obs), np.zeros((1, 2)), np.array([t]), np.array([0.0]), [{}])
    for key in ("state", "agent"):
        np.testing.assert_array_equal(ours.observations[key].numpy(), sb3.observations[key])
        np.testing.assert_array_equal(ours.next_observations[key].numpy(), sb3.next_observations[key])
    sample = ours.sample(16)
    assert sample.observations["agent"].dtype == th.int64 and sample.observations["state"].shape == (16, 3)
    assert th.equal(sample.next_observations["agent"], sample.observations["agent"] + 1)


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: DeviceReplayBuffer(8, OBSERVATION, ACTION, optimize_memory_usage=True), r"optimize_memory_usage=True"),
        (lambda: DeviceDictReplayBuffer(8, OBSERVATION, ACTION), r"needs a Dict observation space"),
        (lambda: DeviceReplayBuffer(8, OBSERVATION, ACTION, device="cpu").sample(2), r"is empty: add transitions"),
    ],
)
def test_refuses_what_it_does_not_support(call, message):
    with pytest.raises((ValueError, TypeError), match=message):
        call()


def test_a_model_with_vecnormalize_is_refused_naming_the_alternative():
    env = VecNormalize(make_vec_env(ENV_ID, n_envs=1, seed=0))
    with pytest.raises(ValueError, match=r"does not support VecNormalize.*replay_buffer_class=ReplayBuffer"):
        SERASAC("MlpPolicy", env, replay_buffer_class=DeviceReplayBuffer, compile_update=True, **SMALL)


def test_serasac_learns_saves_and_reloads_its_device_buffer(tmp_path):
    # Compiled: tests/sera/test_serasac_compiled_step.py
    model = SERASAC("MlpPolicy", ENV_ID, replay_buffer_class=DeviceReplayBuffer, seed=0, **SMALL)
    model.learn(150)
    assert isinstance(model.replay_buffer, DeviceReplayBuffer) and model.replay_buffer.size() == 150
    assert all(th.isfinite(param).all() for param in model.policy.parameters())
    model.save_replay_buffer(tmp_path / "buffer")
    stored = model.replay_buffer.observations.clone()
    model.replay_buffer = None
    model.load_replay_buffer(tmp_path / "buffer")
    assert isinstance(model.replay_buffer, DeviceReplayBuffer) and model.replay_buffer.device == model.device
    assert th.equal(model.replay_buffer.observations, stored) and model.replay_buffer.size() == 150
    model.learn(60, reset_num_timesteps=False)
    assert model.replay_buffer.size() == 210


@COMPILED_GROUP["ctde"]
def test_masac_compiled_learns_from_a_dict_device_buffer():
    buffer_class = DeviceDictReplayBuffer
    settings = compiled_settings("ctde")
    model = MASAC("CTDEPolicy", COMPILED_CTDE_TASK, replay_buffer_class=buffer_class, compile_update=True, seed=0, **settings)
    model.learn(120)
    assert isinstance(model.replay_buffer, DeviceDictReplayBuffer) and model.logger.name_to_value["train/critic_loss"] != 0


def test_the_default_buffer_is_on_the_device_only_for_cuda_graphs():
    model = SERASAC("MlpPolicy", ENV_ID, compile_update="reduce-overhead", device="cpu", **SMALL)
    # On a CPU "reduce-overhead" runs as True, and SB3's buffer serves
    assert type(model.replay_buffer) is ReplayBuffer
    if th.cuda.is_available():
        model = SERASAC("MlpPolicy", ENV_ID, compile_update="reduce-overhead", device="cuda", **SMALL)
        assert type(model.replay_buffer) is DeviceReplayBuffer and model.replay_buffer.device.type == "cuda"


@COMPILED_GROUP["sunrise"]
def test_sunrise_keeps_its_bootstrap_masks_on_the_device_and_learns_compiled(tmp_path):
    # The masks drawn as SUNRISE's own buffer draws them (NumPy's generator), stored and sampled with each transition
    host = SUNRISEReplayBuffer(8, OBSERVATION, ACTION, device="cpu", n_envs=2, n_members=3)
    device = SUNRISEDeviceReplayBuffer(8, OBSERVATION, ACTION, device="cpu", n_envs=2, n_members=3)
    for buffer in (host, device):
        np.random.seed(0)
        _fill(buffer, 6, 2)
    np.testing.assert_array_equal(device.masks.numpy(), host.masks)
    # Each sampled row's masks are its transition's (t and e read back from the observation)
    for batch in device.sample_batches(2, 32):
        t, e = (batch.observations[:, 0] // 10).long(), (batch.observations[:, 0] % 10).long()
        assert th.equal(batch.masks, device.masks[t % 4, e])
    with pytest.raises(ValueError, match="SUNRISEDeviceReplayBuffer"):
        SUNRISE("MlpPolicy", ENV_ID, replay_buffer_class=DeviceReplayBuffer)
    buffer_class, settings = SUNRISEDeviceReplayBuffer, compiled_settings("sunrise")
    model = SUNRISE("MlpPolicy", ENV_ID, replay_buffer_class=buffer_class, compile_update=True, seed=0, **settings)
    assert SUNRISE("MlpPolicy", ENV_ID, **SMALL).replay_buffer_class is SUNRISEReplayBuffer
    assert model._device_buffer_class() is SUNRISEDeviceReplayBuffer  # the default for CUDA graphs on CUDA
    model.learn(120)
    assert model.logger.name_to_value["train/critic_loss"] != 0
    model.save_replay_buffer(tmp_path / "buffer")
    masks = model.replay_buffer.masks.clone()
    model.load_replay_buffer(tmp_path / "buffer")
    assert isinstance(model.replay_buffer, SUNRISEDeviceReplayBuffer) and th.equal(model.replay_buffer.masks, masks)
