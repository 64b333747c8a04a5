"""
Every algorithm stops on a non-finite value with a ``FloatingPointError`` that names it, before it changes the model:
from the env (reward, observation), in a replayed batch, in a rollout, in a loss or its gradient.
"""

import math
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from stable_baselines3 import DDPG, PPO, SAC, TD3
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback

from sb3_sera import IET, MADDPG, MAPPO, MASAC, MATD3, SERASAC, SUNRISE
from sb3_sera.ace import ACE
from sb3_sera.ctde.env import STATE_KEY
from tests.helpers import CTDE_TASK, ENV_ID

OFF_POLICY = dict(learning_starts=20, batch_size=16, buffer_size=500)
AT_STEP = 40


class NonFiniteAt(gym.Wrapper):
    """
    Gives a non-finite reward or observation entry at its ``at``-th step (counted over episodes), finite ones before.

    :param env: the env
    :param at: the step, from 1
    :param part: ``"reward"`` or ``"observation"`` (the first entry of the observation, or of its ``state``)
    :param value: the non-finite value
    """

    def __init__(self, env: gym.Env, at: int, part: str, value: float):
        super().__init__(env)
        self.at, self.part, self.value = at, part, value
        self.steps = 0

    def step(self, action: Any) -> tuple[Any, Any, bool, bool, dict[str, Any]]:
        observation, reward, terminated, truncated, info = self.env.step(action)
        self.steps += 1
        if self.steps == self.at:
            if self.part == "reward":
                reward = self.value
            elif isinstance(observation, dict):
                observation = {**observation, STATE_KEY: observation[STATE_KEY].copy()}
                observation[STATE_KEY][0] = self.value
            else:
                observation = observation.copy()
                observation[0] = self.value
        return observation, reward, terminated, truncated, info


def ctde(algo: type[BaseAlgorithm], **kwargs: Any) -> Callable[[gym.Env], BaseAlgorithm]:
    return lambda env: algo("CTDEPolicy", env, seed=0, **kwargs)


MODELS: dict[str, tuple[str, Callable[[gym.Env], BaseAlgorithm]]] = {
    "ACE": (
        ENV_ID,
        lambda env: ACE("MlpPolicy", env, seed=0, **OFF_POLICY, policy_kwargs=dict(feature_dim=16, hidden=8, n_actors=2)),
    ),
    "MASAC": (CTDE_TASK, ctde(MASAC, **OFF_POLICY, policy_kwargs=dict(net_arch=[16]))),
    "MATD3": (CTDE_TASK, ctde(MATD3, **OFF_POLICY, policy_kwargs=dict(net_arch=[16]))),
    "MADDPG": (CTDE_TASK, ctde(MADDPG, **OFF_POLICY, policy_kwargs=dict(net_arch=[16]))),
    "MAPPO": (CTDE_TASK, ctde(MAPPO, n_steps=32, batch_size=16, n_epochs=2, policy_kwargs=dict(net_arch=[16]))),
    "IET": (CTDE_TASK, ctde(IET, **OFF_POLICY, policy_kwargs=dict(net_arch=[16], hidden_dim=8))),
    "SERASAC": (CTDE_TASK, ctde(SERASAC, **OFF_POLICY, policy_kwargs=dict(n_critics=2, critic_archs=[[16], [16]]))),
    "SUNRISE": (ENV_ID, lambda env: SUNRISE("MlpPolicy", env, seed=0, n_members=2, **OFF_POLICY)),
}
OFF_POLICY_MODELS = ["ACE", "MASAC", "MATD3", "MADDPG", "IET"]


def model_state(model: BaseAlgorithm) -> dict[str, th.Tensor]:
    """Everything the model saves of its torch state (networks, buffers, optimizers, e.g. ``log_ent_coef``), flat."""
    state_dicts, variables = model._get_torch_save_params()
    flat: dict[str, th.Tensor] = {}

    def add(prefix: str, value: Any) -> None:
        if isinstance(value, th.Tensor):
            flat[prefix] = value.detach().clone()
        elif isinstance(value, dict):
            for key, item in value.items():
                add(f"{prefix}.{key}", item)
        elif isinstance(value, (list, tuple)):
            for index, item in enumerate(value):
                add(f"{prefix}.{index}", item)
        elif isinstance(value, (int, float)):
            flat[prefix] = th.tensor(value)

    for name in state_dicts:
        add(name, _getattr(model, name).state_dict())
    for name in variables:
        add(name, _getattr(model, name))
    return flat


def _getattr(obj: Any, dotted: str) -> Any:
    for name in dotted.split("."):
        obj = getattr(obj, name)
    return obj


def assert_unchanged_and_finite(before: dict[str, th.Tensor], after: dict[str, th.Tensor]) -> None:
    assert before.keys() == after.keys()
    for key, value in after.items():
        assert th.equal(before[key], value), key
        assert not value.is_floating_point() or bool(th.isfinite(value).all()), key


class Snapshot(BaseCallback):
    """The model's state when each rollout starts: what a failed rollout must leave as it was."""

    state: dict[str, th.Tensor]

    def _on_rollout_start(self) -> None:
        self.state = model_state(self.model)

    def _on_step(self) -> bool:
        return True


@pytest.mark.parametrize(
    ("part", "value"), [("reward", math.nan), ("reward", math.inf), ("observation", math.nan), ("observation", -math.inf)]
)
@pytest.mark.parametrize("name", MODELS)
def test_a_non_finite_value_from_the_env_stops_training_before_any_change(name, part, value):
    task, make = MODELS[name]
    model = make(NonFiniteAt(gym.make(task), AT_STEP, part, value))
    snapshot = Snapshot()
    named = "observation 'state'" if part == "observation" and task == CTDE_TASK else part
    with pytest.raises(
        FloatingPointError, match=rf"^Non-finite {named} from the env at num_timesteps={AT_STEP}: training stopped"
    ):
        model.learn(100, callback=snapshot)
    assert model.num_timesteps == AT_STEP and model._n_updates > 0
    assert_unchanged_and_finite(snapshot.state, model_state(model))


def trained(name: str) -> BaseAlgorithm:
    task, make = MODELS[name]
    return make(gym.make(task)).learn(30)


def poison(values: np.ndarray | dict[str, np.ndarray], value: float) -> None:
    """Put ``value`` in the first entry of each stored transition (of the ``state`` for CTDE observations)."""
    array = values[STATE_KEY] if isinstance(values, dict) else values
    array[..., 0] = value


@pytest.mark.parametrize(
    ("part", "named"), [("rewards", "reward"), ("observations", "observation"), ("next_observations", "next observation")]
)
@pytest.mark.parametrize("name", OFF_POLICY_MODELS)
def test_a_non_finite_replayed_batch_stops_the_gradient_step(name, part, named):
    model = trained(name)
    buffer = model.replay_buffer
    if part == "next_observations" and getattr(buffer, "optimize_memory_usage", False):
        pytest.skip("no next observations stored")
    poison(getattr(buffer, part), math.nan)
    before = model_state(model)
    steps = model._n_updates
    with pytest.raises(
        FloatingPointError, match=rf"^Non-finite {named}\b.* in the replayed batch at gradient step {steps + 1} "
    ):
        model.train(gradient_steps=2, batch_size=16)
    assert_unchanged_and_finite(before, model_state(model))


@pytest.mark.parametrize("name", OFF_POLICY_MODELS)
def test_an_overflowing_critic_loss_stops_before_the_critic_changes(name):
    # Finite rewards, but so large that the squared TD error overflows
    model = trained(name)
    model.replay_buffer.rewards[:] = 3e38
    before = model_state(model)
    with pytest.raises(FloatingPointError, match=r"^Non-finite (critic loss|(square of the )?gradient of the critic loss) at"):
        model.train(gradient_steps=1, batch_size=16)
    after = model_state(model)
    # SAC steps its entropy coefficient first (on a finite loss): the networks are untouched
    changed = {key for key in before if not th.equal(before[key], after[key])}
    assert changed <= {key for key in before if "ent_coef" in key}, changed
    assert all(not value.is_floating_point() or bool(th.isfinite(value).all()) for value in after.values())


def test_mappo_checks_the_rollout_and_the_gradient_before_the_update():
    task, make = MODELS["MAPPO"]
    model = make(gym.make(task)).learn(32)
    model.rollout_buffer.rewards[3] = math.nan
    before = model_state(model)
    rollout_message = r"^Non-finite reward in the rollout buffer before the update at num_timesteps=32"
    with pytest.raises(FloatingPointError, match=rollout_message):
        model.train()
    assert_unchanged_and_finite(before, model_state(model))
    # Finite parameters whose loss is not: a standard deviation exp(100) overflows, the entropy is inf
    model.rollout_buffer.rewards[3] = 0.0
    with th.no_grad():
        model.policy.log_std.fill_(100.0)
    before = model_state(model)
    with pytest.raises(FloatingPointError, match=r"^Non-finite gradient of the PPO loss at gradient step 1 of the update"):
        model.train()
    assert_unchanged_and_finite(before, model_state(model))


def test_ace_checks_observations_before_its_normalizer_learns_them():
    model = MODELS["ACE"][1](NonFiniteAt(gym.make(ENV_ID), 5, "observation", math.nan))
    with pytest.raises(FloatingPointError, match="Non-finite observation from the env at num_timesteps=5"):
        model.learn(10)
    normalizer = model.policy.network.normalizer
    assert normalizer is not None and normalizer.count.item() == pytest.approx(4, abs=1e-3)
    assert bool(th.isfinite(normalizer.mean).all() and th.isfinite(normalizer.var).all())


@pytest.mark.parametrize(
    ("algo", "sb3_algo", "kwargs"),
    [
        (MASAC, SAC, OFF_POLICY),
        (MATD3, TD3, OFF_POLICY),
        (MADDPG, DDPG, OFF_POLICY),
        (MAPPO, PPO, dict(n_steps=32, batch_size=16, n_epochs=2)),
    ],
    ids=lambda value: getattr(value, "__name__", ""),
)
def test_the_checks_change_nothing_training_computes(algo, sb3_algo, kwargs):
    # Ours (checks watching) and SB3's own algorithm on the same policy (no checks): the same parameters, bit for bit
    ours = algo("CTDEPolicy", gym.make(CTDE_TASK), seed=0, policy_kwargs=dict(net_arch=[16]), **kwargs).learn(100)
    policy_kwargs = dict(net_arch=[16], agent_action_dims=ours.policy.agent_action_dims)
    theirs = sb3_algo(type(ours.policy), gym.make(CTDE_TASK), seed=0, policy_kwargs=policy_kwargs, **kwargs).learn(100)
    assert ours._n_updates == theirs._n_updates > 0
    expected = model_state(theirs)
    for key, value in model_state(ours).items():
        assert th.equal(value, expected[key]), key
