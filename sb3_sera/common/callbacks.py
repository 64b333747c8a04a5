"""Evaluation that also measures the initial-state value bias of the critics (paper section 6, Fig. 4a)."""

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
from torch import nn

#: File written beside ``evaluations.npz`` in the callback's ``log_path``
BIAS_FILE = "initial_state_bias.npz"


class InitialStateBiasCallback(EvalCallback):
    """
    SB3's :class:`~stable_baselines3.common.callbacks.EvalCallback` that, in the same evaluation episodes, records
    the value the critics give the first state and action of each episode, ``V(s0) = 1/K sum_k Q_k(s0, a0)``
    (the state value ``V(s0)`` for an on-policy actor-critic), the episode's discounted return
    ``sum_t gamma^t r_t``, and their difference, the initial-state bias ``b = V(s0) - sum_t gamma^t r_t``.

    Per evaluation, the means over episodes go to the logger (``eval/initial_state_value``,
    ``eval/discounted_return``, ``eval/initial_state_bias``) and, with a ``log_path``, to ``initial_state_bias.npz``
    (``timesteps``, ``values``, ``discounted_returns``, one row per evaluation and one column per episode).
    Takes the arguments of ``EvalCallback``. For a model with neither Q critics over Box actions nor a
    feed-forward value function (DQN, recurrent policies), it warns once and evaluates as ``EvalCallback`` does.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._values: list[float] = []
        self._returns: list[float] = []
        self._running: dict[int, tuple[float, float]] = {}
        self.bias_timesteps: list[int] = []
        self.bias_values: list[list[float]] = []
        self.bias_returns: list[list[float]] = []
        #: Whether the model has critics or a value function to evaluate (set when training starts)
        self.records_bias = False

    def _init_callback(self) -> None:
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
        return continue_training


def initial_state_bias(values: Sequence[Sequence[float]], discounted_returns: Sequence[Sequence[float]]) -> list[float]:
    """Per evaluation, the mean initial-state value minus the mean discounted return of its episodes."""
    return [float(np.mean(v) - np.mean(r)) for v, r in zip(values, discounted_returns, strict=True)]


def _has_value_function(policy: Any) -> bool:
    """An on-policy actor-critic whose value function takes the observation alone (not a recurrent one)."""
    return isinstance(policy, ActorCriticPolicy) and len(inspect.signature(policy.predict_values).parameters) == 1
