"""SUNRISE as an SB3 algorithm: its math on hand values, batched equals looped, acting, save/load, zoo, errors."""

import copy
import math

import gymnasium as gym
import numpy as np
import optuna
import pytest
import torch as th
import yaml
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from torch import nn

from sb3_sera import SUNRISE
from sb3_sera.common.layers import BatchedLinear
from sb3_sera.sunrise.buffers import SUNRISEReplayBufferSamples, bootstrap_masks
from sb3_sera.sunrise.ensemble import backup_weight, ensemble_std, masked_mean, ucb_choice, weighted_bellman_loss
from sb3_sera.sunrise.policies import SUNRISEPolicy
from sb3_sera.zoo import ALGOS, HYPERPARAMS_DIR, register
from tests.helpers import ENV_ID, SMALL, assert_same_state, snapshot


def member_linear(layer: BatchedLinear, member: int) -> nn.Linear:
    """One member of a batched layer as an ordinary ``nn.Linear``, with a copy of its weights."""
    linear = nn.Linear(layer.in_features, layer.out_features)
    with th.no_grad():
        linear.weight.copy_(layer.weight[member].T)
        linear.bias.copy_(layer.bias[member, 0])
    return linear


def member_mlp(layers: nn.Sequential, member: int) -> nn.Sequential:
    """One member of a batched MLP as an ordinary ``nn.Sequential``."""
    return nn.Sequential(
        *(member_linear(layer, member) if isinstance(layer, BatchedLinear) else type(layer)() for layer in layers)
    )


# --- The math on hand-computed values ---


def test_backup_weight_and_ensemble_std_on_hand_values():
    # N=2 members, C=2 critics, 2 samples: full agreement on sample 0; values 0, 2, 0, 2 on sample 1
    q_values = th.tensor([[[1.0, 0.0], [1.0, 2.0]], [[1.0, 0.0], [1.0, 2.0]]])
    std_q = ensemble_std(q_values)
    assert std_q.tolist() == [0.0, 1.0]  # population std: mean 1, squared deviations 1
    assert backup_weight(std_q, 1.0).tolist() == pytest.approx([1.0, 0.5 + 1 / (1 + math.e)])
    assert backup_weight(std_q, 20.0).tolist() == pytest.approx([1.0, 0.5 + 1 / (1 + math.exp(20))])
    assert backup_weight(std_q, 0.0).tolist() == [1.0, 1.0]


def test_masked_loss_on_hand_values():
    # N=2 members, C=2 critics, S=3 samples
    current_q = th.tensor([[[1.0, 2.0, 0.0], [0.0, 0.0, 2.0]], [[1.0, 1.0, 1.0], [3.0, 1.0, 1.0]]])
    target_q = th.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    weights = th.tensor([1.0, 0.5, 0.75])
    masks = th.tensor([[1.0, 1.0, 0.0], [1.0, 0.0, 1.0]])
    # Member 0: squared errors summed over its critics 1, 4, 4; weighted 1, 2, 3; kept 1 + 2, over 2 + 1
    # Member 1: 0 + 4, 0, 0; weighted 4, 0, 0; kept 4 + 0, over 2 + 1
    assert weighted_bellman_loss(current_q, target_q, weights, masks).tolist() == pytest.approx([1.0, 4 / 3])
    # A member with an empty mask has zero loss (the + 1), not a division by zero
    assert masked_mean(th.tensor([[5.0, 7.0]]), th.zeros(1, 2)).tolist() == [0.0]


def test_ucb_choice_on_hand_values():
    # 4 critics, 2 proposals, 1 sample: proposal 0 values 1.5 (std 0), proposal 1 values 0, 0, 2, 2 (mean 1, std 1)
    q_values = th.tensor([[[1.5], [0.0]], [[1.5], [0.0]], [[1.5], [2.0]], [[1.5], [2.0]]])
    assert ucb_choice(q_values, 0.0).tolist() == [0]  # mean only: 1.5 > 1
    assert ucb_choice(q_values, 1.0).tolist() == [1]  # 1 + 1 * 1 = 2 > 1.5
    assert ucb_choice(q_values, 0.5).tolist() == [0]  # a tie, 1.5 each: the first proposal


def test_bootstrap_masks_give_every_transition_a_member():
    np.random.seed(0)
    masks = bootstrap_masks(10_000, 5, 0.5)
    assert set(np.unique(masks)) == {0.0, 1.0}
    assert masks.sum(axis=1).min() >= 1
    # Bernoulli(0.5), plus one member for the 1/32 of transitions that drew none
    assert masks.mean() == pytest.approx(0.5 + 1 / 32 / 5, abs=0.01)
    assert bootstrap_masks(100, 3, 1.0).min() == 1.0


# --- Batched networks and updates equal a loop over members ---


def test_batched_networks_equal_a_loop_over_members():
    model = SUNRISE("MlpPolicy", ENV_ID, n_members=3, policy_kwargs=dict(net_arch=[16, 8]), **SMALL)
    obs = th.randn(7, 3)
    member_actions = th.rand(3, 7, 1) * 2 - 1
    mean, log_std = model.actor(obs)
    assert mean.shape == log_std.shape == (3, 7, 1)
    for member in range(3):
        latent = member_mlp(model.actor.latent_pi, member)(obs)
        th.testing.assert_close(mean[member], member_linear(model.actor.mu, member)(latent))
        th.testing.assert_close(log_std[member], member_linear(model.actor.log_std, member)(latent).clamp(-20, 2))
    # Each member's critics on its own actions, and every critic on one action batch
    per_member = model.critic.q_values(obs, member_actions)
    shared = model.critic.q_values(obs, member_actions[0])
    assert per_member.shape == shared.shape == (3, 2, 7)
    for member in range(3):
        for critic in range(2):
            q_net = member_mlp(model.critic.q_net, member * 2 + critic)
            own = q_net(th.cat([obs, member_actions[member]], dim=1)).squeeze(1)
            th.testing.assert_close(per_member[member, critic], own)
            th.testing.assert_close(shared[member, critic], q_net(th.cat([obs, member_actions[0]], dim=1)).squeeze(1))
    # SB3's critic interface: one (S, 1) tensor per Q-network
    values = model.critic(obs, member_actions[0])
    assert len(values) == 6 and all(value.shape == (7, 1) for value in values)
    th.testing.assert_close(th.cat(values, dim=1).T, shared.flatten(0, 1))


def reference_log_prob(mean: th.Tensor, log_std: th.Tensor, noise: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
    """SB3's squashed Gaussian, written with torch.distributions: action and log-probability of one member."""
    gaussian = mean + log_std.exp() * noise
    action = th.tanh(gaussian)
    log_prob = th.distributions.Normal(mean, log_std.exp()).log_prob(gaussian).sum(dim=1)
    return action, log_prob - th.log(1 - action.pow(2) + 1e-6).sum(dim=1)


def test_gradient_step_equals_a_loop_over_members():
    """One batched update against the authors' per-member loop (in SB3's order: entropy, critics, actor)."""
    n_members, lr = 3, 0.05
    model = SUNRISE(
        "MlpPolicy",
        ENV_ID,
        n_members=n_members,
        seed=0,
        learning_rate=lr,
        policy_kwargs=dict(net_arch=[16, 16], optimizer_class=th.optim.SGD),
        **SMALL,
    ).learn(SMALL["learning_starts"])
    data = model.replay_buffer.sample(32)
    assert isinstance(data, SUNRISEReplayBufferSamples) and data.masks.shape == (32, n_members)
    assert model.log_ent_coef is not None
    with th.no_grad():
        model.log_ent_coef.copy_(th.tensor([-1.0, -0.5, 0.2]))  # a different entropy coefficient per member

    # The members as separate networks, each with its own optimizers
    members = []
    for m in range(n_members):
        actor = nn.ModuleDict(
            dict(
                latent=member_mlp(model.actor.latent_pi, m),
                mu=member_linear(model.actor.mu, m),
                log_std=member_linear(model.actor.log_std, m),
            )
        )
        critics = nn.ModuleList([member_mlp(model.critic.q_net, 2 * m + c) for c in range(2)])
        targets = nn.ModuleList([member_mlp(model.critic_target.q_net, 2 * m + c) for c in range(2)])
        log_alpha = model.log_ent_coef[m].detach().clone().requires_grad_(True)
        optimizers = (
            th.optim.SGD(actor.parameters(), lr=lr),
            th.optim.SGD(critics.parameters(), lr=lr),
            th.optim.Adam([log_alpha], lr=lr),
        )
        members.append((actor, critics, targets, log_alpha, optimizers))

    def act(actor: nn.ModuleDict, obs: th.Tensor, noise: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        latent = actor["latent"](obs)
        return reference_log_prob(actor["mu"](latent), actor["log_std"](latent).clamp(-20, 2), noise)

    th.manual_seed(1)
    noise_pi, noise_next = th.randn(n_members, 32, 1), th.randn(n_members, 32, 1)
    obs, next_obs = data.observations, data.next_observations
    with th.no_grad():
        next_samples = [act(actor, next_obs, noise_next[m]) for m, (actor, *_) in enumerate(members)]
        next_values = [
            [target(th.cat([next_obs, next_samples[m][0]], dim=1)) for target in targets]
            for m, (_, _, targets, _, _) in enumerate(members)
        ]
        std_q = th.cat([value for values in next_values for value in values], dim=1).std(dim=1, unbiased=False)
        weight = (th.sigmoid(-std_q * 20.0) + 0.5).unsqueeze(1)
    critic_losses = []
    for m, (actor, critics, _, log_alpha, (actor_optimizer, critic_optimizer, alpha_optimizer)) in enumerate(members):
        mask = data.masks[:, m : m + 1]
        action_pi, log_pi = act(actor, obs, noise_pi[m])
        alpha = log_alpha.detach().exp()
        alpha_loss = (-(log_alpha * (log_pi + model.target_entropy).detach()) * mask.squeeze(1)).sum() / (mask.sum() + 1)
        alpha_optimizer.zero_grad()
        alpha_loss.backward()
        alpha_optimizer.step()
        with th.no_grad():
            next_q = th.min(*next_values[m]) - alpha * next_samples[m][1].unsqueeze(1)
            target_q = data.rewards + (1 - data.dones) * model.gamma * next_q
        critic_loss = sum(
            (weight * mask * (critic(th.cat([obs, data.actions], dim=1)) - target_q).pow(2)).sum() / (mask.sum() + 1)
            for critic in critics
        )
        critic_optimizer.zero_grad()
        critic_loss.backward()
        critic_optimizer.step()
        critic_losses.append(critic_loss.item())
        q_pi = th.min(*[critic(th.cat([obs, action_pi], dim=1)) for critic in critics])
        actor_loss = ((alpha * log_pi.unsqueeze(1) - q_pi) * mask).sum() / (mask.sum() + 1)
        actor_optimizer.zero_grad()
        actor_loss.backward()
        actor_optimizer.step()

    th.manual_seed(1)
    logged = model._gradient_step(data)
    assert logged["critic_loss"].item() == pytest.approx(np.mean(critic_losses), rel=1e-5)
    assert logged["ensemble_std"].item() == pytest.approx(std_q.mean().item(), rel=1e-5)
    assert logged["backup_weight"].item() == pytest.approx(weight.mean().item(), rel=1e-5)
    tolerance = dict(rtol=1e-5, atol=1e-6)
    for m, (actor, critics, _, log_alpha, _) in enumerate(members):
        th.testing.assert_close(model.log_ent_coef[m], log_alpha, **tolerance)
        for batched, looped in [
            (model.actor.mu, actor["mu"]),
            (model.actor.log_std, actor["log_std"]),
            *zip(model.actor.latent_pi[::2], actor["latent"][::2], strict=True),
        ]:
            th.testing.assert_close(batched.weight[m].T, looped.weight, **tolerance)
            th.testing.assert_close(batched.bias[m, 0], looped.bias, **tolerance)
        for c, critic in enumerate(critics):
            for batched, looped in zip(model.critic.q_net[::2], critic[::2], strict=True):
                th.testing.assert_close(batched.weight[2 * m + c].T, looped.weight, **tolerance)
                th.testing.assert_close(batched.bias[2 * m + c, 0], looped.bias, **tolerance)


# --- Acting ---


def test_evaluation_acts_with_the_mean_of_the_deterministic_actions():
    model = SUNRISE("MlpPolicy", ENV_ID, seed=0, **SMALL)
    observation = np.array([0.3, -0.2, 0.5], dtype=np.float32)
    action, _ = model.predict(observation, deterministic=True)
    with th.no_grad():
        mean, _ = model.actor(th.as_tensor(observation).unsqueeze(0))
    expected = 2.0 * th.tanh(mean).mean(dim=0).squeeze(0).numpy()  # Pendulum's actions lie in [-2, 2]
    np.testing.assert_allclose(action, expected, rtol=1e-6, atol=1e-7)


def test_ucb_exploration_takes_the_proposal_with_the_highest_bound():
    model = SUNRISE("MlpPolicy", ENV_ID, seed=0, n_members=4, ucb_lambda=1.0, **SMALL)
    obs = th.randn(6, 3)
    th.manual_seed(3)
    actions = model.policy._predict(obs, deterministic=False)
    th.manual_seed(3)
    proposals, _ = model.actor.action_log_prob(obs)
    for sample in range(6):
        scores = []
        for proposal in range(4):
            # Every online critic of every member (SB3's interface), on this proposal
            values = th.cat(model.critic(obs[sample : sample + 1], proposals[proposal, sample : sample + 1]))
            scores.append((values.mean() + 1.0 * values.std(unbiased=False)).item())
        assert th.equal(actions[sample], proposals[int(np.argmax(scores)), sample])


class MemberRecorder(BaseCallback):
    """Records, at each step, the member acting in each env and whether its episode ended."""

    def __init__(self) -> None:
        super().__init__()
        self.steps: list[tuple[np.ndarray, np.ndarray]] = []

    def _on_step(self) -> bool:
        assert isinstance(self.model, SUNRISE) and self.model._episode_members is not None
        self.steps.append((self.model._episode_members.copy(), self.locals["dones"].copy()))
        return True


def test_without_ucb_one_member_acts_for_a_whole_episode():
    recorder = MemberRecorder()
    env = make_vec_env(ENV_ID, n_envs=2, seed=0)  # Pendulum episodes: 200 steps
    # No gradient step is needed: the members act from the start (after the uniform warm-up, with random actions)
    model = SUNRISE("MlpPolicy", env, seed=0, **{**SMALL, "learning_starts": 1_000}).learn(1_000, callback=recorder)
    changes = 0
    for (before, done), (after, _) in zip(recorder.steps[:-1], recorder.steps[1:], strict=True):
        # The member drawn at an episode's end acts in the next one
        np.testing.assert_array_equal(before[~done], after[~done])
        changes += int((before != after).sum())
    assert changes > 0 and all(step[1].sum() in (0, 2) for step in recorder.steps)
    # A stochastic prediction outside learn() draws a member per row
    assert model.policy.episode_members is None
    assert model.predict(np.zeros((4, 3), dtype=np.float32))[0].shape == (4, 1)


# --- Training, save/load, determinism, multi-env ---


def test_learn_logs_sac_keys_and_sunrise_quantities():
    model = SUNRISE("MlpPolicy", ENV_ID, seed=0, **SMALL).learn(200)
    logged = model.logger.name_to_value
    for key in ("ent_coef", "ent_coef_loss", "actor_loss", "critic_loss", "backup_weight", "ensemble_std", "learning_rate"):
        assert np.isfinite(logged[f"train/{key}"]), key
    assert 0.5 <= logged["train/backup_weight"] <= 1.0 and logged["train/ensemble_std"] > 0
    assert logged["train/n_updates"] == 150
    assert model.log_ent_coef is not None and model.log_ent_coef.shape == (5,)
    # The members learn their entropy coefficients separately (each on its own mask)
    assert len(set(model.log_ent_coef.tolist())) == 5
    model.train(gradient_steps=0)


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(ent_coef=0.1),
        dict(ent_coef="auto_0.5"),
        dict(n_members=1),
        dict(bootstrap_prob=1.0, backup_temperature=0.0),
        dict(ucb_lambda=10.0),
        dict(optimize_memory_usage=True, replay_buffer_kwargs=dict(handle_timeout_termination=False)),
        dict(policy_kwargs=dict(n_critics=1, net_arch=dict(pi=[32], qf=[16, 16]))),
        dict(target_update_interval=2, gradient_steps=2, train_freq=2),
    ],
)
def test_variants_train(kwargs):
    model = SUNRISE("MlpPolicy", ENV_ID, seed=0, **{**SMALL, **kwargs}).learn(120)
    assert np.isfinite(model.logger.name_to_value["train/critic_loss"])


def test_save_load_and_continue_with_the_replay_buffer(tmp_path):
    model = SUNRISE("MlpPolicy", ENV_ID, seed=0, n_members=3, ucb_lambda=0.5, **SMALL).learn(150)
    model.save(tmp_path / "model")
    model.save_replay_buffer(tmp_path / "buffer")
    loaded = SUNRISE.load(tmp_path / "model", env=gym.make(ENV_ID))
    loaded.load_replay_buffer(tmp_path / "buffer")
    assert (loaded.n_members, loaded.ucb_lambda, loaded.policy.n_members, loaded.policy.ucb_lambda) == (3, 0.5, 3, 0.5)
    assert_same_state(snapshot(model), snapshot(loaded))
    # The bootstrap masks survive: every stored transition keeps the members it was drawn for
    assert loaded.replay_buffer.masks.shape == (2_000, 1, 3)
    np.testing.assert_array_equal(loaded.replay_buffer.masks, model.replay_buffer.masks)
    assert loaded.replay_buffer.masks[:150].sum(axis=-1).min() >= 1
    observation = np.array([0.1, 0.2, 0.3], dtype=np.float32)
    np.testing.assert_array_equal(
        model.predict(observation, deterministic=True)[0], loaded.predict(observation, deterministic=True)[0]
    )
    loaded.learn(100, reset_num_timesteps=False)
    assert loaded.num_timesteps == 250 and loaded.logger.name_to_value["train/n_updates"] == 200
    assert loaded.replay_buffer.masks[:250].sum(axis=-1).min() >= 1
    # Settings given to load() reach the policy
    assert SUNRISE.load(tmp_path / "model", ucb_lambda=2.0).policy.ucb_lambda == 2.0
    mean_return, _ = evaluate_policy(loaded, loaded.get_env(), n_eval_episodes=1)
    assert np.isfinite(mean_return)


@pytest.mark.parametrize("ucb_lambda", [0.0, 0.5])
def test_save_load_continue_equals_continuing_in_memory(tmp_path, ucb_lambda):
    # Stopped mid-episode (Pendulum's last 200 steps): with ucb_lambda=0 the member acting in it must be kept
    model = SUNRISE("MlpPolicy", ENV_ID, seed=0, n_members=3, ucb_lambda=ucb_lambda, **SMALL).learn(150)
    model.save(tmp_path / "model")
    model.save_replay_buffer(tmp_path / "buffer")
    loaded = SUNRISE.load(tmp_path / "model", env=copy.deepcopy(model.get_env()), force_reset=False)
    loaded.load_replay_buffer(tmp_path / "buffer")
    for continued in (model, loaded):
        continued.set_random_seed(1)
        continued.learn(100, reset_num_timesteps=False)
    assert_same_state(snapshot(model), snapshot(loaded))


def test_a_new_episode_after_a_reset_gets_a_new_member():
    model = SUNRISE("MlpPolicy", ENV_ID, seed=0, n_members=50, **SMALL).learn(60)
    acting = model._episode_members.copy()
    # learn() resets the env for a new run: the next episode is acted in by a member drawn for it
    model.learn(1, reset_num_timesteps=True)
    assert model._episode_members is not None and not np.array_equal(model._episode_members, acting)


def test_policy_saves_and_loads_alone(tmp_path):
    model = SUNRISE("MlpPolicy", ENV_ID, seed=0, n_members=2, ucb_lambda=1.0, policy_kwargs=dict(net_arch=[32]), **SMALL)
    model.policy.save(tmp_path / "policy")
    policy = SUNRISEPolicy.load(tmp_path / "policy")
    assert (policy.n_members, policy.ucb_lambda, policy.net_arch) == (2, 1.0, [32])
    observations = np.random.default_rng(0).normal(size=(5, 3)).astype(np.float32)
    expected_actions = model.predict(observations, deterministic=True)[0]
    np.testing.assert_array_equal(policy.predict(observations, deterministic=True)[0], expected_actions)


def test_non_finite_values_stop_training_before_any_change():
    model = SUNRISE("MlpPolicy", ENV_ID, seed=0, **SMALL).learn(SMALL["learning_starts"])
    model.replay_buffer.rewards[:] = np.inf
    before = snapshot(model)
    with pytest.raises(FloatingPointError, match=r"Non-finite TD target at gradient step 1 \(num_timesteps=50\)"):
        model.train(gradient_steps=1, batch_size=32)
    assert_same_state(before, snapshot(model))


def test_same_seed_same_parameters():
    first = SUNRISE("MlpPolicy", ENV_ID, seed=3, **SMALL).learn(150)
    second = SUNRISE("MlpPolicy", ENV_ID, seed=3, **SMALL).learn(150)
    assert_same_state(snapshot(first), snapshot(second))
    np.testing.assert_array_equal(first.replay_buffer.masks, second.replay_buffer.masks)
    third = SUNRISE("MlpPolicy", ENV_ID, seed=4, **SMALL).learn(150)
    assert not th.equal(first.actor.mu.weight, third.actor.mu.weight)


def test_multi_env_and_progress_bar():
    env = make_vec_env(ENV_ID, n_envs=2, seed=0)
    model = SUNRISE("MlpPolicy", env, seed=0, **SMALL).learn(200, progress_bar=True)
    assert model.replay_buffer.masks.shape == (1_000, 2, 5)  # SB3 splits buffer_size over the envs
    assert model.replay_buffer.masks[:100].sum(axis=-1).min() >= 1
    mean_return, _ = evaluate_policy(model, env, n_eval_episodes=2)
    assert np.isfinite(mean_return)


# --- Errors ---


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(n_members=0), r"n_members=0 is out of range: allowed an integer >= 1"),
        (dict(bootstrap_prob=0.0), r"bootstrap_prob=0.0 is out of range: allowed \(0.0, 1.0\]"),
        (dict(bootstrap_prob=1.5), r"bootstrap_prob=1.5 is out of range"),
        (dict(backup_temperature=-1.0), r"backup_temperature=-1.0 is out of range: allowed \[0.0, inf\)"),
        (dict(ucb_lambda=float("nan")), r"ucb_lambda=nan is invalid"),
        (dict(learning_rate=0.0), r"learning_rate=0.0 is out of range"),
        (dict(batch_size=0), r"batch_size=0 is out of range"),
        (dict(tau=1.5), r"tau=1.5 is out of range"),
        (dict(gamma=-0.1), r"gamma=-0.1 is out of range"),
        (dict(target_update_interval=0), r"target_update_interval=0 is out of range"),
        (dict(ent_coef="auto_-1"), r"ent_coef='auto_-1' is invalid"),
        (dict(ent_coef=0.0), r"ent_coef=0.0 is out of range"),
        (dict(target_entropy="high"), r"target_entropy='high' is invalid"),
        (dict(policy_kwargs=dict(n_members=3)), r"pass n_members to SUNRISE itself"),
        (dict(replay_buffer_kwargs=dict(bootstrap_prob=0.3)), r"pass bootstrap_prob to SUNRISE itself"),
        (dict(policy_kwargs=dict(n_critics=0)), r"n_critics=0 is out of range"),
        (dict(replay_buffer_class=ReplayBuffer), r"replay_buffer_class=ReplayBuffer is invalid"),
    ],
)
def test_hyperparameters_out_of_range_are_named(kwargs, message):
    with pytest.raises(ValueError, match=message):
        SUNRISE("MlpPolicy", ENV_ID, **{**SMALL, **kwargs})


def test_numbers_as_yaml_and_numpy_give_them():
    model = SUNRISE("MlpPolicy", ENV_ID, learning_starts=1e2, n_members=np.int64(3), backup_temperature=np.float32(5))
    assert (model.learning_starts, model.n_members, model.backup_temperature) == (100, 3, 5.0)
    assert type(model.n_members) is int


def test_multi_agent_tasks_are_refused_with_the_reason():
    with pytest.raises(ValueError, match="SUNRISE is single-agent for now"):
        SUNRISE("CTDEPolicy", ENV_ID)
    with pytest.raises(ValueError, match="SUNRISE is single-agent for now"):
        SUNRISE("MlpPolicy", "sb3_sera/SimpleSpread-v0")


# --- Zoo ---


def test_zoo_registration_sampler_and_hyperparameter_file():
    register()
    from rl_zoo3 import hyperparams_opt, utils

    assert ALGOS["sunrise"] is SUNRISE and utils.ALGOS["sunrise"] is SUNRISE
    trial = optuna.create_study().ask()
    params = hyperparams_opt.HYPERPARAMS_SAMPLER["sunrise"](trial, 1, 1, {"using_her_replay_buffer": False})
    assert 2 <= params["n_members"] <= 10 and params["backup_temperature"] > 0 and params["ucb_lambda"] >= 0
    stored = hyperparams_opt.HYPERPARAMS_CONVERTER["sunrise"](dict(trial.params))
    assert stored["n_members"] == params["n_members"] and stored["policy_kwargs"] == params["policy_kwargs"]
    entries = yaml.load((HYPERPARAMS_DIR / "sunrise.yml").read_text(), Loader=yaml.UnsafeLoader)
    paper = entries["HalfCheetah-v5"]
    assert entries["Ant-v5"] == entries["Humanoid-v5"] == paper
    assert (paper["n_members"], paper["bootstrap_prob"], paper["backup_temperature"], paper["ucb_lambda"]) == (5, 0.5, 20, 0)
    assert (paper["batch_size"], paper["learning_rate"], paper["tau"]) == (256, 3e-4, 0.005)
    # Every entry builds a SUNRISE (on Pendulum, with a small buffer)
    for entry in entries.values():
        kwargs = {key: value for key, value in entry.items() if key not in ("n_timesteps", "policy")}
        SUNRISE(entry["policy"], ENV_ID, **{**kwargs, "buffer_size": 100})


# --- Learning ---


@pytest.mark.slow
def test_sunrise_learns_pendulum():
    model = SUNRISE("MlpPolicy", ENV_ID, seed=0, learning_rate=1e-3).learn(8_000)
    mean_return, _ = evaluate_policy(model, model.get_env(), n_eval_episodes=5)
    # A random policy scores about -1200; a solved pendulum, above -200
    assert mean_return > -400
