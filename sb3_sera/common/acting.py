"""
The action ``learn()`` takes, without what SB3's ``predict`` does for inputs ``learn()`` cannot give it (``docs/speed.md``,
"The host floor"): ``learn()`` acts on the vectorized env's last observation, a NumPy array (or a dict of them) of the
observation space's shape with one row per env, so the checks and conversions ``predict`` makes for a single
observation, a Gym-API tuple or an image to transpose are not needed.
"""

from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.distributions import SquashedDiagGaussianDistribution
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.preprocessing import is_image_space
from stable_baselines3.sac.policies import Actor as SACActor
from stable_baselines3.sac.policies import SACPolicy


def acts_directly(policy: BasePolicy) -> bool:
    """
    Whether :func:`learn_action` gives ``policy``'s action as its ``predict`` would: the policy keeps SB3's
    ``predict`` and observation conversion, and no observation is an image (``predict`` may transpose those).
    """
    space = policy.observation_space
    parts = list(space.spaces.values()) if isinstance(space, spaces.Dict) else [space]
    return (
        type(policy).predict is BasePolicy.predict
        and type(policy).obs_to_tensor is BasePolicy.obs_to_tensor
        and all(isinstance(part, spaces.Box) and not is_image_space(part) for part in parts)
    )


def learn_action(policy: BasePolicy, observation: np.ndarray | dict[str, np.ndarray]) -> np.ndarray:
    """
    ``policy.predict(observation, deterministic=False)[0]`` for a vectorized observation of a policy that
    :func:`acts_directly`: evaluation mode, the observation as a tensor on the policy's device (a copy, as SB3 makes),
    the policy's ``_predict`` without gradients (:func:`squashed_gaussian_action` where it has a
    :func:`drawing_actor`), and the action in the action space's bounds, as ``predict`` gives it.
    """
    policy.set_training_mode(False)
    device = policy.device
    if isinstance(observation, dict):
        obs: Any = {key: th.tensor(value, device=device) for key, value in observation.items()}
    else:
        obs = th.tensor(observation, device=device)
    actor = drawing_actor(policy)
    with th.no_grad():
        actions = squashed_gaussian_action(actor, obs) if actor is not None else policy._predict(obs, deterministic=False)
    action_space = policy.action_space
    result = actions.cpu().numpy().reshape((-1, *action_space.shape))  # type: ignore[misc, arg-type]
    if actor is not None and np.isnan(result).any():
        # SB3's draw checks its distribution's parameters: its error (a NaN mean or scale), or its NaN action
        return policy.predict(observation, deterministic=False)[0]
    if isinstance(action_space, spaces.Box):
        if policy.squash_output:
            return policy.unscale_action(result)
        return np.clip(result, action_space.low, action_space.high)
    return result


def drawing_actor(policy: BasePolicy) -> SACActor | None:
    """
    ``policy``'s actor where its stochastic action is SB3's SAC actor's squashed Gaussian draw, which
    :func:`squashed_gaussian_action` makes without ``torch.distributions`` (the policy keeps SAC's ``_predict``, its
    actor is SB3's SAC ``Actor`` itself, no subclass, without gSDE); None otherwise.
    """
    actor = getattr(policy, "actor", None)
    if (
        type(policy)._predict is SACPolicy._predict
        and type(actor) is SACActor
        and not actor.use_sde
        and isinstance(actor.action_dist, SquashedDiagGaussianDistribution)
    ):
        return actor
    return None


def squashed_gaussian_action(actor: SACActor, observation: th.Tensor) -> th.Tensor:
    """
    ``actor(observation)``'s stochastic action, computed as torch's ``Normal.rsample`` and SB3's squashing compute it
    (the same draw from torch's generator, the same operations: ``tanh(mean + eps * std)``), without building the
    distribution objects. Unlike SB3's, it does not check the mean and the scale: :func:`learn_action` checks the
    action for NaN.
    """
    mean_actions, log_std, _ = actor.get_action_dist_params(observation)
    action_std = th.ones_like(mean_actions) * log_std.exp()
    noise = th.empty(mean_actions.shape, dtype=mean_actions.dtype, device=mean_actions.device).normal_()
    return th.tanh(mean_actions + noise * action_std)


class LearnActions(OffPolicyAlgorithm):
    """
    An off-policy algorithm whose ``learn()`` takes its actions through :func:`learn_action` where the policy
    :func:`acts_directly` (the same actions as SB3's ``predict``, drawn from the same generator), and through SB3's
    ``predict`` otherwise. ``predict`` called by a user is SB3's.
    """

    #: Whether the action being sampled is ``learn()``'s (set by ``_sample_action``)
    _sampling_action: bool = False
    #: The policy :func:`acts_directly` was last asked about, and its answer
    _direct_policy: tuple[BasePolicy | None, bool] = (None, False)

    def _sample_action(self, *args: Any, **kwargs: Any) -> tuple[np.ndarray, np.ndarray]:
        self._sampling_action = True
        try:
            return super()._sample_action(*args, **kwargs)
        finally:
            self._sampling_action = False

    def predict(
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """SB3's ``predict`` (see :meth:`stable_baselines3.common.base_class.BaseAlgorithm.predict`)."""
        if self._sampling_action and not deterministic and state is None and self._acts_directly():
            return learn_action(self.policy, observation), None
        return super().predict(observation, state, episode_start, deterministic)

    def _acts_directly(self) -> bool:
        if self._direct_policy[0] is not self.policy:
            self._direct_policy = (self.policy, acts_directly(self.policy))
        return self._direct_policy[1]

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "_direct_policy", "_sampling_action"]
