"""InitialStateBiasCallback: V(s0) and the discounted return against hand-computed values."""

import gymnasium as gym
import numpy as np
import pandas as pd
import pytest
import torch as th
from gymnasium import spaces
from sb3_contrib import TQC
from stable_baselines3 import DQN, PPO, SAC
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import configure

from sb3_sera import SERASAC
from sb3_sera.common.evaluation import (
    BIAS_FILE,
    DIAGNOSTICS_FILE,
    InitialStateBiasCallback,
    critic_diagnostics,
    monte_carlo_errors,
    monte_carlo_samples,
)

START = np.array([0.3, -0.2], dtype=np.float32)


class CountingEnv(gym.Env):
    """Starts at START, pays rewards 1, 2, 3 and ends after three steps; actions in [-2, 2]."""

    observation_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
    action_space = spaces.Box(-2.0, 2.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return START.copy(), {}

    def step(self, action):
        self.t += 1
        return START.copy(), float(self.t), self.t == 3, False, {}


def expected_value(model) -> float:
    """Mean of the critics at the start state and the deterministic action, scaled to [-1, 1] by hand."""
    action, _ = model.predict(START, deterministic=True)
    obs = th.as_tensor(START).reshape(1, -1)
    with th.no_grad():
        if isinstance(model, PPO):
            return float(model.policy.predict_values(obs))
        values = model.critic(obs, th.as_tensor(action / 2.0).reshape(1, -1))
        # TQC: one tensor of quantiles per critic; SAC and SERASAC: a tuple of values
        return float(values.mean() if isinstance(values, th.Tensor) else th.cat(values, dim=1).mean())


class Probe(BaseCallback):
    """Computes the expected V(s0) right after each evaluation, before the model trains again."""

    def __init__(self, every: int) -> None:
        super().__init__()
        self.every, self.values = every, []

    def _on_step(self) -> bool:
        if self.n_calls % self.every == 0:
            self.values.append(expected_value(self.model))
        return True


@pytest.mark.parametrize("algo", [SERASAC, SAC, TQC, PPO])
def test_bias_by_hand(algo, tmp_path):
    kwargs = {"n_steps": 18, "batch_size": 6} if algo is PPO else {"learning_starts": 6, "batch_size": 4}
    model = algo("MlpPolicy", CountingEnv(), gamma=0.5, seed=0, **kwargs)
    eval_env = make_vec_env(CountingEnv, n_envs=2)
    callback = InitialStateBiasCallback(eval_env, eval_freq=9, n_eval_episodes=4, log_path=str(tmp_path), verbose=0)
    model.set_logger(configure(str(tmp_path / "log"), ["csv"]))
    probe = Probe(every=9)
    model.learn(18, callback=[callback, probe])
    # 1 + 0.5 * 2 + 0.25 * 3 = 2.75 for every episode, V(s0) that of the model at the time of the evaluation
    records = np.load(tmp_path / BIAS_FILE)
    assert records["timesteps"].tolist() == [9, 18]
    np.testing.assert_allclose(records["discounted_returns"], np.full((2, 4), 2.75))
    np.testing.assert_allclose(records["values"], np.repeat(np.array(probe.values)[:, None], 4, axis=1), rtol=1e-5)
    # the evaluation's rows of the logger (off-policy training also dumps rows of its own)
    logged = pd.read_csv(tmp_path / "log" / "progress.csv").dropna(subset=["eval/initial_state_bias"])
    np.testing.assert_allclose(logged["eval/initial_state_bias"], np.array(probe.values) - 2.75, rtol=1e-5)
    np.testing.assert_allclose(logged["eval/discounted_return"], [2.75, 2.75])
    assert (tmp_path / "evaluations.npz").exists()


def test_models_without_critics_are_evaluated_without_bias(tmp_path):
    model = DQN("MlpPolicy", "CartPole-v1", learning_starts=10, seed=0)
    callback = InitialStateBiasCallback(
        make_vec_env("CartPole-v1"), eval_freq=20, n_eval_episodes=1, log_path=str(tmp_path), verbose=0
    )
    with pytest.warns(UserWarning, match="DQNPolicy has neither Q critics over Box actions nor a feed-forward value"):
        model.learn(40, callback=callback)
    assert np.load(tmp_path / "evaluations.npz")["timesteps"].tolist() == [20, 40]
    assert not (tmp_path / BIAS_FILE).exists() and callback.bias_timesteps == []


@pytest.mark.parametrize("algo", [SERASAC, SAC])
def test_critic_diagnostics_recorded_at_each_evaluation_without_changing_training(algo, tmp_path):
    def train(record: bool):
        model = algo("MlpPolicy", "Pendulum-v1", learning_starts=50, batch_size=32, seed=0)
        callback = InitialStateBiasCallback(
            make_vec_env("Pendulum-v1", seed=1), eval_freq=100, n_eval_episodes=1, log_path=str(tmp_path / str(record))
        )
        if not record:
            callback._record_critic_diagnostics = lambda: None  # type: ignore[method-assign]
        model.learn(300, callback=callback)
        return model

    model = train(record=True)
    records = np.load(tmp_path / "True" / DIAGNOSTICS_FILE)
    n_critics = 5 if algo is SERASAC else 2
    assert records["timesteps"].tolist() == [100, 200, 300]
    assert records["td_error_corr_matrix"].shape == (3, n_critics, n_critics)
    assert records["critic_corr_matrix"].shape == (3, n_critics, n_critics)
    for index in range(3):
        matrix = records["td_error_corr_matrix"][index]
        off_diagonal = (matrix.sum() - np.trace(matrix)) / (n_critics * (n_critics - 1))
        assert records["td_error_corr"][index] == pytest.approx(off_diagonal, abs=1e-6)
    assert np.all(records["td_target_var"] > 0)
    assert ("critic_lr" in records.files) == (algo is SERASAC)
    # The diagnostics' draws from the replay buffer and the actor leave the training's random streams alone
    unrecorded = train(record=False)
    assert all(th.equal(a, b) for a, b in zip(model.policy.parameters(), unrecorded.policy.parameters(), strict=True))


def test_critic_diagnostics_by_hand():
    # SAC's target y = r + gamma (1 - d) (min_k Qbar_k(s', a') - alpha log pi(a'|s')), recomputed from the same draws
    model = SAC("MlpPolicy", "Pendulum-v1", learning_starts=10, batch_size=16, seed=0).learn(60)
    th.manual_seed(3)
    np.random.seed(3)
    values = critic_diagnostics(model, 64)
    th.manual_seed(3)
    np.random.seed(3)
    batch = model.replay_buffer.sample(64)
    with th.no_grad():
        next_actions, next_log_prob = model.actor.action_log_prob(batch.next_observations)
        next_q = th.min(th.cat(model.critic_target(batch.next_observations, next_actions), dim=1), dim=1, keepdim=True).values
        target = batch.rewards + (1 - batch.dones) * model.gamma * (
            next_q - th.exp(model.log_ent_coef) * next_log_prob.reshape(-1, 1)
        )
        current = th.cat(model.critic(batch.observations, batch.actions), dim=1)
    assert float(values["td_target_var"]) == pytest.approx(float(target.var(unbiased=False)), rel=1e-5)
    expected = np.corrcoef((target - current).numpy().T)
    np.testing.assert_allclose(values["td_error_corr_matrix"], expected, atol=1e-5)


def test_serasac_logs_the_td_error_correlation(tmp_path):
    model = SERASAC("MlpPolicy", "Pendulum-v1", learning_starts=50, batch_size=32, seed=0)
    model.set_logger(configure(str(tmp_path), ["csv"]))
    model.learn(400, log_interval=1)
    progress = pd.read_csv(tmp_path / "progress.csv")
    values = progress["train/td_error_corr"].dropna()
    assert len(values) == 2 and values.between(-1.0, 1.0).all()
    assert "train/critic_corr" in progress


def test_monte_carlo_samples_by_hand():
    episode = [(np.array([t]), np.array([0.0]), float(t + 1)) for t in range(3)]
    # rewards 1, 2, 3 and gamma 0.5: returns-to-go 1 + 0.5 * 2 + 0.25 * 3, 2 + 0.5 * 3, 3
    samples = monte_carlo_samples(episode, 0.5, truncated=False)
    assert [sample[2] for sample in samples] == [2.75, 3.5, 3.0]
    assert [int(sample[0][0]) for sample in samples] == [0, 1, 2]
    # Cut by a time limit after 10 steps: step t's unseen tail weighs 0.5 ** (10 - t), at most 0.01 for t <= 3
    long_episode = [(np.array([t]), np.array([0.0]), 1.0) for t in range(10)]
    kept = monte_carlo_samples(long_episode, 0.5, truncated=True)
    assert len(kept) == 4
    assert kept[3][2] == pytest.approx(sum(0.5**u for u in range(7)))
    assert monte_carlo_samples(long_episode[:6], 0.5, truncated=True) == []
    assert monte_carlo_samples(long_episode, 1.0, truncated=True) == []


def test_monte_carlo_errors_by_hand():
    model = SAC("MlpPolicy", CountingEnv(), learning_starts=6, batch_size=4, seed=0).learn(12)
    rng = np.random.default_rng(0)
    observations = rng.uniform(-1, 1, (7, 2)).astype(np.float32)
    actions = rng.uniform(-2, 2, (7, 1)).astype(np.float32)
    returns = rng.normal(size=7)
    samples = [(observations[i], actions[i], float(returns[i])) for i in range(7)]
    values = monte_carlo_errors(model, samples, n_critics=2)
    with th.no_grad():
        q_values = th.cat(model.critic(th.as_tensor(observations), th.as_tensor(actions / 2.0)), dim=1).numpy()
    errors = q_values - returns[:, None]
    np.testing.assert_allclose(values["mc_error_corr_matrix"], np.corrcoef(errors.T), atol=1e-5)
    np.testing.assert_allclose(values["mc_error_mean"], errors.mean(axis=0), rtol=1e-5)
    np.testing.assert_allclose(values["mc_error_cov_matrix"], np.cov(errors.T, bias=True), rtol=1e-4)
    assert int(values["mc_samples"]) == 7
    empty = monte_carlo_errors(model, samples[:1], n_critics=2)
    assert np.isnan(empty["mc_error_corr_matrix"]).all() and int(empty["mc_samples"]) == 1


@pytest.mark.parametrize("algo", [SERASAC, SAC])
def test_evaluation_episodes_give_the_monte_carlo_errors(algo, tmp_path):
    # learning_starts above the budget: the critics the evaluations saw are the model's after learn()
    model = algo("MlpPolicy", CountingEnv(), learning_starts=30, batch_size=4, gamma=0.5, seed=0)
    eval_env = make_vec_env(CountingEnv, n_envs=2)
    callback = InitialStateBiasCallback(eval_env, eval_freq=9, n_eval_episodes=4, log_path=str(tmp_path), verbose=0)
    model.learn(18, callback=callback)
    records = np.load(tmp_path / DIAGNOSTICS_FILE)
    n_critics = 5 if algo is SERASAC else 2
    # Four episodes of three terminated steps each at each evaluation
    assert records["mc_samples"].tolist() == [12, 12]
    assert records["mc_error_corr_matrix"].shape == (2, n_critics, n_critics)
    assert records["mc_error_mean"].shape == (2, n_critics)
    # The last evaluation's errors, recomputed: every episode repeats START, the deterministic action, and the
    # returns-to-go 2.75, 3.5, 3 (rewards 1, 2, 3, gamma 0.5), so each critic's mean error is its value minus 3.0833
    action, _ = model.predict(START, deterministic=True)
    with th.no_grad():
        q_values = model.critic(th.as_tensor(START).reshape(1, -1), th.as_tensor(action / 2.0).reshape(1, -1))
    expected = th.cat(q_values, dim=1).numpy()[0] - np.mean([2.75, 3.5, 3.0])
    np.testing.assert_allclose(records["mc_error_mean"][-1], expected, rtol=1e-5)
    assert {"td_target_mean", "critic_cov_matrix", "td_error_cov_matrix"} <= set(records.files)


def test_serasac_td_targets_by_hand():
    # y = r + gamma (1 - d) (SERA aggregate of the target critics at a' ~ pi(s') - alpha log pi(a'|s'))
    from sb3_sera.sera.aggregation import aggregate_target

    model = SERASAC("MlpPolicy", "Pendulum-v1", learning_starts=10, batch_size=16, seed=0).learn(60)
    batch = model.replay_buffer.sample(32)
    th.manual_seed(5)
    targets, values = model.td_targets(batch)
    th.manual_seed(5)
    with th.no_grad():
        next_actions, next_log_prob = model.actor.action_log_prob(batch.next_observations)
        aggregate = aggregate_target(model.critic_target.q_values(batch.next_observations, next_actions), "sera").unsqueeze(1)
        expected = batch.rewards + (1 - batch.dones) * model.gamma * (
            aggregate - th.exp(model.log_ent_coef) * next_log_prob.reshape(-1, 1)
        )
        np.testing.assert_allclose(targets.numpy(), expected.numpy(), rtol=1e-6)
        np.testing.assert_allclose(values.numpy(), model.critic.q_values(batch.observations, batch.actions).numpy())
    assert values.shape == (32, 5) and not values.requires_grad
