"""
CTDE policies: one actor per agent reading only its own observation, centralized critics on the state and the
joint action (SPEC section 2). The off-policy policies reuse SB3's per-algorithm actors, one per agent.
"""

from typing import Any, cast

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.policies import BaseModel, BasePolicy
from stable_baselines3.common.preprocessing import get_flattened_obs_dim
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, FlattenExtractor
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from stable_baselines3.common.vec_env import VecEnv
from stable_baselines3.sac.policies import Actor as SACActor
from stable_baselines3.sac.policies import SACPolicy
from stable_baselines3.td3.policies import Actor as TD3Actor
from stable_baselines3.td3.policies import TD3Policy
from torch import nn

from sb3_sera.ctde.env import STATE_KEY
from sb3_sera.sera.policies import SERAPolicy


class StateExtractor(BaseFeaturesExtractor):
    """The centralized critics' features: the ``state`` entry of a CTDE observation, flattened."""

    def __init__(self, observation_space: spaces.Dict):
        super().__init__(observation_space, get_flattened_obs_dim(observation_space[STATE_KEY]))

    def forward(self, observations: dict[str, th.Tensor]) -> th.Tensor:
        return th.flatten(observations[STATE_KEY], start_dim=1)


def agent_action_dims_of(env: VecEnv) -> dict[str, int]:
    """The agents of a (vectorized) :class:`~sb3_sera.ctde.env.CTDEEnv` and the size of each one's action."""
    try:
        slices: dict[str, slice] = env.get_attr("action_slices", indices=[0])[0]
    except AttributeError as error:
        raise ValueError(
            "The CTDE policies need a CTDEEnv (e.g. gymnasium.make('sb3_sera/HalfCheetah-6x1-v0') or "
            "CTDEEnv(pettingzoo_parallel_env)), or policy_kwargs=dict(agent_action_dims={agent: size, ...})"
        ) from error
    return {agent: part.stop - part.start for agent, part in slices.items()}


def fill_agent_layout(model: BaseAlgorithm) -> None:
    """Give a CTDE policy the agents' action sizes, read from the model's CTDEEnv, unless already given."""
    policy_kwargs: dict[str, Any] = model.policy_kwargs
    if is_ctde_policy(model.policy_class) and "agent_action_dims" not in policy_kwargs:
        if model.env is None:
            raise ValueError("A CTDE policy needs an env, or policy_kwargs=dict(agent_action_dims=...)")
        policy_kwargs["agent_action_dims"] = agent_action_dims_of(model.env)


def check_layout(observation_space: spaces.Space, action_space: spaces.Space, agent_action_dims: dict[str, int]) -> None:
    """Raise ``ValueError`` unless the spaces are those of a CTDEEnv with these agents and action sizes."""
    if not isinstance(observation_space, spaces.Dict) or STATE_KEY not in observation_space.spaces:
        raise ValueError(f"CTDE policies need a Dict observation space with a {STATE_KEY!r} entry, got {observation_space}")
    missing = [agent for agent in agent_action_dims if agent not in observation_space.spaces]
    if missing:
        raise ValueError(f"Agents {missing} have no observation in {observation_space}")
    total = sum(agent_action_dims.values())
    if not isinstance(action_space, spaces.Box) or action_space.shape != (total,):
        raise ValueError(f"The joint action space {action_space} does not hold the agents' actions {agent_action_dims}")


class CTDEActor(BaseModel):
    """
    One SB3 actor per agent, each reading only its agent's observation; the joint action is their concatenation
    in agent order, and (SAC family) the joint log-probability the sum of theirs.

    :param observation_space: the CTDE Dict observation space
    :param action_space: the joint action space
    :param agent_action_dims: the agents, in joint-action order, and their action sizes
    :param agent_actor_class: SB3's actor of the algorithm (``sac.policies.Actor`` or ``td3.policies.Actor``)
    :param agent_actor_kwargs: its keyword arguments, but for the spaces and the features extractor
    :param share_parameters: one actor for all agents (their observation and action spaces must be equal)
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        agent_action_dims: dict[str, int],
        agent_actor_class: type[BasePolicy],
        agent_actor_kwargs: dict[str, Any],
        share_parameters: bool = False,
    ):
        super().__init__(observation_space, action_space)
        self.agents = list(agent_action_dims)
        self.agent_action_dims = dict(agent_action_dims)
        self.share_parameters = share_parameters
        boxes = {agent: observation_space[agent] for agent in self.agents}
        if share_parameters:
            shapes = {agent: (boxes[agent].shape, agent_action_dims[agent]) for agent in self.agents}
            if len(set(shapes.values())) > 1:
                raise ValueError(
                    "share_actor=True needs agents with equal observation and action spaces, got "
                    f"(observation shape, action size) {shapes}; pad the observations and add an agent indicator "
                    "(the task builders' agent_indicator=True) or keep one actor per agent"
                )
        actors: dict[str, nn.Module] = {}
        for agent in self.agents[:1] if share_parameters else self.agents:
            box = boxes[agent]
            actors[agent] = agent_actor_class(
                **{
                    **agent_actor_kwargs,
                    "observation_space": box,
                    "action_space": spaces.Box(-1.0, 1.0, (agent_action_dims[agent],), dtype=np.float32),
                    "features_extractor": FlattenExtractor(box),
                    "features_dim": get_flattened_obs_dim(box),
                }
            )
        self.agent_actors = nn.ModuleDict(actors)

    def agent_actor(self, agent: str) -> nn.Module:
        """The network that acts for ``agent``."""
        return self.agent_actors[self.agents[0] if self.share_parameters else agent]

    def forward(self, obs: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        assert isinstance(obs, dict)
        if self.agent_actor_is_stochastic:
            return th.cat([self.agent_actor(agent)(obs[agent], deterministic) for agent in self.agents], dim=1)
        return th.cat([self.agent_actor(agent)(obs[agent]) for agent in self.agents], dim=1)

    @property
    def agent_actor_is_stochastic(self) -> bool:
        return hasattr(self.agent_actor(self.agents[0]), "action_log_prob")

    def action_log_prob(self, obs: PyTorchObs) -> tuple[th.Tensor, th.Tensor]:
        """Joint action and ``log pi(a|o) = sum_m log pi_m(a_m|o_m)`` (SAC family)."""
        assert isinstance(obs, dict)
        pairs = [cast(SACActor, self.agent_actor(agent)).action_log_prob(obs[agent]) for agent in self.agents]
        actions, log_probs = zip(*pairs, strict=True)
        return th.cat(actions, dim=1), th.stack(log_probs, dim=0).sum(dim=0)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        return self(observation, deterministic)


class _CTDEMixin:
    """
    What the CTDE variants of SB3's off-policy policies add to them: per-agent actors (of ``agent_actor_class``)
    and the state-only critic input. Comes first in the bases, before the SB3 policy it extends.
    """

    agent_actor_class: type[BasePolicy]
    actor_kwargs: dict[str, Any]
    observation_space: spaces.Dict
    action_space: spaces.Box
    device: th.device

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        agent_action_dims: dict[str, int] | None = None,
        share_actor: bool = False,
        **kwargs: Any,
    ):
        if agent_action_dims is None:
            raise ValueError("CTDE policies need agent_action_dims (the CTDE algorithms fill it from the CTDEEnv)")
        check_layout(observation_space, action_space, agent_action_dims)
        if kwargs.get("share_features_extractor"):
            raise ValueError(
                "share_features_extractor=True is not possible: the actors read local observations, the critics the state"
            )
        if kwargs.get("use_sde"):
            raise ValueError("use_sde=True is not supported by the CTDE policies")
        kwargs.setdefault("features_extractor_class", StateExtractor)
        self.agent_action_dims = dict(agent_action_dims)
        self.share_actor = share_actor
        super().__init__(observation_space, action_space, lr_schedule, **kwargs)  # type: ignore[call-arg]

    def make_actor(self, features_extractor: BaseFeaturesExtractor | None = None) -> CTDEActor:
        agent_kwargs = {k: v for k, v in self.actor_kwargs.items() if k not in ("observation_space", "action_space")}
        return CTDEActor(
            self.observation_space,
            self.action_space,
            self.agent_action_dims,
            self.agent_actor_class,
            agent_kwargs,
            share_parameters=self.share_actor,
        ).to(self.device)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()  # type: ignore[misc]
        data.update(agent_action_dims=self.agent_action_dims, share_actor=self.share_actor)
        return data


def is_ctde_policy(policy_class: type) -> bool:
    """Whether ``policy_class`` is one of the CTDE policies (it then needs ``agent_action_dims``)."""
    return issubclass(policy_class, _CTDEMixin)


class MASACPolicy(_CTDEMixin, SACPolicy):  # type: ignore[misc]
    """
    SAC's policy for CTDE: per-agent squashed Gaussian actors, twin centralized critics on (state, joint action).

    Takes SB3's ``SACPolicy`` arguments (``net_arch``, ``n_critics``, ...) plus ``agent_action_dims`` (the agents, in
    joint-action order, and their action sizes; filled by the algorithms) and ``share_actor`` (one actor for all).
    """

    agent_actor_class = SACActor


class SERACTDEPolicy(_CTDEMixin, SERAPolicy):  # type: ignore[misc]
    """
    SERASAC's policy for CTDE: per-agent squashed Gaussian actors, the heterogeneous critic ensemble on
    (state, joint action).

    Takes :class:`~sb3_sera.sera.policies.SERAPolicy`'s arguments (``n_critics``, ``critic_archs``, ...) plus
    ``agent_action_dims`` and ``share_actor`` (see :class:`MASACPolicy`).
    """

    agent_actor_class = SACActor


class MATD3Policy(_CTDEMixin, TD3Policy):  # type: ignore[misc]
    """
    TD3's (and DDPG's) policy for CTDE: per-agent deterministic actors, centralized critics on (state, joint action).

    Takes SB3's ``TD3Policy`` arguments plus ``agent_action_dims`` and ``share_actor`` (see :class:`MASACPolicy`).
    """

    agent_actor_class = TD3Actor
