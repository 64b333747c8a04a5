"""
Evaluation that also measures the initial-state value bias of the critics (paper section 6, Fig. 4a) and, for the SAC
family, the critics' TD-target variance and correlations on a replay batch (Fig. 4c and 5), and the correlation of
their errors against the Monte Carlo returns of the evaluation episodes (a measure of synchronisation that the values'
own correlation, dominated by each state's value, cannot show).
"""

import inspect
import math
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.callbacks import EvalCallback
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.sac import SAC
from torch import nn

from sb3_sera.common.capabilities import OwnTDTargets, PerCriticRates, as_the_model_sees, capability
from sb3_sera.common.correlation import correlation_matrix, mean_off_diagonal
from sb3_sera.common.targets import sac_td_target

#: Files written beside ``evaluations.npz`` in the callback's ``log_path``
BIAS_FILE = "initial_state_bias.npz"
DIAGNOSTICS_FILE = "critic_diagnostics.npz"
#: Weight of a truncated episode's unseen tail (``gamma ** steps_left``) above which a step's return-to-go is not
#: used as a Monte Carlo return
MC_TAIL_WEIGHT = 0.01


class InitialStateBiasCallback(EvalCallback):
    """
    SB3's :class:`~stable_baselines3.common.callbacks.EvalCallback` that, in the same evaluation episodes, records
    the value the critics give the first state and action of each episode, ``V(s0) = 1/K sum_k Q_k(s0, a0)``
    (the state value ``V(s0)`` for an on-policy actor-critic), the episode's discounted return
    ``sum_t gamma^t r_t``, and their difference, the initial-state bias ``b = V(s0) - sum_t gamma^t r_t``.

    Per evaluation, the means over episodes go to the logger (``eval/initial_state_value``,
    ``eval/discounted_return``, ``eval/initial_state_bias``) and, with a ``log_path``, to ``initial_state_bias.npz``
    (``timesteps``, ``values``, ``discounted_returns``, one row per evaluation and one column per episode).
    For a model of the SAC family (SAC, MASAC, SERASAC) with a filled replay buffer, each evaluation also records
    :func:`critic_diagnostics` on ``diagnostics_batch_size`` replayed transitions to ``critic_diagnostics.npz``
    (one row per evaluation), with the random generators' states put back so that training is unchanged, and
    :func:`monte_carlo_errors` on the evaluation's own steps: each critic's error against the discounted return
    that followed each step of the evaluation episodes (steps of an episode cut by a time limit count only while
    the unseen tail weighs at most ``MC_TAIL_WEIGHT``, i.e. ``gamma ** steps_left <= 0.01``).
    Takes the arguments of ``EvalCallback``. For a model with neither Q critics over Box actions nor a
    feed-forward value function (DQN, recurrent policies), it warns once and evaluates as ``EvalCallback`` does.

    :param diagnostics_batch_size: transitions drawn from the replay buffer for the critic diagnostics
    """

    def __init__(self, *args: Any, diagnostics_batch_size: int = 1024, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.diagnostics_batch_size = diagnostics_batch_size
        #: Per evaluation, :func:`critic_diagnostics` of the model (SAC family only)
        self.diagnostics: dict[str, list[np.ndarray]] = {}
        self._values: list[float] = []
        self._returns: list[float] = []
        self._running: dict[int, tuple[float, float]] = {}
        # Per env, the evaluation episode under way: observations, actions and rewards; per evaluation, the steps
        # kept as Monte Carlo samples (observation, action, discounted return that followed)
        self._episodes: dict[int, list[tuple[Any, np.ndarray, float]]] = {}
        self._mc_samples: list[tuple[Any, np.ndarray, float]] = []
        self.bias_timesteps: list[int] = []
        self.bias_values: list[list[float]] = []
        self.bias_returns: list[list[float]] = []
        #: Whether the model has critics or a value function to evaluate (set when training starts)
        self.records_bias = False

    def _init_callback(self) -> None:
        # A model acting on per-episode latents (IET): its evaluation episodes draw them as its training episodes do,
        # from a generator of their own seeded with the model's seed, so that evaluations are repeatable and leave
        # training's random streams alone (an env already holding them, a resumed run's, is kept)
        self.eval_env = as_the_model_sees(self.model, self.eval_env)
        super()._init_callback()
        policy = self.model.policy
        self.records_bias = _has_value_function(policy) or (
            isinstance(policy.action_space, spaces.Box) and isinstance(getattr(policy, "critic", None), nn.Module)
        )
        if not self.records_bias:
            warnings.warn(
                f"InitialStateBiasCallback: {type(policy).__name__} has neither Q critics over Box actions nor a "
                "feed-forward value function, so the initial-state bias is not recorded; evaluations go on as usual",
                stacklevel=2,
            )

    def _initial_value(self, observation: Any, action: np.ndarray) -> float:
        policy = self.model.policy
        with th.no_grad():
            obs_tensor, _ = policy.obs_to_tensor(observation)
            if _has_value_function(policy):
                return float(cast(ActorCriticPolicy, policy).predict_values(obs_tensor).mean())
            action_tensor = th.as_tensor(policy.scale_action(action), device=policy.device).float().reshape(1, -1)
            # SB3's critics (and SERASAC's ensemble) return one value per critic, sb3-contrib's TQC one tensor of
            # quantiles per critic: the mean over all of them either way
            values = cast(nn.Module, policy.critic)(obs_tensor, action_tensor)
            q_values = values if isinstance(values, th.Tensor) else th.cat(values, dim=1)
        return float(q_values.mean())

    def _log_success_callback(self, locals_: dict[str, Any], globals_: dict[str, Any]) -> None:
        super()._log_success_callback(locals_, globals_)
        if not self.records_bias:
            return
        env_index, step = locals_["i"], int(locals_["current_lengths"][locals_["i"]]) - 1
        observation = observation_at(locals_["observations"], env_index)
        if step == 0:
            self._running[env_index] = (self._initial_value(observation, locals_["actions"][env_index]), 0.0)
            self._episodes[env_index] = []
        value, discounted_return = self._running[env_index]
        gamma = float(self.model.gamma)  # type: ignore[attr-defined]
        discounted_return += gamma**step * float(locals_["reward"])
        self._running[env_index] = (value, discounted_return)
        self._episodes[env_index].append((observation, locals_["actions"][env_index], float(locals_["reward"])))
        # evaluate_policy's own rule for the end of an episode (a Monitor-wrapped env's lost life is not one)
        if locals_["done"] and (not locals_["is_monitor_wrapped"] or "episode" in locals_["info"]):
            truncated = bool(locals_["info"].get("TimeLimit.truncated", False))
            self._mc_samples.extend(monte_carlo_samples(self._episodes.pop(env_index), gamma, truncated))
            self._values.append(value)
            self._returns.append(discounted_return)
            # Recorded after every episode: the logger keeps the last value, the mean over the whole evaluation
            self.logger.record("eval/initial_state_value", float(np.mean(self._values)))
            self.logger.record("eval/discounted_return", float(np.mean(self._returns)))
            self.logger.record("eval/initial_state_bias", initial_state_bias([self._values], [self._returns])[0])

    def _on_step(self) -> bool:
        evaluating = self.eval_freq > 0 and self.n_calls % self.eval_freq == 0
        if evaluating:
            self._values, self._returns, self._running = [], [], {}
            self._episodes, self._mc_samples = {}, []
        continue_training = super()._on_step()
        if evaluating and self.records_bias:
            self.bias_timesteps.append(self.num_timesteps)
            self.bias_values.append(self._values)
            self.bias_returns.append(self._returns)
            if self.log_path is not None:
                np.savez(
                    Path(self.log_path).parent / BIAS_FILE,
                    timesteps=self.bias_timesteps,
                    values=self.bias_values,
                    discounted_returns=self.bias_returns,
                )
        if evaluating:
            self._record_critic_diagnostics()
        return continue_training

    def _record_critic_diagnostics(self) -> None:
        model = self.model
        buffer = getattr(model, "replay_buffer", None)
        if not capability(model, "soft_q_critics") or buffer is None or buffer.size() == 0:
            return
        model = cast(SAC, model)
        numpy_state = np.random.get_state()
        devices = [model.device] if model.device.type == "cuda" else []
        with th.random.fork_rng(devices=devices):
            values = critic_diagnostics(model, self.diagnostics_batch_size)
        np.random.set_state(numpy_state)
        values.update(monte_carlo_errors(model, self._mc_samples, n_critics=values["critic_corr_matrix"].shape[0]))
        values["timesteps"] = np.array(self.num_timesteps)
        for key, value in values.items():
            self.diagnostics.setdefault(key, []).append(value)
        for key in ("td_target_var", "critic_corr", "td_error_corr", "mc_error_corr"):
            self.logger.record(f"eval/{key}", float(values[key]))
        if self.log_path is not None:
            arrays: dict[str, Any] = {key: np.stack(value) for key, value in self.diagnostics.items()}
            np.savez(Path(self.log_path).parent / DIAGNOSTICS_FILE, **arrays)


def critic_diagnostics(model: SAC, batch_size: int) -> dict[str, np.ndarray]:
    """
    The critics of a SAC-family model on ``batch_size`` transitions from its replay buffer: the TD target ``y`` the
    model trains on (SERASAC: its aggregation of the target critics; SAC and MASAC: the minimum of the twin target
    critics), the online values ``Q_i(s, a)`` and the TD errors ``delta_i = y - Q_i(s, a)``.

    :return: ``td_target_var`` (batch variance of ``y``) and ``td_target_mean`` (its batch mean, the scale that
        normalises the variance), ``critic_corr_matrix`` and ``td_error_corr_matrix`` (K x K Pearson correlations over
        the batch of the values and of the TD errors), their mean off-diagonal entries ``critic_corr`` and
        ``td_error_corr``, ``critic_cov_matrix`` and ``td_error_cov_matrix`` (the K x K covariances, from which any
        other linear measure of the critics can be derived), and for SERASAC the critics' current learning rates
        ``critic_lr`` (K values)
    """
    assert model.replay_buffer is not None
    replay_data = model.replay_buffer.sample(batch_size, env=model.get_vec_normalize_env())
    with th.no_grad():
        if capability(model, "own_td_targets"):
            target_q_values, current_q_values = cast(OwnTDTargets, model).td_targets(replay_data)
        else:
            target_q_values, current_q_values = sac_td_targets(model, replay_data)
        critic_corr = correlation_matrix(current_q_values)
        td_error_corr = correlation_matrix(target_q_values - current_q_values)
        td_errors = target_q_values - current_q_values
        values = {
            "td_target_var": target_q_values.var(unbiased=False),
            "td_target_mean": target_q_values.mean(),
            "critic_corr_matrix": critic_corr,
            "critic_corr": mean_off_diagonal(critic_corr),
            "td_error_corr_matrix": td_error_corr,
            "td_error_corr": mean_off_diagonal(td_error_corr),
            "critic_cov_matrix": th.cov(current_q_values.T, correction=0),
            "td_error_cov_matrix": th.cov(td_errors.T, correction=0),
        }
    result = {key: value.cpu().numpy() for key, value in values.items()}
    if capability(model, "per_critic_rates"):
        result["critic_lr"] = np.array(cast(PerCriticRates, model).critic_learning_rates())
    return result


def sac_td_targets(model: SAC, replay_data: ReplayBufferSamples) -> tuple[th.Tensor, th.Tensor]:
    """
    SB3's SAC target for a replayed batch (:func:`~sb3_sera.common.targets.sac_td_target`, at the model's entropy
    coefficient) and the online critics' values ``Q_k(s, a)``: ``(S, 1)`` and ``(S, K)``.
    """
    ent_coef = th.exp(model.log_ent_coef.detach()) if model.log_ent_coef is not None else model.ent_coef_tensor
    target_q_values = sac_td_target(model.actor, model.critic_target, replay_data, ent_coef, model.gamma)
    return target_q_values, th.cat(model.critic(replay_data.observations, replay_data.actions), dim=1)


def observation_at(observations: Any, index: int) -> Any:
    """A copy of observation ``index`` of a vectorized batch (a Dict observation: each key's row)."""
    if isinstance(observations, dict):
        return {key: np.array(value[index]) for key, value in observations.items()}
    return np.array(observations[index])


def monte_carlo_samples(
    episode: Sequence[tuple[Any, np.ndarray, float]], gamma: float, truncated: bool
) -> list[tuple[Any, np.ndarray, float]]:
    """
    The steps of one episode whose discounted return-to-go ``G_t = sum_{u >= t} gamma^(u-t) r_u`` is a Monte Carlo
    return of ``(s_t, a_t)``: every step of an episode that ended in a terminal state; of one cut by a time limit,
    the steps whose unseen tail weighs ``gamma ** steps_left <= MC_TAIL_WEIGHT``.

    :param episode: ``(observation, action, reward)`` per step
    :return: ``(observation, action, G_t)`` per kept step
    """
    returns = np.zeros(len(episode))
    running = 0.0
    for t in range(len(episode) - 1, -1, -1):
        running = episode[t][2] + gamma * running
        returns[t] = running
    kept = len(episode)
    if truncated:
        # Step t's unseen tail weighs gamma ** (len - t): kept while len - t >= the horizon where it falls to the limit
        if gamma >= 1.0:
            kept = 0
        elif gamma > 0.0:
            horizon = math.ceil(math.log(MC_TAIL_WEIGHT) / math.log(gamma))
            kept = max(len(episode) - horizon + 1, 0)
    return [(observation, action, float(returns[t])) for t, (observation, action, _) in enumerate(episode[:kept])]


def monte_carlo_errors(model: SAC, samples: Sequence[tuple[Any, np.ndarray, float]], n_critics: int) -> dict[str, np.ndarray]:
    """
    Each critic's error against Monte Carlo returns, ``e_i = Q_i(s, a) - G`` over the ``(s, a, G)`` samples of
    :func:`monte_carlo_samples`, and how the critics' errors move together.

    Unlike the correlation of the values (near 1 for any trained ensemble, since values differ most between states)
    this correlation is high only when the critics make the same errors: the synchronisation the paper's Fig. 5
    attributes to a shared step size. The errors include whatever separates the critics' target (the soft value of
    the stochastic policy) from the deterministic evaluation policy's return; that part is common to the critics
    and to the variants compared.

    :return: ``mc_error_corr_matrix`` and ``mc_error_cov_matrix`` (K x K, over the samples), ``mc_error_corr`` (mean
        off-diagonal correlation), ``mc_error_mean`` (K mean errors) and ``mc_samples`` (the number of samples);
        NaN where fewer than two samples were kept
    """
    nan_matrix = np.full((n_critics, n_critics), np.nan, dtype=np.float32)
    if len(samples) < 2:
        return {
            "mc_error_corr_matrix": nan_matrix,
            "mc_error_cov_matrix": nan_matrix.copy(),
            "mc_error_corr": np.array(np.nan, dtype=np.float32),
            "mc_error_mean": np.full(n_critics, np.nan, dtype=np.float32),
            "mc_samples": np.array(len(samples)),
        }
    policy = model.policy
    first = samples[0][0]
    if isinstance(first, dict):
        observations: Any = {key: np.stack([sample[0][key] for sample in samples]) for key in first}
    else:
        observations = np.stack([sample[0] for sample in samples])
    actions = np.stack([sample[1] for sample in samples]).reshape(len(samples), -1)
    returns = th.as_tensor(np.array([sample[2] for sample in samples]), dtype=th.float32, device=policy.device)
    with th.no_grad():
        obs_tensor, _ = policy.obs_to_tensor(observations)
        action_tensor = th.as_tensor(policy.scale_action(actions), device=policy.device).float()
        values = cast(nn.Module, policy.critic)(obs_tensor, action_tensor)
        # TQC's critics return quantiles (batch, critics, quantiles): a critic's value is their mean
        q_values = values.mean(dim=-1) if isinstance(values, th.Tensor) else th.cat(values, dim=1)
        errors = q_values - returns.reshape(-1, 1)
        corr = correlation_matrix(errors)
        result = {
            "mc_error_corr_matrix": corr,
            "mc_error_cov_matrix": th.cov(errors.T, correction=0),
            "mc_error_corr": mean_off_diagonal(corr),
            "mc_error_mean": errors.mean(dim=0),
        }
    return {**{key: value.cpu().numpy() for key, value in result.items()}, "mc_samples": np.array(len(samples))}


def initial_state_bias(values: Sequence[Sequence[float]], discounted_returns: Sequence[Sequence[float]]) -> list[float]:
    """Per evaluation, the mean initial-state value minus the mean discounted return of its episodes."""
    return [float(np.mean(v) - np.mean(r)) for v, r in zip(values, discounted_returns, strict=True)]


def _has_value_function(policy: Any) -> bool:
    """An on-policy actor-critic whose value function takes the observation alone (not a recurrent one)."""
    return isinstance(policy, ActorCriticPolicy) and len(inspect.signature(policy.predict_values).parameters) == 1
