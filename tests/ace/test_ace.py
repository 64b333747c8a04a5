"""ACE: the look-ahead tree and the action choice by hand, batched heads, normalizer, and SB3-style runs."""

import numpy as np
import pytest
import torch as th
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.noise import VectorizedActionNoise

from sb3_sera.ace import ACE
from sb3_sera.ace.ace import DecayingNormalNoise
from sb3_sera.ace.policies import ActorHeads, RunningObservationNorm
from sb3_sera.ace.tree import best_actions, head_values, state_value, tree_value


# A world small enough to compute by hand: one feature, one action dimension, two heads.
# Q(phi, a) = phi * a; the model moves phi to phi + a and pays r = 2a; the heads propose phi and -phi.
def critic(phi, action):
    return phi * action


def env_model(phi, action):
    return phi + action, 2 * action


def actors(phi):
    return th.stack([phi, -phi], dim=-2)


def scalar(value: float) -> th.Tensor:
    return th.tensor([[value]])


def test_depth_two_tree_value_by_hand():
    assert tree_value(scalar(2.0), scalar(3.0), 1, 0.5, critic, env_model, actors).q_value.item() == 6.0
    # phi' = 5, r = 6; at phi' the heads propose 5 and -5, worth 25 and -25: Q_2 = 6 + 0.5 * 25 = 18.5
    value = tree_value(scalar(2.0), scalar(3.0), 2, 0.5, critic, env_model, actors)
    assert (value.q_value.item(), value.reward.item(), value.next_value.item()) == (18.5, 6.0, 25.0)
    # Depth 3: phi' = 5, r = 6, then each head's depth-2 value at 5: a = 5 -> 10 + 0.5 * 100 = 60; a = -5 -> -10 + 0
    assert tree_value(scalar(2.0), scalar(3.0), 3, 0.5, critic, env_model, actors).q_value.item() == 6.0 + 0.5 * 60.0
    with pytest.raises(ValueError, match="depth=0 is invalid"):
        tree_value(scalar(2.0), scalar(3.0), 0, 0.5, critic, env_model, actors)


def test_action_choice_by_hand_and_the_tree_changes_it():
    phi = th.tensor([[-1.0], [2.0]])
    # phi = -1: heads propose -1 and 1. Depth 1: Q = 1 and -1 -> head 0. Depth 2: a = -1 -> phi' = -2, r = -2,
    # best next value 4 -> 0; a = 1 -> phi' = 0, r = 2, next value 0 -> 2: head 1.
    # phi = 2: heads 2 and -2. Depth 2: a = 2 -> 4 + 0.5 * 16 = 12; a = -2 -> -4 + 0 = -4: head 0.
    proposals, values = head_values(phi, 1, 0.5, critic, env_model, actors)
    assert values.tolist() == [[1.0, -1.0], [4.0, -4.0]]
    proposals, values = head_values(phi, 2, 0.5, critic, env_model, actors)
    assert values.tolist() == [[0.0, 2.0], [12.0, -4.0]]
    actions, heads = best_actions(proposals, values)
    assert heads.tolist() == [1, 0] and actions.tolist() == [[1.0], [2.0]]
    assert state_value(phi, 2, 0.5, critic, env_model, actors).tolist() == [[2.0], [12.0]]


def test_batched_heads_equal_a_loop_over_heads():
    th.manual_seed(0)
    heads = ActorHeads(feature_dim=7, action_dim=3, n_heads=5, hidden=11)
    features = th.randn(4, 6, 7)
    batched = heads(features)
    assert batched.shape == (4, 6, 5, 3)
    looped = th.stack([heads.head(index, features) for index in range(5)], dim=-2)
    assert th.allclose(batched, looped, atol=1e-6)
    # Gradients match too
    batched.sum().backward()
    grad = heads.out_weight.grad.clone()
    heads.zero_grad()
    th.stack([heads.head(index, features) for index in range(5)], dim=-2).sum().backward()
    assert th.allclose(grad, heads.out_weight.grad, atol=1e-5)


def test_running_normalizer_matches_numpy():
    norm = RunningObservationNorm(2)
    batches = [np.random.default_rng(seed).normal(3.0, 2.0, size=(n, 2)) for seed, n in ((0, 5), (1, 1), (2, 40))]
    for batch in batches:
        norm.update(th.as_tensor(batch, dtype=th.float32))
    seen = np.concatenate(batches)
    np.testing.assert_allclose(norm.mean.numpy(), seen.mean(axis=0), rtol=1e-5)
    np.testing.assert_allclose(norm.var.numpy(), seen.var(axis=0), rtol=1e-4)
    assert norm(th.tensor([[1e6, -1e6]])).tolist() == [[10.0, -10.0]]


def small(**kwargs):
    return ACE(
        "MlpPolicy", "Pendulum-v1", learning_starts=50, batch_size=16, seed=0,
        policy_kwargs=dict(feature_dim=32, hidden=16, n_actors=3), **kwargs,
    )  # fmt: skip


def test_learn_save_load_continue(tmp_path):
    model = small().learn(150)
    assert model.policy.network.normalizer.count.item() == pytest.approx(150, abs=1e-3)
    # The exploration noise decays linearly to 0 at the end of the run
    assert isinstance(model.action_noise, DecayingNormalNoise) and model.action_noise.sigma == pytest.approx(0.0)
    model.save(tmp_path / "ace")
    model.save_replay_buffer(tmp_path / "buffer")
    loaded = ACE.load(tmp_path / "ace", env=model.get_env())
    loaded.load_replay_buffer(tmp_path / "buffer")
    observation = model.get_env().reset()
    assert np.array_equal(
        model.predict(observation, deterministic=True)[0], loaded.predict(observation, deterministic=True)[0]
    )
    for a, b in zip(model.policy.state_dict().values(), loaded.policy.state_dict().values(), strict=True):
        assert th.equal(a, b)
    assert loaded.policy.network_target.normalizer is loaded.policy.network.normalizer
    loaded.learn(60, reset_num_timesteps=False)
    assert loaded.num_timesteps == 210 and loaded.replay_buffer.size() == 210
    mean, _ = evaluate_policy(loaded, loaded.get_env(), n_eval_episodes=1)
    assert np.isfinite(mean)


def test_determinism_and_multi_env():
    first, second = small().learn(120), small().learn(120)
    for a, b in zip(first.policy.parameters(), second.policy.parameters(), strict=True):
        assert th.equal(a, b)
    multi = ACE(
        "MlpPolicy", make_vec_env("Pendulum-v1", n_envs=2, seed=0), learning_starts=20, batch_size=8,
        policy_kwargs=dict(feature_dim=16, hidden=8), seed=0,
    ).learn(60)  # fmt: skip
    assert multi.num_timesteps == 60 and multi.replay_buffer.size() == 30


def test_exploration_noise_decays_with_several_envs():
    # SB3 gives each env its own copy of the noise (VectorizedActionNoise) when n_envs > 1: each copy decays
    model = ACE(
        "MlpPolicy", make_vec_env("Pendulum-v1", n_envs=2, seed=0), learning_starts=20, batch_size=8,
        policy_kwargs=dict(feature_dim=16, hidden=8), seed=0,
    )  # fmt: skip
    sigmas: list[list[float]] = []

    def record(locals_, globals_):
        sigmas.append([noise.sigma for noise in locals_["self"].action_noise.noises])
        return True

    model.learn(60, callback=record)
    assert isinstance(model.action_noise, VectorizedActionNoise) and len(sigmas) == 30
    # Linear from 0.3 to 0 over the run (a callback sees the noise acted with at that step: 0.3 * (1 - t / 30))
    np.testing.assert_allclose(sigmas, [[0.3 * (1 - t / 30)] * 2 for t in range(30)], atol=1e-9)
    assert model.logger.name_to_value["train/exploration_noise"] == pytest.approx(0.0)


def test_defaults_are_the_authors():
    model = ACE("MlpPolicy", "Pendulum-v1")
    assert (model.learning_rate, model.batch_size, model.tau, model.gamma) == (1e-4, 64, 1e-3, 0.99)
    # The authors' objective: TD and reward-model losses; the next-value alignment is their option, off by default
    assert model.align_next_value is False and model.critic_loss_weight == 10.0


def assert_orthogonal(weight: th.Tensor, gain: float) -> None:
    """``W W^T = gain^2 I`` on the smaller side of ``W`` (rows or columns orthonormal, then scaled)."""
    matrix = weight if weight.shape[0] <= weight.shape[1] else weight.T
    th.testing.assert_close(matrix @ matrix.T, gain**2 * th.eye(matrix.shape[0]), atol=1e-5 * max(gain**2, 1e-3), rtol=0)


def test_layers_are_initialized_as_the_authors():
    # The authors' layer_init: orthogonal weights (gain 1; 3e-3 for the actors' and the critic's output layers), zero
    # biases (ShangtongZhang/DeepRL, PlanEnsembleDeterministicNet)
    th.manual_seed(0)
    network = small().policy.network
    linears = {
        "features": (network.features[0], 1.0),
        "critic hidden": (network.critic_net[0], 1.0),
        "critic output": (network.critic_net[2], 3e-3),
        "reward hidden": (network.env_model.reward[0], 1.0),
        "reward output": (network.env_model.reward[2], 1.0),
        "transition state": (network.env_model.transition_state, 1.0),
        "transition action": (network.env_model.transition_action, 1.0),
    }
    for name, (layer, gain) in linears.items():
        assert_orthogonal(layer.weight.detach(), gain)
        assert th.count_nonzero(layer.bias) == 0, name
    heads = network.actors
    for index in range(heads.hidden_weight.shape[0]):
        # Stored as (in, out) for the batched product: the nn.Linear weight is the transpose
        assert_orthogonal(heads.hidden_weight[index].detach().T, 1.0)
        assert_orthogonal(heads.out_weight[index].detach().T, 3e-3)
    for bias in (heads.hidden_bias, heads.out_bias):
        assert th.count_nonzero(bias) == 0
    # Each head has its own initialization
    assert not th.equal(heads.hidden_weight[0], heads.hidden_weight[1])


def test_float64_observations_train():
    # MuJoCo tasks give float64 observations, which the replay buffer keeps
    model = ACE(
        "MlpPolicy",
        "InvertedPendulum-v5",
        learning_starts=20,
        batch_size=8,
        seed=0,
        policy_kwargs=dict(feature_dim=16, hidden=8),
    )
    model.learn(40)
    assert model.replay_buffer.observations.dtype == np.float64 and model._n_updates == 20


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"tau": 1.5}, r"tau=1.5 is out of range"),
        ({"critic_loss_weight": 0.0}, r"critic_loss_weight=0.0 is out of range"),
        ({"exploration_noise": -0.1}, r"exploration_noise=-0.1 is out of range"),
        ({"policy_kwargs": {"depth": 0}}, r"depth=0 is out of range: allowed an integer >= 1"),
        ({"policy_kwargs": {"n_actors": 0}}, r"n_actors=0 is out of range"),
        ({"policy_kwargs": {"n_actors": 2.5}}, r"n_actors=2.5 is invalid: expected an integer >= 1"),
        ({"policy_kwargs": {"hidden": 0}}, r"hidden=0 is out of range"),
    ],
)
def test_bad_hyperparameters_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        ACE("MlpPolicy", "Pendulum-v1", **kwargs)


@pytest.mark.parametrize("policy", ["MultiInputPolicy", "CTDEPolicy"])
def test_multi_agent_tasks_are_refused_with_a_reason(policy):
    with pytest.raises(ValueError, match=r"ACE takes flat Box observations.*single-agent \(no CTDE tasks\)"):
        ACE(policy, "sb3_sera/SimpleSpread-v0")


@pytest.mark.slow
def test_ace_learns_pendulum():
    # ACE solves Pendulum within 2,000 steps here; its depth-2 tree makes each gradient step about 15 times as costly
    # as SAC's on this task (25 branches through 400/300-wide networks), so the budget stays small
    model = ACE("MlpPolicy", "Pendulum-v1", learning_rate=1e-3, batch_size=128, tau=5e-3, seed=0).learn(3_000)
    mean, _ = evaluate_policy(model, model.get_env(), n_eval_episodes=5)
    assert mean > -600
