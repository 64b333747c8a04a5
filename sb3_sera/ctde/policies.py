"""
CTDE policies: one actor per agent reading only its own observation, centralized critics on the state and the
joint action (docs/SPEC.md, section 2). The off-policy policies reuse SB3's per-algorithm actors, one per agent.
"""

from typing import Any, cast, overload

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.base_class import BaseAlgorithm, maybe_make_env
from stable_baselines3.common.policies import ActorCriticPolicy, BasePolicy, ContinuousCritic
from stable_baselines3.common.preprocessing import get_flattened_obs_dim
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor, FlattenExtractor, create_mlp
from stable_baselines3.common.type_aliases import GymEnv, PyTorchObs, Schedule
from stable_baselines3.common.vec_env import VecEnv
from stable_baselines3.sac.policies import Actor as SACActor
from stable_baselines3.sac.policies import SACPolicy
from stable_baselines3.td3.policies import Actor as TD3Actor
from stable_baselines3.td3.policies import TD3Policy
from torch import nn

from sb3_sera.common.arguments import check_gymnasium_env
from sb3_sera.common.normalization import CriticNorm
from sb3_sera.common.training_flags import ActorCriticTrainingMode
from sb3_sera.ctde.actors import CTDEActor, StackedCTDEActor, check_shareable
from sb3_sera.ctde.env import STATE_KEY, CTDEEnv


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
        # A new dict: the user's policy_kwargs may serve other models too
        model.policy_kwargs = {**policy_kwargs, "agent_action_dims": agent_action_dims_of(model.env)}


@overload
def make_env_for_policy(
    algorithm_class: type[BaseAlgorithm], policy: str | type[BasePolicy], env: GymEnv | str, verbose: int = 0
) -> GymEnv: ...


@overload
def make_env_for_policy(
    algorithm_class: type[BaseAlgorithm], policy: str | type[BasePolicy], env: None, verbose: int = 0
) -> None: ...


def make_env_for_policy(
    algorithm_class: type[BaseAlgorithm], policy: str | type[BasePolicy], env: GymEnv | str | None, verbose: int = 0
) -> GymEnv | None:
    """
    ``env`` made as SB3 makes it (an id becomes ``gym.make(id, render_mode="rgb_array")``), after checking that it
    is no PettingZoo env (``TypeError`` saying to wrap it in :class:`~sb3_sera.ctde.env.CTDEEnv`) and that a CTDE env
    gets a CTDE policy.

    On a :class:`~sb3_sera.ctde.env.CTDEEnv`, SB3 would answer ``"MlpPolicy"`` with advice to use
    ``"MultiInputPolicy"``, which builds one actor reading every agent's observation and the state: a model that
    trains, but cannot act decentrally. Both raise ``ValueError`` instead, naming ``"CTDEPolicy"``. A CTDEEnv whose
    observation was flattened (``gymnasium.wrappers.FlattenObservation``) is an ordinary env and takes any policy.

    :param algorithm_class: the algorithm being built (its ``policy_aliases`` resolve ``policy``)
    :param policy: the policy alias or class
    :param env: the env, its Gymnasium id, or None
    :param verbose: SB3's verbosity (1 prints that the env is made from its id)
    """
    if env is None:
        return None
    check_gymnasium_env(algorithm_class.__name__, env, multi_agent=True)
    env = maybe_make_env(env, verbose)
    policy_class = algorithm_class.policy_aliases.get(policy) if isinstance(policy, str) else policy
    if policy_class is None or is_ctde_policy(policy_class) or not _gives_ctde_observations(env):
        # An unknown alias gets SB3's own error
        return env
    name = policy if isinstance(policy, str) else policy.__name__
    raise ValueError(
        f"{algorithm_class.__name__} on a CTDE env needs policy='CTDEPolicy' (one actor per agent on its own "
        f"observation, centralized critics on the state), not {name!r}: {name!r} would build one actor that reads every "
        "agent's observation and the state, a model that cannot act decentrally. To train such a centralized policy on "
        "purpose, flatten the observation first (gymnasium.wrappers.FlattenObservation)."
    )


def _gives_ctde_observations(env: GymEnv) -> bool:
    """Whether ``env`` (a Gymnasium env or a VecEnv) is a CTDEEnv whose Dict observations reach the policy."""
    observation_space = env.observation_space
    if not isinstance(observation_space, spaces.Dict) or STATE_KEY not in observation_space.spaces:
        return False
    if isinstance(env, VecEnv):
        try:
            env.get_attr("action_slices", indices=[0])
        except AttributeError:
            return False
        return True
    return isinstance(env.unwrapped, CTDEEnv)


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


def check_policy_arguments(
    observation_space: spaces.Space,
    action_space: spaces.Space,
    agent_action_dims: dict[str, int] | None,
    kwargs: dict[str, Any],
) -> dict[str, int]:
    """The checks every CTDE policy makes of its arguments; returns a copy of ``agent_action_dims``."""
    if agent_action_dims is None:
        raise ValueError("CTDE policies need agent_action_dims (the CTDE algorithms fill it from the CTDEEnv)")
    check_layout(observation_space, action_space, agent_action_dims)
    if kwargs.get("use_sde"):
        raise ValueError("use_sde=True is not supported by the CTDE policies")
    return dict(agent_action_dims)


class CTDEPolicyMixin(ActorCriticTrainingMode):
    """
    What the CTDE variants of SB3's off-policy policies add to them: per-agent actors (of ``agent_actor_class``)
    and the state-only critic input. Comes first in the bases, before the SB3 policy it extends: MASAC's and
    MATD3's here, SERASAC's (:class:`~sb3_sera.sera.policies.SERACTDEPolicy`) and IET's with their algorithms.
    """

    agent_actor_class: type[BasePolicy]
    #: The per-agent actors' container (SB3's SAC and TD3 actors stacked into one network), and the centralized
    #: critics' features
    ctde_actor_class: type[CTDEActor] = StackedCTDEActor
    critic_features_class: type[BaseFeaturesExtractor] = StateExtractor
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
        agent_action_dims = check_policy_arguments(observation_space, action_space, agent_action_dims, kwargs)
        if kwargs.get("share_features_extractor"):
            raise ValueError(
                "share_features_extractor=True is not possible: the actors read local observations, the critics the state"
            )
        kwargs.setdefault("features_extractor_class", self.critic_features_class)
        self.agent_action_dims = agent_action_dims
        self.share_actor = share_actor
        super().__init__(observation_space, action_space, lr_schedule, **kwargs)  # type: ignore[call-arg]

    def agent_actor_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of each agent's actor, but for the spaces and the features extractor."""
        return {k: v for k, v in self.actor_kwargs.items() if k not in ("observation_space", "action_space")}

    def make_actor(self, features_extractor: BaseFeaturesExtractor | None = None) -> CTDEActor:
        return self.ctde_actor_class(
            self.observation_space,
            self.action_space,
            self.agent_action_dims,
            self.agent_actor_class,
            self.agent_actor_kwargs(),
            share_parameters=self.share_actor,
        ).to(self.device)

    def _build(self, lr_schedule: Schedule) -> None:
        super()._build(lr_schedule)  # type: ignore[misc]
        actor = getattr(self, "actor", None)
        if isinstance(actor, StackedCTDEActor):
            # A model saved with one actor per agent loads its actor's Adam state stacked too
            actor.optimizer.register_load_state_dict_pre_hook(actor.stack_optimizer_state)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()  # type: ignore[misc]
        data.update(agent_action_dims=self.agent_action_dims, share_actor=self.share_actor)
        return data


def is_ctde_policy(policy_class: type) -> bool:
    """Whether ``policy_class`` is one of the CTDE policies (it then needs ``agent_action_dims``)."""
    return issubclass(policy_class, (CTDEPolicyMixin, MAPPOPolicy))


class MASACPolicy(CTDEPolicyMixin, SACPolicy):  # type: ignore[misc]
    """
    SAC's policy for CTDE: per-agent squashed Gaussian actors, twin centralized critics on (state, joint action).

    Takes SB3's ``SACPolicy`` arguments (``net_arch``, ``n_critics``, ...) plus ``agent_action_dims`` (the agents, in
    joint-action order, and their action sizes; filled by the algorithms), ``share_actor`` (one actor for all), and
    DroQ's critics as SERASAC takes them: ``layer_norm`` and ``dropout_rate`` (SBX's arguments). CrossQ's
    (``batch_norm``) need critics without target networks, which SB3's SAC step does not have: a ``ValueError``
    says how SERASAC trains MASAC's ensemble with them.
    """

    agent_actor_class = SACActor

    def __init__(
        self,
        *args: Any,
        layer_norm: bool = False,
        dropout_rate: float = 0.0,
        batch_norm: bool = False,
        **kwargs: Any,
    ):
        if batch_norm is not False:
            raise ValueError(
                "MASAC's critics train with target networks (SB3's SAC step); batch_norm=True needs critics without "
                "them. SERASAC trains MASAC's ensemble with CrossQ's critics: SERASAC('CTDEPolicy', env, policy_kwargs="
                "dict(n_critics=2, net_arch=[256, 256], batch_norm=True), target_aggregation='min', "
                "actor_aggregation='min', adaptive_critic_lr=False, disagreement_coef=0)"
            )
        self.critic_norm = CriticNorm(layer_norm=layer_norm, dropout_rate=dropout_rate).checked()
        super().__init__(*args, **kwargs)

    def make_critic(self, features_extractor: BaseFeaturesExtractor | None = None) -> ContinuousCritic:
        """SB3's critics; with DroQ's settings, their Q-networks built again with dropout and LayerNorm."""
        critic = super().make_critic(features_extractor)
        post_linear_modules = self.critic_norm.post_linear_modules
        if not post_linear_modules:
            return critic
        input_dim = next(layer for layer in critic.q_networks[0].modules() if isinstance(layer, nn.Linear)).in_features
        for idx in range(critic.n_critics):
            arch, activation_fn = self.critic_kwargs["net_arch"], self.critic_kwargs["activation_fn"]
            layers = create_mlp(input_dim, 1, arch, activation_fn, post_linear_modules=post_linear_modules)  # type: ignore[arg-type]
            critic.q_networks[idx] = nn.Sequential(*layers).to(self.device)
            critic.add_module(f"qf{idx}", critic.q_networks[idx])
        return critic

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(layer_norm=self.critic_norm.layer_norm, dropout_rate=self.critic_norm.dropout_rate)
        return data


class MATD3Policy(CTDEPolicyMixin, TD3Policy):  # type: ignore[misc]
    """
    TD3's (and DDPG's) policy for CTDE: per-agent deterministic actors, centralized critics on (state, joint action).

    Takes SB3's ``TD3Policy`` arguments plus ``agent_action_dims`` and ``share_actor`` (see :class:`MASACPolicy`).
    """

    agent_actor_class = TD3Actor


class ConcatExtractor(BaseFeaturesExtractor):
    """MAPPO's features: the agents' observations in agent order, then the state, flattened and concatenated."""

    def __init__(self, observation_space: spaces.Dict, agents: list[str]):
        self.keys = [*agents, STATE_KEY]
        self.dims = [get_flattened_obs_dim(observation_space[key]) for key in self.keys]
        super().__init__(observation_space, sum(self.dims))

    def forward(self, observations: dict[str, th.Tensor]) -> th.Tensor:
        return th.cat([th.flatten(observations[key], start_dim=1) for key in self.keys], dim=1)


class GaussianAgentActor(BasePolicy):
    """
    One agent's MAPPO actor: a Gaussian whose mean is an MLP of the agent's observation, with a
    state-independent standard deviation. While training, the joint policy owns the log standard deviations;
    :class:`~sb3_sera.ctde.execution.DecentralizedActors` copies the agent's share into ``log_std``.

    :param observation_space: the agent's observation space
    :param action_space: the agent's action space (actions are clipped to it when executed)
    :param net_arch: hidden layer sizes of the mean network
    :param activation_fn: activation function
    :param normalize_images: SB3's image normalization flag (observations are flat vectors here)
    """

    log_std: th.Tensor

    def __init__(
        self,
        observation_space: spaces.Box,
        action_space: spaces.Box,
        net_arch: list[int],
        activation_fn: type[nn.Module] = nn.Tanh,
        normalize_images: bool = False,
    ):
        super().__init__(
            observation_space,
            action_space,
            features_extractor=FlattenExtractor(observation_space),
            normalize_images=normalize_images,
        )
        self.net_arch = net_arch
        self.activation_fn = activation_fn
        action_dim = int(np.prod(action_space.shape))
        self.mu = nn.Sequential(*create_mlp(get_flattened_obs_dim(observation_space), action_dim, net_arch, activation_fn))
        self.register_buffer("log_std", th.zeros(action_dim))

    def forward(self, obs: th.Tensor, deterministic: bool = False) -> th.Tensor:
        mean = self.mu(self.extract_features(obs, self.features_extractor))
        return mean if deterministic else mean + th.exp(self.log_std) * th.randn_like(mean)

    def _predict(self, observation: PyTorchObs, deterministic: bool = False) -> th.Tensor:
        assert isinstance(observation, th.Tensor)
        return self(observation, deterministic)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(net_arch=self.net_arch, activation_fn=self.activation_fn)
        return data


class CTDEMlpExtractor(nn.Module):
    """
    MAPPO's networks after :class:`ConcatExtractor`: the actor latent is the per-agent Gaussian means (each from
    its agent's observation only), the critic latent an MLP of the state.

    :param observation_space: the CTDE Dict observation space
    :param agent_action_dims: the agents, in joint-action order, and their action sizes
    :param pi_arch: hidden layers of each agent's mean network
    :param vf_arch: hidden layers of the centralized value network
    :param activation_fn: activation function
    :param share_parameters: one mean network for all agents
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        agent_action_dims: dict[str, int],
        pi_arch: list[int],
        vf_arch: list[int],
        activation_fn: type[nn.Module],
        share_parameters: bool = False,
    ):
        super().__init__()
        self.agents = list(agent_action_dims)
        self.share_parameters = share_parameters
        self.obs_dims = [get_flattened_obs_dim(observation_space[agent]) for agent in self.agents]
        state_dim = get_flattened_obs_dim(observation_space[STATE_KEY])
        check_shareable(observation_space, agent_action_dims, share_parameters)
        self.agent_actors = nn.ModuleDict(
            {
                agent: GaussianAgentActor(
                    cast(spaces.Box, observation_space[agent]),
                    spaces.Box(-np.inf, np.inf, (agent_action_dims[agent],), dtype=np.float32),
                    pi_arch,
                    activation_fn,
                )
                for agent in (self.agents[:1] if share_parameters else self.agents)
            }
        )
        self.value_net = nn.Sequential(*create_mlp(state_dim, -1, vf_arch, activation_fn))
        self.latent_dim_pi = sum(agent_action_dims.values())
        self.latent_dim_vf = vf_arch[-1] if vf_arch else state_dim

    def agent_actor(self, agent: str) -> GaussianAgentActor:
        """The network that acts for ``agent``."""
        return cast(GaussianAgentActor, self.agent_actors[self.agents[0] if self.share_parameters else agent])

    def forward(self, features: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        return self.forward_actor(features), self.forward_critic(features)

    def forward_actor(self, features: th.Tensor) -> th.Tensor:
        observations = features[:, : sum(self.obs_dims)].split(self.obs_dims, dim=1)
        return th.cat([self.agent_actor(agent).mu(obs) for agent, obs in zip(self.agents, observations, strict=True)], dim=1)

    def forward_critic(self, features: th.Tensor) -> th.Tensor:
        return self.value_net(features[:, sum(self.obs_dims) :])


class MAPPOPolicy(ActorCriticPolicy):
    """
    PPO's policy for CTDE: per-agent Gaussian actors on local observations and a centralized value V(state).

    Takes SB3's ``ActorCriticPolicy`` arguments (``net_arch`` as ``dict(pi=[...], vf=[...])`` or one list for both,
    ``activation_fn``, ``log_std_init``, ``ortho_init``, ...) plus ``agent_action_dims`` (the agents, in
    joint-action order, and their action sizes; filled by the algorithm) and ``share_actor`` (one actor for all).
    """

    mlp_extractor: CTDEMlpExtractor  # type: ignore[assignment]

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        agent_action_dims: dict[str, int] | None = None,
        share_actor: bool = False,
        **kwargs: Any,
    ):
        agent_action_dims = check_policy_arguments(observation_space, action_space, agent_action_dims, kwargs)
        if kwargs.get("share_features_extractor") is False:
            raise ValueError("share_features_extractor=False is not supported by MAPPOPolicy")
        self.agent_action_dims = agent_action_dims
        self.share_actor = share_actor
        kwargs["features_extractor_class"] = ConcatExtractor
        kwargs["features_extractor_kwargs"] = {"agents": list(agent_action_dims)}
        super().__init__(observation_space, action_space, lr_schedule, **kwargs)

    def _build_mlp_extractor(self) -> None:
        if isinstance(self.net_arch, dict):
            pi_arch, vf_arch = self.net_arch.get("pi", []), self.net_arch.get("vf", [])
        else:
            pi_arch = vf_arch = list(self.net_arch)
        self.mlp_extractor = CTDEMlpExtractor(
            self.observation_space,  # type: ignore[arg-type]
            self.agent_action_dims,
            pi_arch,
            vf_arch,
            self.activation_fn,
            share_parameters=self.share_actor,
        ).to(self.device)

    def _build(self, lr_schedule: Schedule) -> None:
        super()._build(lr_schedule)
        # The agents' mean networks already output the joint mean: no mixing layer after them
        self.action_net = nn.Identity()
        if self.ortho_init:
            for agent in self.mlp_extractor.agents:
                self.init_weights(self.mlp_extractor.agent_actor(agent).mu[-1], gain=0.01)
        self.optimizer = self.optimizer_class(self.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs)  # type: ignore[call-arg]

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        for key in ("features_extractor_class", "features_extractor_kwargs"):
            data.pop(key, None)
        data.update(agent_action_dims=self.agent_action_dims, share_actor=self.share_actor)
        return data
