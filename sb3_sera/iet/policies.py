"""
IET's policy (docs/SPEC.md, section 4, our adaptation): MASAC's CTDE policy whose per-agent actors are soft-modular
networks conditioned on the agent's per-episode latent, with centralized critics that read the state and every
agent's latent.
"""

from typing import Any, cast

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.preprocessing import get_flattened_obs_dim
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.type_aliases import PyTorchObs, Schedule
from stable_baselines3.sac.policies import Actor as SACActor
from stable_baselines3.sac.policies import SACPolicy
from torch import nn

from sb3_sera.ctde.env import STATE_KEY
from sb3_sera.ctde.execution import register_actor_kind
from sb3_sera.ctde.policies import CTDEActor, CTDEPolicyMixin
from sb3_sera.iet.latents import LATENT_KEY, draw_latents
from sb3_sera.iet.networks import SoftModularNetwork


def check_latent_entry(observation_space: spaces.Space) -> int:
    """Raise ``ValueError`` unless the observations hold the agents' latents; return the latent size."""
    if not isinstance(observation_space, spaces.Dict) or LATENT_KEY not in observation_space.spaces:
        raise ValueError(
            f"IETPolicy reads the agents' latents from the {LATENT_KEY!r} entry of the observations, which IET adds "
            f"to its CTDE env: build it with IET('CTDEPolicy', env), got observation space {observation_space}"
        )
    shape = observation_space[LATENT_KEY].shape
    assert shape is not None and len(shape) == 2, f"the latents are (n_agents, latent_dim), got shape {shape}"
    return int(shape[1])


class StateLatentExtractor(BaseFeaturesExtractor):
    """IET's centralized critics' features: the ``state`` and every agent's latent, flattened and concatenated."""

    def __init__(self, observation_space: spaces.Dict):
        dims = [get_flattened_obs_dim(observation_space[key]) for key in (STATE_KEY, LATENT_KEY)]
        super().__init__(observation_space, sum(dims))

    def forward(self, observations: dict[str, th.Tensor]) -> th.Tensor:
        return th.cat([th.flatten(observations[key], start_dim=1) for key in (STATE_KEY, LATENT_KEY)], dim=1)


class IETAgentActor(SACActor):
    """
    One agent's IET actor: SB3's SAC actor (squashed Gaussian, no gSDE) whose hidden layers are a
    :class:`~sb3_sera.iet.networks.SoftModularNetwork` reading the agent's observation followed by its latent.

    :param observation_space: the actor's input space: the agent's observation and its latent, one flat ``Box``
    :param action_space: the agent's action space (``[-1, 1]``)
    :param features_extractor: the flattening of the input
    :param features_dim: the input's size
    :param latent_dim: size of the latent, the input's last entries
    :param hidden_dim: width of the soft-modular network
    :param n_layers: module layers (at least 2)
    :param n_modules: modules per layer
    :param n_gating_layers: layers between the latent and the routing
    :param normalize_images: SB3's image normalization flag (inputs are flat vectors here)
    """

    def __init__(
        self,
        observation_space: spaces.Box,
        action_space: spaces.Box,
        features_extractor: nn.Module,
        features_dim: int,
        latent_dim: int,
        hidden_dim: int = 64,
        n_layers: int = 2,
        n_modules: int = 2,
        n_gating_layers: int = 2,
        normalize_images: bool = True,
    ):
        # SAC's actor, its hidden layers then replaced: mu and log_std read the soft-modular network's hidden_dim outputs
        super().__init__(
            observation_space,
            action_space,
            net_arch=[hidden_dim],
            features_extractor=features_extractor,
            features_dim=features_dim,
            normalize_images=normalize_images,
        )
        self.latent_dim = latent_dim
        self.modular_kwargs = dict(
            hidden_dim=hidden_dim, n_layers=n_layers, n_modules=n_modules, n_gating_layers=n_gating_layers
        )
        self.latent_pi = SoftModularNetwork(features_dim - latent_dim, latent_dim, **self.modular_kwargs)  # type: ignore[assignment]

    @property
    def modular_network(self) -> SoftModularNetwork:
        return cast(SoftModularNetwork, self.latent_pi)

    def draw_latent(self, rng: np.random.Generator) -> np.ndarray:
        """A new latent of the agent's next episode, as training draws them (:func:`~sb3_sera.iet.latents.draw_latents`)."""
        return draw_latents(rng, 1, 1, self.latent_dim)[0, 0]

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        for key in ("net_arch", "activation_fn", "use_sde", "log_std_init", "full_std", "use_expln", "clip_mean"):
            data.pop(key)
        data.update(latent_dim=self.latent_dim, **self.modular_kwargs)
        return data


class IETActor(CTDEActor):
    """
    The agents' IET actors: agent ``i``'s actor reads its own observation and row ``i`` of the ``"latent"`` entry.
    Takes :class:`~sb3_sera.ctde.actors.CTDEActor`'s arguments.
    """

    def agent_input_space(self, observation_space: spaces.Dict, agent: str) -> spaces.Box:
        size = get_flattened_obs_dim(observation_space[agent]) + check_latent_entry(observation_space)
        return spaces.Box(-np.inf, np.inf, (size,), dtype=np.float32)

    def agent_input(self, obs: dict[str, th.Tensor], agent: str) -> th.Tensor:
        latent = obs[LATENT_KEY][:, self.agents.index(agent)]
        return th.cat([th.flatten(obs[agent], start_dim=1), latent], dim=1)

    def routing(self, obs: dict[str, th.Tensor]) -> tuple[th.Tensor, th.Tensor]:
        """
        Every agent's routing on a batch of observations: the mixing matrices ``(n_agents, n_layers - 1, batch, M, M)``
        and the final weights ``(n_agents, batch, M)`` (see :meth:`.SoftModularNetwork.routing`).
        """
        matrices, finals = [], []
        for agent in self.agents:
            network = cast(IETAgentActor, self.agent_actor(agent)).modular_network
            layer_matrices, final, _ = network.routing(self.agent_input(obs, agent))
            matrices.append(th.stack(layer_matrices))
            finals.append(final)
        return th.stack(matrices), th.stack(finals)


class IETPolicy(CTDEPolicyMixin, SACPolicy):  # type: ignore[misc]
    """
    IET's policy on a CTDE task: per-agent squashed Gaussian actors whose hidden layers are soft-modular networks
    driven by the agent's per-episode latent, and twin centralized critics on (state, every latent, joint action).

    Takes SB3's ``SACPolicy`` arguments (``net_arch`` sizes the critics; the actors are sized by the soft-modular
    arguments) plus ``agent_action_dims`` and ``share_actor`` (see :class:`~sb3_sera.ctde.policies.MASACPolicy`) and

    :param hidden_dim: width of each actor's soft-modular network (the authors' 64)
    :param n_layers: its module layers, at least 2 (the authors' 2)
    :param n_modules: its modules per layer (the authors' 2)
    :param n_gating_layers: its layers between the latent and the routing (the authors' 2)

    The observations hold the agents' latents under ``"latent"``; :meth:`predict` draws them for observations
    without it.
    """

    agent_actor_class = IETAgentActor
    ctde_actor_class = IETActor
    critic_features_class = StateLatentExtractor

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        lr_schedule: Schedule,
        agent_action_dims: dict[str, int] | None = None,
        share_actor: bool = False,
        hidden_dim: int = 64,
        n_layers: int = 2,
        n_modules: int = 2,
        n_gating_layers: int = 2,
        **kwargs: Any,
    ):
        self.latent_dim = check_latent_entry(observation_space)
        net_arch = kwargs.get("net_arch")
        if isinstance(net_arch, dict) and "pi" in net_arch:
            raise ValueError(
                "IETPolicy's actors are soft-modular networks sized by hidden_dim, n_layers, n_modules and "
                f"n_gating_layers: net_arch sizes the critics only (a list, or dict(qf=[...])), got {net_arch}"
            )
        self.modular_kwargs = dict(
            hidden_dim=hidden_dim, n_layers=n_layers, n_modules=n_modules, n_gating_layers=n_gating_layers
        )
        super().__init__(observation_space, action_space, lr_schedule, agent_action_dims, share_actor, **kwargs)

    def agent_actor_kwargs(self) -> dict[str, Any]:
        return {"latent_dim": self.latent_dim, "normalize_images": self.normalize_images, **self.modular_kwargs}

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(self.modular_kwargs)
        return data

    def predict(
        self,
        observation: np.ndarray | dict[str, np.ndarray],
        state: tuple[np.ndarray, ...] | None = None,
        episode_start: np.ndarray | None = None,
        deterministic: bool = False,
    ) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        """
        SB3's ``predict``. Observations with a ``"latent"`` entry (those of the env IET trains on) act with their
        latents. For observations without one (a CTDE env IET did not wrap, e.g. an evaluation env) the latents are
        the policy's state, as a recurrent policy's hidden state: drawn from ``N(0, I)`` when ``state`` is None and
        for the envs whose ``episode_start`` is True, kept otherwise, and returned as ``(latents,)`` to pass back
        (``evaluate_policy`` does).

        :return: the actions and the next state (``(latents,)``, shape ``(n_envs, n_agents, latent_dim)``, or the
            given ``state`` when the observations held the latents)
        """
        if not isinstance(observation, dict) or LATENT_KEY in observation:
            return super().predict(observation, state, episode_start, deterministic)
        state_shape = self.observation_space[STATE_KEY].shape
        assert state_shape is not None
        env_state = np.asarray(observation[STATE_KEY])
        vectorized = env_state.ndim > len(state_shape)
        latents = self.next_latents(env_state.shape[0] if vectorized else 1, state, episode_start)
        with_latents = {**observation, LATENT_KEY: latents if vectorized else latents[0]}
        actions, _ = super().predict(with_latents, None, None, deterministic)
        return actions, (latents,)

    def next_latents(self, n_envs: int, state: tuple[np.ndarray, ...] | None, episode_start: np.ndarray | None) -> np.ndarray:
        """The latents to act with: ``state``'s, drawn anew where there are none or an episode starts."""
        n_agents = len(self.agent_action_dims)
        shape = (n_envs, n_agents, self.latent_dim)
        # Drawn as training draws them, from a generator seeded by torch's global one (as SB3's predict samples)
        rng = np.random.default_rng(int(th.randint(0, 2**62, (1,)).item()))
        if state is None:
            return draw_latents(rng, n_envs, n_agents, self.latent_dim)
        latents = np.array(state[0], dtype=np.float32)
        if latents.shape != shape:
            raise ValueError(f"IET's state is the agents' latents, shape {shape} for these observations, got {latents.shape}")
        if episode_start is not None:
            starts = np.asarray(episode_start, dtype=bool).reshape(n_envs)
            latents[starts] = draw_latents(rng, int(starts.sum()), n_agents, self.latent_dim)
        return latents

    def routing(self, obs: PyTorchObs) -> tuple[th.Tensor, th.Tensor]:
        """The actors' routing on a batch of observations with latents (see :meth:`IETActor.routing`)."""
        assert isinstance(obs, dict)
        return cast(IETActor, self.actor).routing(obs)


# Decentralized controllers save and load IET's agents' actors
register_actor_kind("iet", IETAgentActor)
