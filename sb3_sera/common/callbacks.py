"""
Evaluation that also measures the initial-state value bias of the critics (paper section 6, Fig. 4a) and, for the SAC
family, the critics' TD-target variance and correlations on a replay batch (Fig. 4c and 5).
"""

import inspect
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.callbacks import EvalCallback
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.sac import SAC
from torch import nn

from sb3_sera.iet import IET
from sb3_sera.sera import SERASAC
from sb3_sera.sera.aggregation import correlation_matrix, mean_off_diagonal

#: Files written beside ``evaluations.npz`` in the callback's ``log_path``
BIAS_FILE = "initial_state_bias.npz"
DIAGNOSTICS_FILE = "critic_diagnostics.npz"


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
    (one row per evaluation), with the random generators' states put back so that training is unchanged.
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
        self.bias_timesteps: list[int] = []
        self.bias_values: list[list[float]] = []
        self.bias_returns: list[list[float]] = []
        #: Whether the model has critics or a value function to evaluate (set when training starts)
        self.records_bias = False

    def _init_callback(self) -> None:
        if isinstance(self.model, IET):
            # IET's evaluation episodes draw their latents as its training episodes do, from a generator of their own
            # seeded with the model's seed: evaluations are repeatable and leave training's random streams alone
            self.eval_env = self.model.with_latents(self.eval_env, seed=self.model.seed)
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
        if step == 0:
            observations = locals_["observations"]
            if isinstance(observations, dict):
                observation: Any = {key: value[env_index] for key, value in observations.items()}
            else:
                observation = observations[env_index]
            self._running[env_index] = (self._initial_value(observation, locals_["actions"][env_index]), 0.0)
        value, discounted_return = self._running[env_index]
        discounted_return += float(self.model.gamma) ** step * float(locals_["reward"])  # type: ignore[attr-defined]
        self._running[env_index] = (value, discounted_return)
        # evaluate_policy's own rule for the end of an episode (a Monitor-wrapped env's lost life is not one)
        if locals_["done"] and (not locals_["is_monitor_wrapped"] or "episode" in locals_["info"]):
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
        if not isinstance(model, SAC) or buffer is None or buffer.size() == 0:
            return
        numpy_state = np.random.get_state()
        devices = [model.device] if model.device.type == "cuda" else []
        with th.random.fork_rng(devices=devices):
            values = critic_diagnostics(model, self.diagnostics_batch_size)
        np.random.set_state(numpy_state)
        values["timesteps"] = np.array(self.num_timesteps)
        for key, value in values.items():
            self.diagnostics.setdefault(key, []).append(value)
        for key in ("td_target_var", "critic_corr", "td_error_corr"):
            self.logger.record(f"eval/{key}", float(values[key]))
        if self.log_path is not None:
            arrays: dict[str, Any] = {key: np.stack(value) for key, value in self.diagnostics.items()}
            np.savez(Path(self.log_path).parent / DIAGNOSTICS_FILE, **arrays)


def critic_diagnostics(model: SAC, batch_size: int) -> dict[str, np.ndarray]:
    """
    The critics of a SAC-family model on ``batch_size`` transitions from its replay buffer: the TD target ``y`` the
    model trains on (SERASAC: its aggregation of the target critics; SAC and MASAC: the minimum of the twin target
    critics), the online values ``Q_i(s, a)`` and the TD errors ``delta_i = y - Q_i(s, a)``.

    :return: ``td_target_var`` (batch variance of ``y``), ``critic_corr_matrix`` and ``td_error_corr_matrix``
        (K x K Pearson correlations over the batch of the values and of the TD errors), their mean off-diagonal
        entries ``critic_corr`` and ``td_error_corr``, and for SERASAC the critics' current learning rates
        ``critic_lr`` (K values)
    """
    assert model.replay_buffer is not None
    replay_data = model.replay_buffer.sample(batch_size, env=model._vec_normalize_env)
    discounts = replay_data.discounts if replay_data.discounts is not None else model.gamma
    with th.no_grad():
        ent_coef = th.exp(model.log_ent_coef) if model.log_ent_coef is not None else model.ent_coef_tensor
        next_actions, next_log_prob = model.actor.action_log_prob(replay_data.next_observations)
        next_log_prob = next_log_prob.reshape(-1, 1)
        if isinstance(model, SERASAC):
            update = model._critic_update_eager(
                replay_data.observations,
                replay_data.actions,
                replay_data.next_observations,
                replay_data.rewards,
                replay_data.dones,
                discounts,
                next_actions,
                next_log_prob,
                ent_coef,
            )
            target_q_values, current_q_values = update.target_q_values, update.current_q_values
        else:
            next_q_values = th.cat(model.critic_target(replay_data.next_observations, next_actions), dim=1)
            next_q = th.min(next_q_values, dim=1, keepdim=True).values - ent_coef * next_log_prob
            target_q_values = replay_data.rewards + (1 - replay_data.dones) * discounts * next_q
            current_q_values = th.cat(model.critic(replay_data.observations, replay_data.actions), dim=1)
        critic_corr = correlation_matrix(current_q_values)
        td_error_corr = correlation_matrix(target_q_values - current_q_values)
        values = {
            "td_target_var": target_q_values.var(unbiased=False),
            "critic_corr_matrix": critic_corr,
            "critic_corr": mean_off_diagonal(critic_corr),
            "td_error_corr_matrix": td_error_corr,
            "td_error_corr": mean_off_diagonal(td_error_corr),
        }
    result = {key: value.cpu().numpy() for key, value in values.items()}
    if isinstance(model, SERASAC):
        rates = {group["critic_index"]: group["lr"] for group in model.critic.optimizer.param_groups}
        result["critic_lr"] = np.array([rates[index] for index in range(model.critic.n_critics)])
    return result


def initial_state_bias(values: Sequence[Sequence[float]], discounted_returns: Sequence[Sequence[float]]) -> list[float]:
    """Per evaluation, the mean initial-state value minus the mean discounted return of its episodes."""
    return [float(np.mean(v) - np.mean(r)) for v, r in zip(values, discounted_returns, strict=True)]


def _has_value_function(policy: Any) -> bool:
    """An on-policy actor-critic whose value function takes the observation alone (not a recurrent one)."""
    return isinstance(policy, ActorCriticPolicy) and len(inspect.signature(policy.predict_values).parameters) == 1
