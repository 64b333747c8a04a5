"""The CTDE policies and algorithms: decentralized actors, centralized critics, training, save/load, execution."""

import copy
import inspect
import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from sb3_contrib import TQC

from sb3_sera import MADDPG, MAPPO, MASAC, MATD3, SERASAC
from sb3_sera.ctde.algorithms import _CTDEAlgorithm, _sb3_algorithm, _sb3_train_signature
from sb3_sera.ctde.env import STATE_KEY, with_agent_indicator
from sb3_sera.ctde.execution import DecentralizedActors
from sb3_sera.ctde.tasks import mamujoco_parallel_env
from tests.helpers import SMALL_CTDE

ALGORITHMS = {
    SERASAC: SMALL_CTDE,
    MASAC: SMALL_CTDE,
    MATD3: SMALL_CTDE,
    MADDPG: SMALL_CTDE,
    MAPPO: dict(n_steps=64, batch_size=32, n_epochs=2),
}


def batch(observation: dict[str, np.ndarray]) -> dict[str, th.Tensor]:
    return {key: th.as_tensor(value).unsqueeze(0) for key, value in observation.items()}


@pytest.mark.parametrize("algo", ALGORITHMS, ids=lambda algo: algo.__name__)
def test_train_save_load_predict(algo, tmp_path):
    model = algo("CTDEPolicy", "sb3_sera/SimpleSpread-v0", seed=0, **ALGORITHMS[algo]).learn(200)
    observation = model.env.reset()
    actions, _ = model.predict(observation, deterministic=True)
    model.save(tmp_path / "model")
    loaded = algo.load(tmp_path / "model", env=gym.make("sb3_sera/SimpleSpread-v0"))
    np.testing.assert_array_equal(loaded.predict(observation, deterministic=True)[0], actions)
    loaded.learn(100, reset_num_timesteps=False)


@pytest.mark.parametrize("algo", ALGORITHMS, ids=lambda algo: algo.__name__)
def test_decentralized_controllers(algo, tmp_path):
    model = algo("CTDEPolicy", "sb3_sera/Pusher-3p-v0", seed=0, **ALGORITHMS[algo]).learn(64)
    env = gym.make("sb3_sera/Pusher-3p-v0").unwrapped
    observation, _ = env.reset(seed=3)
    joint, _ = model.predict(observation, deterministic=True)
    controllers = DecentralizedActors.from_model(model)
    local = {agent: observation[agent] for agent in env.agents}
    actions = controllers(local)
    np.testing.assert_allclose(np.concatenate([actions[agent] for agent in env.agents]), joint, atol=1e-5)
    for agent, action in actions.items():
        assert env.agent_action_spaces[agent].contains(action)
    controllers.save(tmp_path / "controllers")
    # Tensors only: a weights_only load reads them
    saved = [th.load(path, weights_only=True) for path in (tmp_path / "controllers").glob("*.pth")]
    assert len(saved) == 3 and not any("critic" in key or "value" in key for state in saved for key in state)
    assert all(isinstance(tensor, th.Tensor) for state in saved for tensor in state.values())
    reloaded = DecentralizedActors.load(tmp_path / "controllers")
    for agent, action in reloaded(local).items():
        np.testing.assert_array_equal(action, actions[agent])
    # agents.json is strict JSON (no Infinity): the unbounded observation spaces' bounds are strings that read back
    text = (tmp_path / "controllers" / "agents.json").read_text()
    layout = json.loads(text, parse_constant=lambda name: pytest.fail(f"agents.json holds {name}"))["agents"]
    assert '"-inf"' in text and all(np.isinf(actor.observation_space.low).all() for actor in reloaded.actors.values())
    assert layout["agent_0"]["arguments"]["observation_space"]["box"]["low"][0] == "-inf"


class _WritesMarker:
    """What a crafted weights file unpickles to: an object whose unpickling runs code (here: creates a file)."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def test_loading_controllers_runs_no_code_from_the_files(tmp_path):
    model = MASAC("CTDEPolicy", "sb3_sera/SimpleSpread-v0", seed=0, **SMALL_CTDE)
    folder = tmp_path / "controllers"
    DecentralizedActors.from_model(model).save(folder)
    marker = tmp_path / "marker"
    # A crafted actor_0.pth: unpickling it would create the marker file
    th.save({"state_dict": _WritesMarker(marker)}, folder / "actor_0.pth")
    with pytest.raises(ValueError, match=r"actor_0\.pth.*not a weights-only file"):
        DecentralizedActors.load(folder)
    assert not marker.exists()
    # agents.json cannot point outside the folder nor name a class
    DecentralizedActors.from_model(model).save(folder)
    saved = json.loads((folder / "agents.json").read_text())

    def write_agent_0(**changes):
        agents = {**saved["agents"], "agent_0": {**saved["agents"]["agent_0"], **changes}}
        (folder / "agents.json").write_text(json.dumps({**saved, "agents": agents}))

    for field, value, message in (
        ("file", "../actor_0.pth", r"file='\.\./actor_0\.pth' is invalid"),
        ("kind", "pickle", r"kind='pickle' is invalid: expected one of"),
        ("arguments", {**saved["agents"]["agent_0"]["arguments"], "activation_fn": {"module": "os.system"}}, "os.system"),
    ):
        write_agent_0(**{field: value})
        with pytest.raises(ValueError, match=message):
            DecentralizedActors.load(folder)
    # Controllers saved before the format held no pickle are refused with the way out
    (folder / "agents.json").write_text(json.dumps(saved["agents"]))
    with pytest.raises(ValueError, match=r"format=None, expected 2.*DecentralizedActors.from_model\(model\).save"):
        DecentralizedActors.load(folder)


@pytest.mark.parametrize("algo", [SERASAC, MASAC, MATD3], ids=lambda algo: algo.__name__)
def test_actions_are_decentralized_and_critics_centralized(algo):
    model = algo("CTDEPolicy", "sb3_sera/Pusher-3p-v0", seed=0, **SMALL_CTDE)
    observation, _ = gym.make("sb3_sera/Pusher-3p-v0").unwrapped.reset(seed=0)
    changed = copy.deepcopy(observation)
    changed["agent_1"] = changed["agent_1"] + 1.0
    changed[STATE_KEY] = changed[STATE_KEY] + 1.0
    with th.no_grad():
        before = model.actor(batch(observation), deterministic=True)
        after = model.actor(batch(changed), deterministic=True)
        # agent_0 acts on its own observation only: actions 0-2; agent_1 owns action 3
        th.testing.assert_close(before[:, :3], after[:, :3])
        assert not th.allclose(before[:, 3], after[:, 3])
        action = th.zeros(1, 7)
        q_before = th.cat(model.critic(batch(observation), action), dim=1)
        q_after = th.cat(model.critic(batch(changed), action), dim=1)
        assert not th.allclose(q_before, q_after)
        # The critics read the state (and the joint action), not the agents' observations
        only_agents = copy.deepcopy(changed)
        only_agents[STATE_KEY] = observation[STATE_KEY]
        th.testing.assert_close(th.cat(model.critic(batch(only_agents), action), dim=1), q_before)


def test_mappo_value_is_centralized_and_actions_decentralized():
    model = MAPPO("CTDEPolicy", "sb3_sera/Pusher-3p-v0", seed=0, **ALGORITHMS[MAPPO])
    observation, _ = gym.make("sb3_sera/Pusher-3p-v0").unwrapped.reset(seed=0)
    changed = copy.deepcopy(observation)
    changed["agent_2"] = changed["agent_2"] + 1.0
    with th.no_grad():
        mean_before = model.policy.get_distribution(batch(observation)).distribution.mean
        mean_after = model.policy.get_distribution(batch(changed)).distribution.mean
        th.testing.assert_close(mean_before[:, :4], mean_after[:, :4])
        assert not th.allclose(mean_before[:, 4:], mean_after[:, 4:])
        th.testing.assert_close(model.policy.predict_values(batch(changed)), model.policy.predict_values(batch(observation)))
        changed[STATE_KEY] = changed[STATE_KEY] + 1.0
        assert not th.allclose(model.policy.predict_values(batch(changed)), model.policy.predict_values(batch(observation)))


def test_joint_log_prob_is_the_sum_of_the_agents():
    model = MASAC("CTDEPolicy", "sb3_sera/Pusher-3p-v0", seed=0, **SMALL_CTDE)
    observation = batch(gym.make("sb3_sera/Pusher-3p-v0").unwrapped.reset(seed=0)[0])
    th.manual_seed(7)
    joint_actions, joint_log_prob = model.actor.action_log_prob(observation)
    th.manual_seed(7)
    parts = [model.actor.agent_actor(agent).action_log_prob(observation[agent]) for agent in model.actor.agents]
    th.testing.assert_close(joint_actions, th.cat([action for action, _ in parts], dim=1))
    th.testing.assert_close(joint_log_prob, sum(log_prob for _, log_prob in parts))

    # MAPPO: the log-probability of a joint action is the sum of per-agent Gaussian log-probabilities
    mappo = MAPPO("CTDEPolicy", "sb3_sera/Pusher-3p-v0", seed=0, **ALGORITHMS[MAPPO])
    actions = th.randn(1, 7)
    _, log_prob, _ = mappo.policy.evaluate_actions(observation, actions)
    std = th.exp(mappo.policy.log_std)
    expected = 0.0
    for agent, part in zip(("agent_0", "agent_1", "agent_2"), (slice(0, 3), slice(3, 4), slice(4, 7)), strict=True):
        mean = mappo.policy.mlp_extractor.agent_actor(agent).mu(observation[agent])
        expected = expected + th.distributions.Normal(mean, std[part]).log_prob(actions[:, part]).sum(dim=1)
    th.testing.assert_close(log_prob, expected)


def test_entropy_target_is_minus_the_joint_action_size():
    for algo in (SERASAC, MASAC):
        model = algo("CTDEPolicy", "sb3_sera/Pusher-3p-v0", **SMALL_CTDE)
        assert model.target_entropy == -7.0  # 3 + 1 + 3 action dimensions


def test_actor_parameter_sharing():
    shared = MASAC("CTDEPolicy", "sb3_sera/SimpleSpread-v0", seed=0, policy_kwargs=dict(share_actor=True), **SMALL_CTDE)
    separate = MASAC("CTDEPolicy", "sb3_sera/SimpleSpread-v0", seed=0, **SMALL_CTDE)
    n_shared = sum(p.numel() for p in shared.actor.parameters())
    assert 3 * n_shared == sum(p.numel() for p in separate.actor.parameters())
    shared.learn(100)
    # HalfCheetah 6x1 agents observe 9 or 8 values: sharing needs SuperSuit's padding and agent indicator
    with pytest.raises(ValueError, match="share_actor=True needs agents with equal observation and action spaces"):
        MASAC("CTDEPolicy", "sb3_sera/HalfCheetah-6x1-v0", policy_kwargs=dict(share_actor=True))
    model = MAPPO(
        "CTDEPolicy",
        gym.make("sb3_sera/HalfCheetah-6x1-v0", agent_indicator=True),
        policy_kwargs=dict(share_actor=True),
        **ALGORITHMS[MAPPO],
    )
    assert len(model.policy.mlp_extractor.agent_actors) == 1
    model.learn(64)


def test_ctde_policy_needs_a_ctde_env():
    with pytest.raises(ValueError, match="The CTDE policies need a CTDEEnv"):
        MASAC("CTDEPolicy", "Pendulum-v1")
    with pytest.raises(ValueError, match="share_features_extractor=True is not possible"):
        SERASAC("CTDEPolicy", "sb3_sera/SimpleSpread-v0", policy_kwargs=dict(share_features_extractor=True))


def test_controllers_need_a_ctde_model():
    with pytest.raises(TypeError, match="not trained with a CTDE policy"):
        DecentralizedActors.from_model(SERASAC("MlpPolicy", "Pendulum-v1", **SMALL_CTDE))


class _CTDETQC(_CTDEAlgorithm, TQC):
    """A CTDE algorithm built on sb3-contrib's TQC, as a user would write one."""

    def _loss_optimizers(self) -> dict[str, th.optim.Optimizer]:
        return {"critic": self.critic.optimizer, "actor": self.actor.optimizer}


def test_a_ctde_algorithm_on_sb3_contribs_tqc_takes_tqcs_arguments_and_train():
    # Once only bases from stable_baselines3 were found: such an algorithm took OffPolicyAlgorithm's signatures
    assert _sb3_algorithm(_CTDETQC) is TQC
    assert _sb3_train_signature(_CTDETQC) == inspect.signature(TQC.train)
    model = _CTDETQC("MlpPolicy", "Pendulum-v1", top_quantiles_to_drop_per_net=3, learning_starts=50, batch_size=16)
    model.learn(60)
    assert model.top_quantiles_to_drop_per_net == 3 and model._n_updates == 10


def test_a_shared_actor_deploys_on_the_env_wrapped_as_in_training_and_names_a_mismatch():
    env = gym.make("sb3_sera/HalfCheetah-6x1-v0", agent_indicator=True)
    model = MASAC("CTDEPolicy", env, seed=0, policy_kwargs=dict(share_actor=True, net_arch=[16]), **SMALL_CTDE)
    controllers = DecentralizedActors.from_model(model.learn(60))
    raw = mamujoco_parallel_env("HalfCheetah", "6x1")
    observations, _ = with_agent_indicator(raw).reset(seed=0)
    actions = controllers(observations)
    assert all(raw.action_space(agent).contains(action) for agent, action in actions.items())
    # On the raw env the shared actor (trained on 9 values and 6 indicators) is given 8 or 9 values: named, not a
    # shape error deep in torch
    observations, _ = raw.reset(seed=0)
    with pytest.raises(ValueError, match=r"observation of 9 values, but its actor was trained on 15\. .*with_agent_ind"):
        controllers(observations)
