"""
The agents' actors as one stacked network: the actions, log-probabilities and gradients of one SB3 actor per agent on
every registered task, shared parameters, and models saved with one actor per agent loading into it.
"""

from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from torch import nn

from sb3_sera import MADDPG, MASAC, MATD3, SERASAC
from sb3_sera.ctde.actors import CTDEActor, StackedCTDEActor
from sb3_sera.ctde.policies import MASACPolicy, MATD3Policy
from sb3_sera.ctde.tasks import TASKS
from sb3_sera.sera.policies import SERACTDEPolicy
from tests.helpers import SMALL_CTDE, assert_close_state, snapshot

#: Every registered task, the generic MaMuJoCo id at a layout whose agents differ in observation and action sizes
TASK_KWARGS: dict[str, dict[str, Any]] = {env_id: {} for env_id in TASKS}
TASK_KWARGS["sb3_sera/MaMuJoCo-v0"] = dict(scenario="Ant", agent_conf="2x4d")


def _observations(env: gym.Env, n: int = 6) -> dict[str, th.Tensor]:
    """A batch of ``n`` observations of ``env`` along a random walk."""
    env.action_space.seed(0)
    observation, _ = env.reset(seed=0)
    seen = []
    for _ in range(n):
        seen.append(observation)
        observation, _, terminated, truncated, _ = env.step(env.action_space.sample())
        if terminated or truncated:
            observation, _ = env.reset()
    return {key: th.as_tensor(np.stack([o[key] for o in seen])) for key in seen[0]}


def _agent_gradients(actor: StackedCTDEActor, agent_actors: dict[str, nn.Module]) -> list[tuple[th.Tensor, th.Tensor]]:
    """Each agent's gradient pairs (its SB3 actor's, the stacked network's share of it), layer by layer."""
    pairs = []
    for index, agent in enumerate(actor.agents):
        row = 0 if actor.share_parameters else index
        layers = [m for m in agent_actors[agent].modules() if isinstance(m, nn.Linear)]
        for stacked, layer in zip(actor.stacked_layers(), layers, strict=True):
            assert stacked.weight.grad is not None and layer.weight.grad is not None
            share = stacked.weight.grad[row, : layer.in_features, : layer.out_features]
            pairs.append((layer.weight.grad.T, share))
            pairs.append((layer.bias.grad, stacked.bias.grad[row, 0, : layer.out_features]))
    return pairs


@pytest.mark.parametrize("env_id", sorted(TASK_KWARGS))
@pytest.mark.parametrize("algo", [MASAC, MATD3], ids=["sac-actor", "td3-actor"])
def test_the_stacked_actors_act_and_learn_as_one_actor_per_agent(env_id, algo):
    env = gym.make(env_id, **TASK_KWARGS[env_id])
    model = algo("CTDEPolicy", env, seed=0, policy_kwargs=dict(net_arch=[16, 8]), **SMALL_CTDE)
    actor = model.actor
    assert isinstance(actor, StackedCTDEActor)
    obs = _observations(env)
    random_state = th.get_rng_state()
    agent_actors = {agent: actor.agent_actor(agent) for agent in actor.agents}
    # The agents' SB3 actors are made without a draw from torch's generator
    assert th.equal(th.get_rng_state(), random_state)
    if algo is MASAC:
        th.manual_seed(3)
        actions, log_prob = actor.action_log_prob(obs)
        th.manual_seed(3)
        parts = [agent_actors[agent].action_log_prob(obs[agent]) for agent in actor.agents]
        expected = th.cat([part[0] for part in parts], dim=1), th.stack([part[1] for part in parts]).sum(dim=0)
        loss, expected_loss = (a.square().sum() + p.sum() for a, p in ((actions, log_prob), expected))
        th.testing.assert_close(actions, expected[0])
        th.testing.assert_close(log_prob, expected[1], rtol=1e-5, atol=1e-4)
        # Deterministic: the squashed means
        means = th.cat([agent_actors[agent](obs[agent], deterministic=True) for agent in actor.agents], dim=1)
        th.testing.assert_close(actor(obs, deterministic=True), means)
    else:
        actions = actor(obs)
        expected_actions = th.cat([agent_actors[agent](obs[agent]) for agent in actor.agents], dim=1)
        th.testing.assert_close(actions, expected_actions)
        loss, expected_loss = actions.square().sum(), expected_actions.square().sum()
    loss.backward()
    expected_loss.backward()
    for expected_grad, grad in _agent_gradients(actor, agent_actors):
        th.testing.assert_close(grad, expected_grad, rtol=1e-4, atol=1e-5)
    # The padded weights get no gradient
    n_inputs = [actor.input_dims[i] for i in range(len(actor.agents))]
    first = actor.stacked_layers()[0]
    assert first.weight.grad is not None
    for index, size in enumerate(n_inputs):
        assert not first.weight.grad[index, size:, :].any()


def test_shared_parameters_run_every_agent_through_one_network():
    env = gym.make("sb3_sera/SimpleSpread-v0")
    model = MASAC("CTDEPolicy", env, seed=0, policy_kwargs=dict(net_arch=[16], share_actor=True), **SMALL_CTDE)
    actor = model.actor
    assert all(layer.weight.shape[0] == 1 for layer in actor.stacked_layers())
    obs = _observations(env)
    shared = actor.agent_actor(actor.agents[0])
    th.manual_seed(5)
    actions, log_prob = actor.action_log_prob(obs)
    th.manual_seed(5)
    parts = [shared.action_log_prob(obs[agent]) for agent in actor.agents]
    th.testing.assert_close(actions, th.cat([part[0] for part in parts], dim=1))
    th.testing.assert_close(log_prob, th.stack([part[1] for part in parts]).sum(dim=0), rtol=1e-5, atol=1e-4)
    (actions.sum() + log_prob.sum()).backward()
    sum(part[0].sum() + part[1].sum() for part in parts).backward()
    for stacked, layer in zip(actor.stacked_layers(), [m for m in shared.modules() if isinstance(m, nn.Linear)], strict=True):
        th.testing.assert_close(stacked.weight.grad[0], layer.weight.grad.T, rtol=1e-4, atol=1e-5)


def test_the_stacked_network_refuses_actors_it_cannot_stack():
    env = gym.make("sb3_sera/SimpleSpread-v0")
    with pytest.raises(ValueError, match=r"StackedCTDEActor stacks .* got Linear: use CTDEActor"):
        StackedCTDEActor(env.observation_space, env.action_space, {"agent_0": 2}, nn.Linear, {})  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("algo", "policy_class", "policy_kwargs"),
    [
        (MASAC, MASACPolicy, {}),
        (MATD3, MATD3Policy, {}),
        (MADDPG, MATD3Policy, {}),
        (SERASAC, SERACTDEPolicy, {}),
        (MASAC, MASACPolicy, {"share_actor": True}),
    ],
    ids=["masac", "matd3", "maddpg", "serasac", "masac-shared"],
)
def test_a_model_saved_with_one_actor_per_agent_loads_stacked(algo, policy_class, policy_kwargs, tmp_path, monkeypatch):
    env_id = "sb3_sera/SimpleSpread-v0" if policy_kwargs.get("share_actor") else "sb3_sera/Pusher-3p-v0"
    # A model of sb3-sera 0.1.0: one SB3 actor per agent, trained so that its optimizers hold Adam states
    with monkeypatch.context() as patch:
        patch.setattr(policy_class, "ctde_actor_class", CTDEActor)
        old = algo("CTDEPolicy", env_id, seed=0, policy_kwargs=dict(net_arch=[16], **policy_kwargs), **SMALL_CTDE)
        assert not isinstance(old.actor, StackedCTDEActor)
        old.learn(SMALL_CTDE["learning_starts"] + 20)
        old.save(tmp_path / "old")
    loaded = algo.load(tmp_path / "old", env=gym.make(env_id))
    assert isinstance(loaded.actor, StackedCTDEActor)
    obs = _observations(gym.make(env_id))
    with th.no_grad():
        th.testing.assert_close(loaded.actor(obs, deterministic=True), old.actor(obs, deterministic=True))
    # Adam's moments, stacked as the parameters are: the same optimizer steps follow
    for agent in loaded.actor.agents:
        agent_actor = loaded.actor.agent_actor(agent)
        old_agent = old.actor.agent_actor(agent)
        for new, before in zip(agent_actor.parameters(), old_agent.parameters(), strict=True):
            th.testing.assert_close(new, before)
    old_state = old.actor.optimizer.state_dict()["state"]
    new_state = loaded.actor.optimizer.state_dict()["state"]
    owners = 1 if policy_kwargs.get("share_actor") else len(loaded.actor.agents)
    assert len(old_state) == owners * len(new_state)
    first = loaded.actor.stacked_layers()[0]
    layer = next(m for m in old.actor.agent_actor(old.actor.agents[-1]).modules() if isinstance(m, nn.Linear))
    moment = new_state[0]["exp_avg"][owners - 1, : layer.in_features, : layer.out_features]
    th.testing.assert_close(moment, old_state[(owners - 1) * len(new_state)]["exp_avg"].T)
    assert new_state[0]["exp_avg"].shape == first.weight.shape
    loaded.learn(20, reset_num_timesteps=False)
    # A stacked model saves and loads as it is
    loaded.save(tmp_path / "new")
    again = algo.load(tmp_path / "new", env=gym.make(env_id))
    assert_close_state(snapshot(loaded, optimizers=True), snapshot(again, optimizers=True))


def test_the_same_seed_gives_the_per_agent_actors_initial_weights(monkeypatch):
    stacked = MASAC("CTDEPolicy", "sb3_sera/Pusher-3p-v0", seed=0, **SMALL_CTDE)
    monkeypatch.setattr(MASACPolicy, "ctde_actor_class", CTDEActor)
    loop = MASAC("CTDEPolicy", "sb3_sera/Pusher-3p-v0", seed=0, **SMALL_CTDE)
    for agent in loop.actor.agents:
        for new, old in zip(
            stacked.actor.agent_actor(agent).parameters(), loop.actor.agent_actor(agent).parameters(), strict=True
        ):
            assert th.equal(new, old)
    # Nothing more is drawn: the critics built after the actors start where they did
    for key, value in loop.critic.state_dict().items():
        assert th.equal(stacked.critic.state_dict()[key], value), key
